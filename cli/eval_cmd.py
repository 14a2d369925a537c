"""`mpnode eval MODEL DATA` and `mpnode simulate MODEL SCENE`: use a trained model."""
import json
import math
import os
from dataclasses import dataclass

import click

from mpnode.base.errors import InputError, NumericalError

from .main import claim_outputs, main


class SubstepsType(click.ParamType):
    """``--substeps``: a positive integer or ``auto``."""

    name = "N|auto"

    def convert(self, value, param, ctx):
        if isinstance(value, int) or value == "auto":
            return value
        text = str(value).strip().lower()
        if text == "auto":
            return "auto"
        try:
            n = int(text)
        except ValueError:
            self.fail(f"{value!r} is neither a positive integer nor 'auto'", param, ctx)
        if n < 1:
            self.fail(f"{n} is not >= 1", param, ctx)
        return n


SUBSTEPS_HELP = ("RK4 steps per dt: a number, or 'auto' -- the smallest s in 1, 2, 4, ..., --max-substeps whose "
                 "step-doubling estimate (max |x_s - x_2s| over the first 20 steps of up to 32 trajectories, in "
                 "units of the training data's std) is <= --substeps-tol.  Default: the model's own.")


def substeps_options(f):
    """--substeps, --substeps-tol and --max-substeps (eval and simulate)."""
    from mpnode.evaluation.stepsize import DEFAULT_MAX_SUBSTEPS, DEFAULT_TOL

    options = [
        click.option("--substeps", type=SubstepsType(), help=SUBSTEPS_HELP),
        click.option("--substeps-tol", type=click.FloatRange(min=0, min_open=True), default=DEFAULT_TOL,
                     show_default=True, help="Tolerance of --substeps auto, in normalised units (the training "
                     "data's std per dimension)."),
        click.option("--max-substeps", type=click.IntRange(min=1), default=DEFAULT_MAX_SUBSTEPS, show_default=True,
                     help="Largest substep count auto tries (and the stability check re-rolls with)."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def format_substeps(substeps, auto_report, stability):
    """Lines about the RK4 substeps: auto's choice, the step-doubling estimate, step-too-large."""
    lines = []
    if auto_report is not None:
        est = ", ".join(f"{k}: {_g(v)}" for k, v in auto_report["estimates"].items())
        verdict = "reached" if auto_report["reached"] else "NOT reached"
        lines.append(f"  substeps: auto chose {substeps} (tolerance {auto_report['tol']:g} {verdict}; step-doubling "
                     f"estimates by substeps {est})")
        if not auto_report["reached"]:
            lines.append(f"  warning: {auto_report['message']}")
    else:
        lines.append(f"  substeps: {substeps}" + (f" (step-doubling error estimate {_g(stability['estimate'])})"
                                                   if stability else ""))
    if stability and stability.get("message"):
        lines.append(("  WARNING: " if stability["step_too_large"] else "  note: ") + stability["message"])
    return lines


def plot_option(what):
    """--plot OUT.png for a command whose figure shows ``what``."""
    return click.option("--plot", type=click.Path(dir_okay=False), metavar="OUT.png",
                        help=f"Also draw {what} to this image file (.png, .pdf, .svg; atomic).  Needs the plot "
                             "extra: pip install 'mpnode[plot]'; without it the command stops before any work.")


def check_plot(plot):
    """Before any work: a figure can be written to ``plot`` (matplotlib installed, a figure format)."""
    if plot:
        from mpnode.plot import check_output

        check_output(plot)


#: --start (eval, and simulate from a trajectory file)
start_option = click.option(
    "--start", type=click.Choice(["encoder", "fit"]), default="encoder", show_default=True,
    help="How the warm-up gives each prediction its start: the model's initial-state estimate (its encoder, or "
         "the first observation), or that estimate fitted to the warm-up's observations through the model (a few "
         "hundred short rollouts).")


def evaluate_and_report(model, traj, source, allow_dt=False, reference_sample=20, substeps=None,
                        substeps_tol=None, max_substeps=None, warmup=0, truth=None, start="encoder", ignore_attrs=False):
    """Evaluate, and time the reference simulator beside the model when the file names one:
    returns (EvalResult, report dict)."""
    from data_gen.invariants import invariant_of
    from data_gen.reference import speed_against_reference
    from data_gen.systems import node_view
    from mpnode.evaluation import stepsize
    from mpnode.evaluation.evaluate import evaluate
    from mpnode.plot import dimension_names

    invariant = invariant_of(traj)
    node_dims, node_names = node_view(traj)
    result = evaluate(model, traj, source=source, allow_dt_mismatch=allow_dt, substeps=substeps,
                      substeps_tol=substeps_tol or stepsize.DEFAULT_TOL,
                      max_substeps=max_substeps or stepsize.DEFAULT_MAX_SUBSTEPS, warmup=warmup, truth=truth,
                      start=start, invariant=invariant and invariant[1], ignore_attrs=ignore_attrs,
                      state_names=dimension_names(model.fitted(traj).attrs, model.spec.state_dim),
                      node_dims=node_dims, node_names=node_names)
    report = {"data": source, **result.summary(), "state_names": traj.attrs.get("state_names"),
              **({"invariant": invariant[0]} if invariant else {})}
    if reference_sample > 0 and traj.regular:
        report["reference"] = speed_against_reference(model, traj, result, reference_sample)
    return result, report


def _g(v):
    return str(v) if isinstance(v, str) else f"{v:.3g}"


def report_steps(horizon):
    """The steps the report shows: 1, T/10, T/5, 2T/5 and T (1, 5, 10, 20, 50 for T = 50)."""
    return sorted({1, *(max(1, horizon * k // 10) for k in (1, 2, 4)), horizon})


def _at(per_step, steps):
    return ", ".join(f"{s}: {_g(per_step[s])}" for s in steps)


def _against_hold(r, steps):
    """The lines comparing the model with holding the initial state, overall and per state group."""
    hold, first = r["hold"], r["hold"]["first_step_not_below"]
    verdict = "below it at every step" if first is None else f"at or above it first at step {first}"
    lines = [f"  holding the initial state: mean {_g(hold['nmse'])}; per step: {_at(hold['nmse_per_step'], steps)} "
             f"(the model is {verdict})"]
    if r["groups"]:
        lines.append(f"  by state group (file attribute state_groups): mean over steps {steps[0]}..{r['horizon']} "
                     "[holding the initial state]; per step")
        width = max(map(len, r["groups"]))
        for name, g in r["groups"].items():
            above = g["first_step_not_below_hold"]
            flag = "" if above is None else f"  (at or above holding first at step {above})"
            lines.append(f"    {name:<{width}} {_g(g['nmse'])} [{_g(g['hold_nmse'])}]; "
                         f"{_at(g['nmse_per_step'], steps)}{flag}")
    return lines


def format_report(report, model_name):
    """The human-readable evaluation report (several lines)."""
    r = report
    lines = [f"{model_name} on {r['data']}: B={r['trajectories']}, T={r['horizon']}, N={r['nodes']}"]
    t = r["horizon"]
    first = max(1, r.get("warmup", 0))
    steps = sorted({max(first, s) for s in report_steps(t)})
    if r.get("warmup"):
        lines.append(f"  warm-up: each prediction starts from the first {r['warmup']} observations; scored after them")
    lines.append(f"  normalised MSE, mean over steps {first}..{t}: {_g(r['nmse'])}   last step: {_g(r['nmse_last'])}")
    if len(r.get("nmse_per_dim", [])) > 1:
        names = r.get("state_names") or [f"x[{k}]" for k in range(len(r["nmse_per_dim"]))]
        lines.append("  per dimension: " + ", ".join(f"{n}: {_g(v)}" for n, v in zip(names, r["nmse_per_dim"]))
                     + (f" (dimension(s) {r['hidden_dims']} never measured in training: not scored)"
                        if r.get("hidden_dims") else ""))
    lines.append("  per step: " + _at(r["nmse_per_step"], steps))
    lines += format_nodes(r)
    lines += _against_hold(r, steps)
    lines += format_trust(r)
    if r["first_bad_step"] is None:
        lines.append("  blow-ups: none (every prediction finite and inside 10x the data's range)")
    else:
        lines.append(f"  blow-ups: {r['blown_up_trajectories']} trajectories; the first at step {r['first_bad_step']}")
    hz = r.get("predictable_horizon")
    if hz:
        parts = []
        for thr, h in hz.items():
            if h["median_step"] is None:
                parts.append(f"nmse > {thr}: beyond step {t} for most ({h['beyond_horizon']} of {r['trajectories']})")
            else:
                when = f" (t = {h['median_time']:.4g})" if h["median_time"] is not None else ""
                parts.append(f"nmse > {thr} at step {h['median_step']}{when}")
        lines.append("  predictable horizon (median over trajectories of the first step whose error exceeds): "
                     + "; ".join(parts))
    if r.get("coverage_90") is not None:
        lines += format_spread(r)
    if "substeps" in r:
        lines += format_substeps(r["substeps"], r.get("substeps_auto"), r.get("stability"))
    lines.append(f"  learned rollout: {r['rollout_seconds']:.3g} s for {r['trajectories']} trajectories "
                 f"({r['node_steps_per_second']:.3g} node-steps/s)")
    ref = r.get("reference")
    if ref:
        lines += format_reference(ref)
    elif "reference" in r:
        lines.append("  reference: the file names no system data_gen can rebuild; not timed")
    return "\n".join(lines)


def format_nodes(r):
    """The lines on where on the network the error lies: the median node and the worst ones, by their
    error on the watched dimensions (mpnode.evaluation.nodes)."""
    v = r.get("per_node")
    if not v or v["median"] is None:
        return []
    names = r.get("state_names") or [f"x[{k}]" for k in range(len(v["nmse_per_dim"][0]))]
    which = ("the whole state" if len(v["dims"]) == len(v["nmse_per_dim"][0])
             else ", ".join(str(names[d]) if d < len(names) else f"x[{d}]" for d in v["dims"]))
    on = (f"all {v['trajectories']} trajectories" if v["all_trajectories"]
          else f"{v['trajectories']} of the {r['trajectories']} trajectories, the others on other graphs")

    def node(e):
        label = e["name"] if e["name"] == f"node {e['node']}" else f"{e['name']} (node {e['node']})"
        return f"{label} {_g(e['nmse'])}, {_g(e['rmse'])}"

    return [f"  per node, by {which} (graph {v['graph']}, {on}; nMSE, RMS error in the data's units): "
            f"median {node(v['median'])}",
            "    worst: " + "; ".join(node(e) for e in v["worst"])]


def format_spread(r):
    """An ensemble's lines: how often the truth lies inside its bands, the error it expects, and
    whether its spread ranks the trajectories' errors."""
    names = r.get("state_names") or [f"x[{k}]" for k in range(len(r["spread_per_dim"]))]
    return [(f"  ensemble: the truth inside the central 50% band {_pct(r['coverage_50'])} of the time, inside the "
             f"90% band {_pct(r['coverage_90'])} (steps 1..{r['horizon']}, all nodes and dimensions)"),
            "  spread (calibrated std, mean over trajectories, steps and nodes): "
            + ", ".join(f"{n}: {_g(v)}" for n, v in zip(names, r["spread_per_dim"]))
            + f"; as a normalised MSE {_g(r['spread_nmse'])} (the error it expects; measured: {_g(r['nmse'])})",
            f"  spread against error across trajectories: Spearman {_g(r['spread_error_spearman'])}"]


def _pct(v):
    return v if isinstance(v, str) else f"{100 * v:.1f}%"


def format_trust(r):
    """The report's lines on how far to trust the error: by block of steps, off the training range,
    the invariant's drift."""
    blocks = r.get("nmse_by_block") or []
    lines = ["  error against horizon (nMSE by block of steps): " + ", ".join(
        f"{b['steps'][0]}-{b['steps'][1]}: {_g(b['value']) if b['value'] is not None else '-'}" for b in blocks)]
    drift = r.get("invariant_drift_by_block")
    if drift:
        lines.append(f"  drift of the {r['invariant']} (|I(t) - I(0)| / |I(0)|, mean over trajectories; the truth's "
                     "in brackets): " + ", ".join(f"{b['steps'][0]}-{b['steps'][1]}: {_g(b['value'])} "
                                                  f"[{_g(b['truth']) if b['truth'] is not None else '-'}]" for b in drift
                                                  if b["value"] is not None))
    if not r.get("training_ranges_recorded", True):
        lines.append("  off the training range: not checked (the model file records no training ranges; "
                     "`mpnode finetune` with --epochs 1 records them)")
    elif not r.get("off_range"):
        lines.append("  off the training range: no input left the range seen in training")
    else:
        lines.append(f"  OFF THE TRAINING RANGE ({len(r['off_range'])} quantities; expect larger errors):")
        lines += [f"    {e['message']}" for e in r["off_range"]]
    return lines


def format_reference(ref):
    """The reference's lines of the report: which setting reaches the model's error at the least
    cost (data_gen.reference), what else was tried, and which of the two is faster."""
    def ms(seconds):
        return f"{seconds * 1e3:.3g} ms"

    k = ref["sample"]
    which = ("the cheapest setting that reaches" if ref["reached"]
             else "no setting tried reaches; the most accurate of them, against")
    tried = "; ".join(f"{t['setting']}: nMSE {_g(t['nmse'])} in {ms(t['seconds_per_trajectory'])}" for t in ref["tried"])
    speed = ref["speedup"]
    verdict = (f"the learned model is {speed:.3g}x faster" if speed >= 1 else
               f"the learned model is {1 / speed:.3g}x SLOWER: at this error, integrating the true equations is cheaper")
    chosen = (f"  reference: the true {ref['system']} equations, {which} the model's normalised MSE on the same {k} "
              f"trajectories ({_g(ref['target_nmse'])}): {ref['integrator']}, "
              f"{ms(ref['reference_seconds_per_trajectory'])} per trajectory (nMSE {_g(ref['reference_nmse_vs_file'])})")
    speed_line = (f"  speed against error: learned {ms(ref['learned_seconds_per_trajectory'])} per trajectory (the same "
                  f"{k} as one batch; {ms(ref['learned_seconds_per_trajectory_full_batch'])} in the full batch) vs "
                  f"reference {ms(ref['reference_seconds_per_trajectory'])}: {verdict}")
    return [chosen, f"    tried, each family cheapest first: {tried}", speed_line]


@main.command("eval")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--predictions", type=click.Path(dir_okay=False),
              help="Write the predicted trajectories here (trajectory format, same graphs; atomic).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
@click.option("--allow-dt-mismatch", is_flag=True,
              help="Roll the model out with the file's dt even if it was trained with another.")
@click.option("--ignore-attrs", is_flag=True,
              help="Leave out DATA's node attributes and edge weights when MODEL was trained without them.")
@click.option("--reference-sample", type=click.IntRange(min=0), default=20, show_default=True,
              help="Trajectories the reference simulator is timed on (0: skip the reference).")
@click.option("--warmup", type=click.IntRange(min=0), default=0, show_default=True, metavar="K",
              help="Let the model see the first K observations of each trajectory before it predicts: a "
                   "model with an initial-state encoder estimates from them what was not measured and what "
                   "noise hides; the error counts the observations after them.")
@start_option
@click.option("--truth", type=click.Path(dir_okay=False), metavar="CLEAN.h5",
              help="Score against the clean states of the same trajectories in this file (DATA noisy); "
                   "default: DATA's own clean truth if it keeps one (mpnode generate --noise), else its "
                   "observations.")
@plot_option("truth against prediction for the first trajectories and nodes, per state dimension, and the "
             "error over time with the predictable horizon; of a network of 3 nodes or more, the network coloured by "
             "each node's error and the worst and the median node over time")
@substeps_options
def eval_cmd(model_file, data, predictions, as_json, allow_dt_mismatch, ignore_attrs, reference_sample, warmup, start,
             truth, plot, substeps, substeps_tol, max_substeps):
    """Roll MODEL out from every initial state of DATA and report error and speed.

    Error: normalised MSE (squared error / per-dimension variance of DATA's true
    states) per step and averaged over steps 1..T, the last step's, and the first
    step where a prediction became non-finite or left ten times the data's range.
    Beside it, holding every state at its initial value and the first step the model is not
    below that; each state group's error when DATA names groups (attribute state_groups).
    Predictable horizon: per trajectory the first step whose normalised MSE exceeds
    0.1 and 1.0, reported as the median over trajectories (in steps and time).
    Speed: rollout wall time and node-steps per second.  Speed against error, when DATA
    names a reference system that data_gen can rebuild from the file's parameters: on
    the first --reference-sample initial states, the true equations at the cheapest
    setting whose nMSE against DATA is no larger than the model's -- the file's scipy
    integrator at looser tolerances (1e-3, 1e-4, ... down to the file's own), or classic
    RK4 with 1, 2, 4, ... steps per dt over the sampled trajectories as one batch,
    whichever is faster -- timed beside the learned rollout of the same states; the
    report says which setting, what was tried, and whether the model is faster or slower.
    A MODEL trained on another system than DATA's is evaluated, with a warning.

    Where on the network: each node's error over the trajectories on the graph most of
    them run on (all when they share one; with a graph each, the first trajectory's), on
    the state dimensions a user of DATA's system watches node by node (a power grid's
    frequency deviation, bus by bus; else the whole state): the median node and the five
    worst, as nMSE and as RMS error in the data's units (--json: per_node, every node's).

    How far to trust the error: the nMSE by block of steps (error against horizon;
    --json: nmse_by_block); the inputs of the model's rollouts that leave the ranges it
    saw in training (the states per dimension, the in-degree, each aggregate input, the
    number of nodes; beyond a margin of 25% of the seen width), one warning per quantity
    on standard error and in the report, naming the value, the bound, by how much and
    where (--json: off_range, [] when none left); and, for data whose system conserves a
    quantity (data_gen names it: the coupled pendulum's energy), its drift along the
    predictions beside the truth's (--json: invariant_drift_by_block).

    An ensemble MODEL (train --ensemble K): the error is the members' mean's; the report
    adds the spread (the members' std times the scale fitted on validation data at
    training time) per dimension (--json: spread_per_node, N x dx), the fraction of true
    values inside the central 50% and 90% bands mean +- 0.674 / 1.645 spread over steps
    1..T, all nodes and dimensions (coverage_50, coverage_90; null for one model), and the
    Spearman correlation of each trajectory's spread with its error.  --predictions then
    holds the mean as x and the spread as x_std; --plot shades the 90% band.

    Substeps: --substeps auto picks the RK4 substeps per dt by step doubling (the
    difference of the rollouts with s and 2s substeps estimates the error of s;
    the smallest s = 1, 2, 4, ... under --substeps-tol wins).  When predictions blow
    up but do not with more substeps, the report says the RK4 step is too large and
    suggests --substeps N (--json: step_too_large, suggested_substeps).

    Exit status: 0 (also when the step is too large: see the report); 2 bad input
    (missing file, dx/du or dt mismatch, an output being written by another run); 3
    predictions non-finite and --predictions given (nothing written); 4 the system
    refused (an output could not be written: permission, full disk, read-only folder;
    nothing is left behind).
    """
    from mpnode.base.atomic import check_outputs
    from mpnode.data import read_trajectories
    from mpnode.model import Model
    from mpnode.model.provenance import system_mismatch

    check_plot(plot)
    outputs = {k: v for k, v in (("--predictions", predictions), ("--plot", plot)) if v}
    check_outputs(outputs, [model_file, data] + ([truth] if truth else []))
    claim_outputs(outputs)
    model = Model.load(model_file)
    traj = read_trajectories(data)
    clean = None if truth is None else read_trajectories(truth).x
    warning = system_mismatch(model, traj.system, data)
    if warning:
        click.echo(f"warning: {warning}", err=True)
    result, report = evaluate_and_report(model, traj, data, allow_dt_mismatch, reference_sample, substeps,
                                         substeps_tol, max_substeps, warmup, clean, start, ignore_attrs)
    report["model"] = model_file
    report["warnings"] = ([warning] if warning else []) + warn_off_range(report["off_range"])
    click.echo(json.dumps(report, indent=2, allow_nan=False) if as_json else format_report(report, model_file))
    _write_eval_outputs(result, traj, data, model_file, plot, predictions, as_json)


def _write_eval_outputs(result, traj, data, model_file, plot, predictions, as_json):
    """`eval`'s figure, then its predictions file (which refuses non-finite predictions: a blow-up
    gets its figure first); each named once written unless the output is JSON."""
    if plot:
        from mpnode.plot import plot_eval

        plot_eval(traj, result, plot, title=f"{os.path.basename(model_file)} on {os.path.basename(data)}")
        if not as_json:
            click.echo(f"wrote {plot}")
    if predictions:
        write_predictions(predictions, result, traj, data, model_file)
        if not as_json:
            click.echo(f"wrote {predictions}")


def _scene_start(model, model_file, scene, s, system):
    """(x0, graphs, graph_index, controls or None) to simulate ``model`` on the scene ``s`` of
    ``system``: InputError unless the model fits (dx, du, N; a closed loop: dt)."""
    from data_gen import closed_loop_start, initial_states

    if system.state_dim != model.spec.state_dim:
        raise InputError(scene, "system", f"{s.system} has {system.state_dim} state dimensions per node but the "
                         f"model has {model.spec.state_dim}", "a scene of the system the model learned")
    if user_controls(model) != system.control_dim:
        raise InputError(model_file, "control_dim", f"the model takes {user_controls(model)} controls per node "
                         f"but {s.system} has {system.control_dim}", "a model of the scene's system")
    model.check_nodes(s.graph.n_nodes, scene, "graph.nodes")
    if system.controllers is None:
        return (*initial_states(s), None)
    if not math.isclose(model.spec.dt, s.dt, rel_tol=1e-9):
        raise InputError(scene, "dt", f"the scene's controllers run every {s.dt:g} but the model steps {model.spec.dt:g}",
                         "a model trained at the scene's dt")
    return closed_loop_start(s)


def write_predictions(path, result, traj, data, model_file):
    """The predictions file of `eval`: the prediction (an ensemble's mean) as x, an ensemble's
    spread as x_std, on the data's graphs (their weights), times, controls and node attributes
    (not the controls the model heard them as); nothing written if one is non-finite."""
    from mpnode.data import write_trajectories
    from mpnode.evaluation.evaluate import predictions_file, substeps_attrs

    attrs = {"predicted_from": os.path.abspath(data), **substeps_attrs(result.substeps, result.substeps_report),
             **{k: traj.attrs[k] for k in ("state_names", "state_groups") if k in traj.attrs}}
    pred = result.predictions[..., :traj.state_dim]  # a model's latent dimensions stay its own
    spread = None if result.spread is None else result.spread[..., :traj.state_dim]
    pf = _or_why(lambda: predictions_file(pred, traj.graphs, traj.graph_index, traj.dt, traj.system,
                                          os.path.abspath(model_file), traj.u, attrs, traj.t, spread,
                                          traj.node_attrs, traj.attr_names), result.stability)
    write_trajectories(path, pf)


def warn_off_range(entries):
    """Each input off the training range as a warning on standard error; returns the warnings."""
    lines = [f"off the training range: {e['message']}" for e in entries]
    for line in lines:
        click.echo(f"warning: {line}", err=True)
    return lines


def _or_why(make, stability):
    """make(); a NumericalError (non-finite predictions) carries the stability check's diagnosis."""
    try:
        return make()
    except NumericalError as e:
        why = stability and stability.get("message")
        raise NumericalError(f"{e}; {why}" if why else str(e)) from None


@main.command("simulate")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("scene", metavar="SCENE|DATA")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Trajectory file to write (atomic).")
@click.option("--trajectories", "-B", type=click.IntRange(min=1), help="Number of trajectories (scene default).")
@click.option("--horizon", "-T", type=click.IntRange(min=1), help="Steps per trajectory (scene default).")
@click.option("--seed", type=int, help="Seed of the initial states (same draws as `mpnode generate --seed`).")
@click.option("--warmup", type=click.IntRange(min=1), metavar="K",
              help="With a trajectory file DATA in place of SCENE: each simulation starts from the state the "
                   "model estimates from the first K observations of a trajectory of DATA (default 1).")
@start_option
@click.option("--ignore-attrs", is_flag=True,
              help="Leave out the node attributes and edge weights of SCENE or DATA when MODEL was trained "
                   "without them (OUTPUT keeps them, as the network simulated).")
@plot_option("the simulated trajectories of the first nodes, per state dimension")
@substeps_options
def simulate_cmd(model_file, scene, output, trajectories, horizon, seed, warmup, start, ignore_attrs, plot, substeps,
                 substeps_tol, max_substeps):
    """Roll MODEL out on SCENE (built-in name or .toml): any graph, any number of nodes;
    or onward from the trajectories of a trajectory file DATA (.h5).

    Initial states come from the scene's sampler, drawn exactly as `mpnode generate`
    draws them (trajectory b from SeedSequence(seed, spawn_key=(b,))), so a generated
    file with the same scene and seed holds the reference trajectories of the same
    initial states.  The output uses the model's dt; its attributes name the model
    and the substeps used.

    A closed-loop scene (the quadrotor swarms, quad3 ... quad12) runs the model in the
    scene's loop: every step the scene's controllers choose the thrusts from the
    model's own state (scenario and thrust noise drawn as `mpnode generate` draws them),
    and the output holds them as u.

    --substeps auto chooses the RK4 substeps by step doubling (see `mpnode eval
    --help`).  Without true states, a prediction counts as blown up when it is
    non-finite or leaves [mean - 20 std, mean + 20 std] of the training data (the
    model's normalisation) widened to hold the initial states; if more substeps
    avoid that, the RK4 step was too large and a --substeps N is suggested.

    From DATA, each trajectory's simulation starts at its first observation time, from
    the state the model estimates from its first --warmup K observations (--start: its
    encoder's estimate, or that fitted to them), on the trajectory's graph, and runs at
    the model's dt to its last observation (or --horizon steps): past what was observed
    when --horizon says so.  -B takes the first B trajectories.

    A MODEL trained on another system than SCENE's is rolled out, with a warning, and so
    is one whose inputs leave the ranges it saw in training (states, in-degree, aggregates,
    number of nodes: one warning per quantity, see `mpnode eval --help`).  An ensemble
    MODEL writes its members' mean as x and its calibrated spread as x_std (--plot shades
    the 90% band).

    A MODEL with node attributes hears those of the scene's trajectories (a _het scene
    draws them with each trajectory's graph and weights) or of DATA, held over the whole
    horizon; OUTPUT keeps them and the weighted graphs.  Attributes or weights that are not
    the model's are refused as `mpnode eval` refuses them (--ignore-attrs as there).
    Exit status: 0 written; 2 bad input (also: more trajectories or steps than memory
    holds, refused before any work; OUTPUT being written by another run); 3 predictions
    non-finite (nothing written); 4 the system refused (OUTPUT could not be written).
    """
    from mpnode.base.atomic import check_outputs
    from mpnode.evaluation.evaluate import simulate
    from mpnode.model import Model

    check_plot(plot)
    check_outputs({"--output": output, **({"--plot": plot} if plot else {})}, [model_file, scene])
    claim_outputs({"--output": output, "--plot": plot})
    model = Model.load(model_file)
    if scene.endswith((".h5", ".hdf5")):
        st = _start_from_data(model, model_file, scene, trajectories, horizon, seed, warmup, start, ignore_attrs)
    else:
        st = _start_from_scene(model, model_file, scene, trajectories, horizon, seed, warmup)
    graphs, held = heard(model, st, scene, ignore_attrs)
    controls = st.controls if held is None or st.controls is None else with_attrs(st.controls, held[:, 0])
    sim = simulate(model, st.x0, graphs, st.graph_index, st.horizon, u=held if st.controls is None else None,
                   substeps=substeps, substeps_tol=substeps_tol, max_substeps=max_substeps,
                   state_names=st.state_names, controls=controls)
    warn_off_range(sim.off_range or [])
    for line in format_substeps(sim.substeps, sim.substeps_report, sim.stability):
        click.echo(line.strip(), err=bool(sim.stability.get("message")) and "WARNING" in line)
    if plot:  # before the trajectory file, which refuses non-finite predictions: a blow-up gets its figure
        from mpnode.plot import plot_simulation

        plot_simulation(sim.predictions, model.spec.dt, plot, state_names=st.state_names,
                        title=f"{os.path.basename(model_file)} ({model.kind}) on {st.name}", spread=sim.spread)
        click.echo(f"wrote {plot}")
    _write_simulation(model, model_file, st, sim, output)
    b, n = st.x0.shape[:2]
    node_steps = b * n * st.horizon
    click.echo(f"wrote {output}: {st.name}, B={b}, T={st.horizon}, N={n}, "
               f"rollout {sim.seconds:.3g} s ({node_steps / max(sim.seconds, 1e-12):.3g} node-steps/s)")


@dataclass
class SimulationStart:
    """Where `mpnode simulate` starts from and what its output says about it."""

    x0: object
    graphs: list
    graph_index: object
    horizon: int
    system: str
    name: str
    description: str
    state_names: list
    attrs: dict
    state_groups: list = None
    controls: object = None  # a closed loop: controls(k, x) -> u, the scene's controllers (data_gen)
    node_attrs: object = None  # (B, N, dp) the nodes' static attributes, named attr_names
    attr_names: list = None


def user_controls(model):
    """The controls a user gives ``model`` per node: its control_dim without its node attributes."""
    return model.spec.control_dim - model.spec.attr_dim


def heard(model, st, source, ignore_attrs):
    """(graphs, attributes held (B, horizon, N, dp) or None): the start ``st``'s network as ``model``
    hears it, checked as `mpnode eval` checks a file (mpnode.model.inputs.for_model: attributes and
    weights that are not the model's refused, or left out with ``ignore_attrs``)."""
    import numpy as np

    from mpnode.data import Trajectories
    from mpnode.model.inputs import for_model

    x = np.broadcast_to(st.x0[:, None], (st.x0.shape[0], st.horizon + 1) + st.x0.shape[1:])  # the horizon: no copy
    probe = Trajectories(x=x, graphs=list(st.graphs), dt=model.spec.dt, system=st.system,
                         graph_index=np.asarray(st.graph_index), node_attrs=st.node_attrs, attr_names=st.attr_names)
    out = for_model(model, probe, source, ignore_attrs)
    return out.graphs, out.u


def with_attrs(controls, attrs):
    """A closed loop's controls(k, x) with the node attributes attrs (B, N, dp) after its own."""
    import numpy as np

    return lambda k, x: np.concatenate([np.asarray(controls(k, x), dtype=np.float64), attrs], axis=2)


def _start_from_scene(model, model_file, scene, trajectories, horizon, seed, warmup):
    """The scene's initial states, drawn as `mpnode generate` draws them (and a closed-loop
    scene's controllers, which choose the controls from the model's state)."""
    from dataclasses import replace

    from data_gen import load_scene
    from data_gen.scenes import check_scene
    from data_gen.systems import get_system

    if warmup is not None:
        raise InputError(scene, "--warmup", "needs observations to warm up on, and a scene has none",
                         "a trajectory file (.h5) in place of the scene, or no --warmup")
    s = load_scene(scene)
    s = replace(s, **{k: v for k, v in {"trajectories": trajectories, "horizon": horizon, "seed": seed}.items()
                      if v is not None})
    check_scene(s, scene)  # the options too (the memory B and T need), before any work
    system = get_system(s.system)
    _warn_system(model, s.system, scene)
    x0, graphs, gi, controls = _scene_start(model, model_file, scene, s, system)
    return SimulationStart(x0, graphs, gi, s.horizon, s.system, s.name, s.description,
                           list(system.state_names) or None, {"scene": s.name, "seed": s.seed, **s.graph.describe()},
                           list(system.state_groups) or None, controls, *_scene_attrs(s, system))


def _scene_attrs(s, system):
    """(node_attrs (B, N, dp), attr_names) of a scene whose trajectories draw their own, the draws
    that gave the initial states' graphs their weights (data_gen.per_trajectory); else (None, None)."""
    from data_gen.per_trajectory import scene_graphs

    if system.draw_trajectory is None:
        return None, None
    made = scene_graphs(s)
    return made.node_attrs, list(made.attr_names)


def _write_simulation(model, model_file, st, sim, output):
    """The simulated trajectories as a trajectory file: the data's own dimensions, controls and
    network (attributes, weighted graphs), named after the model and the substeps used."""
    from mpnode.data import write_trajectories
    from mpnode.evaluation.evaluate import predictions_file, substeps_attrs

    attrs = {**st.attrs, "description": f"{model.kind} rollout of {st.description}",
             **substeps_attrs(sim.substeps, sim.substeps_report),
             **({"state_names": st.state_names} if st.state_names else {}),
             **({"state_groups": st.state_groups} if st.state_groups else {})}
    shown = model.spec.state_dim - model.latent_dims  # latent dimensions stay the model's
    pred = sim.predictions[..., :shown]
    spread = None if sim.spread is None else sim.spread[..., :shown]
    u = sim.u[..., :user_controls(model)] if sim.u is not None and user_controls(model) else None
    pf = _or_why(lambda: predictions_file(pred, st.graphs, st.graph_index, model.spec.dt, st.system,
                                          os.path.abspath(model_file), u, attrs=attrs, spread=spread,
                                          node_attrs=st.node_attrs, attr_names=st.attr_names), sim.stability)
    write_trajectories(output, pf)


def _start_from_data(model, model_file, path, trajectories, horizon, seed, warmup, start, ignore_attrs=False):
    """Each trajectory of the file at ``path`` continued from its first ``warmup`` observations."""
    from mpnode.data import read_trajectories
    from mpnode.evaluation.evaluate import continue_from, subset

    if user_controls(model):
        raise InputError(model_file, "control_dim", f"the model takes controls (du = {user_controls(model)}) "
                         "but a trajectory file's continuation has none", "a model without controls, or a scene")

    if seed is not None:
        raise InputError(path, "--seed", "draws a scene's initial states, and a trajectory file brings its own",
                         "no --seed with a trajectory file")
    traj = read_trajectories(path)
    if trajectories is not None:
        traj = subset(traj, list(range(min(trajectories, traj.n_trajectories))))
    _warn_system(model, traj.system, path)
    x0, steps = continue_from(model, traj, warmup or 1, start, path, ignore_attrs)
    names, groups = traj.attrs.get("state_names"), traj.attrs.get("state_groups")
    return SimulationStart(x0, traj.graphs, traj.graph_index, horizon or steps, traj.system,
                           os.path.basename(path), f"the trajectories of {os.path.basename(path)}",
                           list(names) if names is not None else None,
                           {"simulated_from": os.path.abspath(path), "warmup": warmup or 1},
                           list(groups) if groups is not None else None, node_attrs=traj.node_attrs,
                           attr_names=traj.attr_names)


def _warn_system(model, system, source):
    """Say so on standard error when ``model`` learned another system than ``source``'s."""
    from mpnode.model.provenance import system_mismatch

    warning = system_mismatch(model, system, source)
    if warning:
        click.echo(f"warning: {warning}", err=True)

"""`mpnode eval MODEL DATA` and `mpnode simulate MODEL SCENE`: use a trained model."""
import json
import math
import os
import time

import click

from mpnode.errors import InputError, NumericalError

from .main import main


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
    from mpnode.stepsize import DEFAULT_MAX_SUBSTEPS, DEFAULT_TOL

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


def substeps_attrs(substeps, auto_report):
    """Attributes naming the substeps of a predictions file (and auto's rule and estimate)."""
    attrs = {"substeps": int(substeps)}
    if auto_report is not None:
        attrs.update(substeps_auto=1, substeps_tol=float(auto_report["tol"]),
                     substeps_tol_reached=int(auto_report["reached"]), substeps_rule=auto_report["rule"])
        if isinstance(auto_report["estimate"], float):
            attrs["substeps_estimate"] = auto_report["estimate"]
    return attrs


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


# ---------------------------------------------------------------------------
# Reference timing (data_gen knows the physics; the library does not)
# ---------------------------------------------------------------------------
def reference_timing(traj, pred, sample):
    """Time the reference simulator on the first ``sample`` trajectories' initial states.

    Returns a dict (system, integrator, sample, seconds per trajectory, the learned model's
    seconds per trajectory on the same batch, the reference's own nmse against the file), or
    None when the file does not name a reference system data_gen can rebuild.
    """
    import numpy as np

    from mpnode.data_gen.simulate import integrate
    from mpnode.data_gen.systems import SYSTEMS, file_rhs

    if traj.system not in SYSTEMS or "predicted_by" in traj.attrs or traj.u is not None:
        return None
    system = SYSTEMS[traj.system]
    method = str(traj.attrs.get("integrator", "DOP853"))
    rtol, atol = float(traj.attrs.get("rtol", 1e-9)), float(traj.attrs.get("atol", 1e-9))
    if traj.state_dim != system.state_dim:
        return None
    try:
        rhs = file_rhs(traj)
    except (KeyError, ValueError, TypeError):
        return None
    k = min(sample, traj.n_trajectories)
    x = np.asarray(traj.x, dtype=np.float64)
    out = np.empty((k,) + x.shape[1:])
    start = time.perf_counter()
    for b in range(k):
        out[b] = integrate(rhs[int(traj.graph_index[b])], x[b, 0], traj.horizon, traj.dt, method, rtol, atol,
                           system.guard)
    seconds = time.perf_counter() - start
    var = x.reshape(-1, x.shape[-1]).var(axis=0)
    var[var <= 0] = 1.0
    ref_err = float((((out[:, 1:] - x[:k, 1:]) ** 2) / var).mean())
    return {"system": traj.system, "integrator": f"{method} rtol={rtol:g} atol={atol:g}", "sample": k,
            "reference_seconds_per_trajectory": seconds / k, "reference_nmse_vs_file": ref_err}


def learned_timing_on_sample(model, traj, k, repeats=3):
    """Seconds per trajectory of the learned rollout of the first k trajectories as one batch (best of repeats)."""
    from mpnode.evaluate import rollout_all

    x0 = traj.x[:k, 0]
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        rollout_all(model, x0, traj.graphs, traj.graph_index[:k], traj.horizon)
        best = min(best, time.perf_counter() - start)
    return best / k


def run_eval(model, traj, source, allow_dt=False, reference_sample=20, substeps=None, substeps_tol=None,
             max_substeps=None):
    """Evaluate and time; returns (EvalResult, report dict)."""
    from mpnode import stepsize
    from mpnode.evaluate import evaluate

    result = evaluate(model, traj, source=source, allow_dt_mismatch=allow_dt, substeps=substeps,
                      substeps_tol=substeps_tol or stepsize.DEFAULT_TOL,
                      max_substeps=max_substeps or stepsize.DEFAULT_MAX_SUBSTEPS)
    report = {"data": source, **result.summary()}
    if reference_sample > 0:
        ref = reference_timing(traj, result.predictions, reference_sample)
        if ref is not None:
            m = model if math.isclose(traj.dt, model.spec.dt) else model.with_spec(dt=float(traj.dt))
            m = m.with_spec(substeps=result.substeps)
            ref["learned_seconds_per_trajectory"] = learned_timing_on_sample(m, traj, ref["sample"])
            ref["learned_seconds_per_trajectory_full_batch"] = result.rollout_seconds / result.n_trajectories
            ref["speedup"] = ref["reference_seconds_per_trajectory"] / ref["learned_seconds_per_trajectory"]
        report["reference"] = ref
    return result, report


def _g(v):
    return str(v) if isinstance(v, str) else f"{v:.3g}"


def format_report(report, model_name):
    """The human-readable evaluation report (several lines)."""
    r = report
    lines = [f"{model_name} on {r['data']}: B={r['trajectories']}, T={r['horizon']}, N={r['nodes']}"]
    per = r["nmse_per_step"]
    t = r["horizon"]
    steps = sorted({1, max(1, t // 4), max(1, t // 2), max(1, 3 * t // 4), t})
    lines.append(f"  normalised MSE, mean over steps 1..{t}: {_g(r['nmse'])}   last step: {_g(r['nmse_last'])}")
    lines.append("  per step: " + ", ".join(f"{s}: {_g(per[s])}" for s in steps))
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
    if "substeps" in r:
        lines += format_substeps(r["substeps"], r.get("substeps_auto"), r.get("stability"))
    lines.append(f"  learned rollout: {r['rollout_seconds']:.3g} s for {r['trajectories']} trajectories "
                 f"({r['node_steps_per_second']:.3g} node-steps/s)")
    ref = r.get("reference")
    if ref:
        lines.append(f"  reference {ref['system']} ({ref['integrator']}), timed on {ref['sample']} trajectories: "
                     f"{ref['reference_seconds_per_trajectory'] * 1e3:.3g} ms per trajectory "
                     f"(its nmse against the file: {ref['reference_nmse_vs_file']:.2g})")
        lines.append(f"  speed against error: learned {ref['learned_seconds_per_trajectory'] * 1e3:.3g} ms per "
                     f"trajectory (same {ref['sample']} as one batch; "
                     f"{ref['learned_seconds_per_trajectory_full_batch'] * 1e3:.3g} ms in the full batch) vs "
                     f"reference {ref['reference_seconds_per_trajectory'] * 1e3:.3g} ms: "
                     f"{ref['speedup']:.3g}x faster at normalised MSE {_g(r['nmse'])}")
    elif "reference" in r:
        lines.append("  reference: the file names no system data_gen can rebuild; not timed")
    return "\n".join(lines)


@main.command("eval")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--predictions", type=click.Path(dir_okay=False),
              help="Write the predicted trajectories here (trajectory format, same graphs; atomic).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
@click.option("--allow-dt-mismatch", is_flag=True,
              help="Roll the model out with the file's dt even if it was trained with another.")
@click.option("--reference-sample", type=click.IntRange(min=0), default=20, show_default=True,
              help="Trajectories the reference simulator is timed on (0: skip the reference).")
@substeps_options
def eval_cmd(model_file, data, predictions, as_json, allow_dt_mismatch, reference_sample, substeps, substeps_tol,
             max_substeps):
    """Roll MODEL out from every initial state of DATA and report error and speed.

    Error: normalised MSE (squared error / per-dimension variance of DATA's true
    states) per step and averaged over steps 1..T, the last step's, and the first
    step where a prediction became non-finite or left ten times the data's range.
    Predictable horizon: per trajectory the first step whose normalised MSE exceeds
    0.1 and 1.0, reported as the median over trajectories (in steps and time).
    Speed: rollout wall time and node-steps per second; when DATA names a reference
    system that mpnode.data_gen can rebuild from the file's parameters, the reference
    simulator is timed on a sample of the same initial states (speed against error).

    Substeps: --substeps auto picks the RK4 substeps per dt by step doubling (the
    difference of the rollouts with s and 2s substeps estimates the error of s;
    the smallest s = 1, 2, 4, ... under --substeps-tol wins).  When predictions blow
    up but do not with more substeps, the report says the RK4 step is too large and
    suggests --substeps N (--json: step_too_large, suggested_substeps).

    Exit status: 0 (also when the step is too large: see the report); 2 bad input
    (missing file, dx/du or dt mismatch); 3 predictions non-finite and --predictions
    given (nothing written).
    """
    from mpnode.data import read_trajectories, write_trajectories
    from mpnode.evaluate import prediction_file
    from mpnode.model import Model

    model = Model.load(model_file)
    traj = read_trajectories(data)
    result, report = run_eval(model, traj, data, allow_dt_mismatch, reference_sample, substeps, substeps_tol,
                              max_substeps)
    report["model"] = model_file
    if as_json:
        click.echo(json.dumps(report, indent=2, allow_nan=False))
    else:
        click.echo(format_report(report, model_file))
    if predictions:
        attrs = {"predicted_from": os.path.abspath(data), **substeps_attrs(result.substeps, result.substeps_report)}
        try:
            pf = prediction_file(traj, result.predictions, os.path.abspath(model_file), attrs)
        except NumericalError as e:
            st = result.stability
            raise NumericalError(f"{e}; {st['message']}" if st and st.get("message") else str(e)) from None
        write_trajectories(predictions, pf)
        if not as_json:
            click.echo(f"wrote {predictions}")


@main.command("simulate")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("scene")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Trajectory file to write (atomic).")
@click.option("--trajectories", "-B", type=click.IntRange(min=1), help="Number of trajectories (scene default).")
@click.option("--horizon", "-T", type=click.IntRange(min=1), help="Steps per trajectory (scene default).")
@click.option("--seed", type=int, help="Seed of the initial states (same draws as `mpnode generate --seed`).")
@substeps_options
def simulate_cmd(model_file, scene, output, trajectories, horizon, seed, substeps, substeps_tol, max_substeps):
    """Roll MODEL out on SCENE (built-in name or .toml): any graph, any number of nodes.

    Initial states come from the scene's sampler, drawn exactly as `mpnode generate`
    draws them (trajectory b from SeedSequence(seed, spawn_key=(b,))), so a generated
    file with the same scene and seed holds the reference trajectories of the same
    initial states.  The output uses the model's dt; its attributes name the model
    and the substeps used.

    --substeps auto chooses the RK4 substeps by step doubling (see `mpnode eval
    --help`).  Without true states, a prediction counts as blown up when it is
    non-finite or leaves [mean - 20 std, mean + 20 std] of the training data (the
    model's normalisation) widened to hold the initial states; if more substeps
    avoid that, the RK4 step was too large and a --substeps N is suggested.
    """
    from dataclasses import replace
    from types import SimpleNamespace

    import numpy as np

    from mpnode.data import write_trajectories
    from mpnode.data_gen import load_scene
    from mpnode.data_gen.initial import get_sampler
    from mpnode.data_gen.systems import get_system
    from mpnode.evaluate import prediction_file, rollout_all
    from mpnode.model import Model

    folder = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(folder):
        raise InputError("--output", output, f"folder {folder} does not exist", "a path in an existing folder")
    model = Model.load(model_file)
    s = load_scene(scene)
    s = replace(s, **{k: v for k, v in dict(trajectories=trajectories, horizon=horizon, seed=seed).items()
                      if v is not None})
    system = get_system(s.system)
    if system.state_dim != model.spec.state_dim:
        raise InputError(scene, "system", f"{s.system} has {system.state_dim} state dimensions per node but the "
                         f"model has {model.spec.state_dim}", "a scene of the system the model learned")
    if model.spec.control_dim:
        raise InputError(model_file, "control_dim", f"the model takes controls (du = {model.spec.control_dim}) "
                         "but scenes have none", "a model without controls")
    graphs = s.graph.build()
    sampler = get_sampler(s.initial, system, s.graph.n_nodes, scene, "initial")
    gi = np.arange(s.trajectories) % len(graphs)
    x0 = np.stack([sampler(np.random.default_rng(np.random.SeedSequence(s.seed, spawn_key=(b,))), system,
                           graphs[gi[b]].n_nodes) for b in range(s.trajectories)])
    from mpnode import stepsize
    from mpnode.evaluate import blow_up_mask

    graph_arg = graphs[0] if len(graphs) == 1 else [graphs[int(i)] for i in gi]
    auto_report = None
    if substeps == "auto":
        chosen, auto_report = stepsize.choose_substeps(model, x0, graph_arg, None, substeps_tol,
                                                       max_substeps=max_substeps, horizon=s.horizon)
        model = model.with_spec(substeps=chosen)
    elif substeps is not None:
        model = model.with_spec(substeps=substeps)
    start = time.perf_counter()
    pred = rollout_all(model, x0, graphs, gi, s.horizon)
    seconds = time.perf_counter() - start
    box = simulation_box(model, x0)
    stability = stepsize.stability_check(model, x0, graph_arg, None, pred, blow_up_mask(pred, box=box),
                                         substeps_tol, max_substeps=max_substeps, box=box)
    for line in format_substeps(model.spec.substeps, auto_report, stability):
        click.echo(line.strip(), err=bool(stability.get("message")) and "WARNING" in line)

    src = SimpleNamespace(graphs=graphs, dt=model.spec.dt, system=s.system, u=None, graph_index=gi)
    attrs = {"scene": s.name, "seed": s.seed, "description": f"MP-NODE rollout of {s.description}",
             **s.graph.describe(), **substeps_attrs(model.spec.substeps, auto_report)}
    try:
        pf = prediction_file(src, pred, os.path.abspath(model_file), attrs)
    except NumericalError as e:
        raise NumericalError(f"{e}; {stability['message']}" if stability.get("message") else str(e)) from None
    write_trajectories(output, pf)
    click.echo(f"wrote {output}: {s.name}, B={s.trajectories}, T={s.horizon}, N={s.graph.n_nodes}, "
               f"rollout {seconds:.3g} s ({s.trajectories * s.graph.n_nodes * s.horizon / max(seconds, 1e-12):.3g} "
               f"node-steps/s)")


def simulation_box(model, x0):
    """(mid, r) of the blow-up test without true states: 10x this box is mean +- 20 std of the
    training data (the model's normalisation), widened to hold the initial states x0."""
    import numpy as np

    lo = np.minimum(model.x_mean - 2 * model.x_std, x0.reshape(-1, x0.shape[-1]).min(axis=0))
    hi = np.maximum(model.x_mean + 2 * model.x_std, x0.reshape(-1, x0.shape[-1]).max(axis=0))
    return (lo + hi) / 2, hi - lo

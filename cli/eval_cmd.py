"""`mpnode eval MODEL DATA` and `mpnode simulate MODEL SCENE`: use a trained model."""
import json
import math
import os
import sys
import time

import click

from mpnode.errors import InputError

from .main import main


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
    from mpnode.data_gen.systems import SYSTEMS, make_rhs

    if traj.system not in SYSTEMS or "predicted_by" in traj.attrs or traj.u is not None:
        return None
    system = SYSTEMS[traj.system]
    params = {**traj.attrs, **traj.params}
    method = str(traj.attrs.get("integrator", "DOP853"))
    rtol, atol = float(traj.attrs.get("rtol", 1e-9)), float(traj.attrs.get("atol", 1e-9))
    if traj.state_dim != system.state_dim:
        return None
    try:
        rhs = [make_rhs(traj.system, params, g) for g in traj.graphs]
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


def run_eval(model, traj, source, allow_dt=False, reference_sample=20):
    """Evaluate and time; returns (EvalResult, report dict)."""
    from mpnode.evaluate import evaluate

    result = evaluate(model, traj, source=source, allow_dt_mismatch=allow_dt)
    report = {"data": source, **result.summary()}
    if reference_sample > 0:
        ref = reference_timing(traj, result.predictions, reference_sample)
        if ref is not None:
            m = model if math.isclose(traj.dt, model.spec.dt) else model.with_spec(dt=float(traj.dt))
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
def eval_cmd(model_file, data, predictions, as_json, allow_dt_mismatch, reference_sample):
    """Roll MODEL out from every initial state of DATA and report error and speed.

    Error: normalised MSE (squared error / per-dimension variance of DATA's true
    states) per step and averaged over steps 1..T, the last step's, and the first
    step where a prediction became non-finite or left ten times the data's range.
    Speed: rollout wall time and node-steps per second; when DATA names a reference
    system that mpnode.data_gen can rebuild from the file's parameters, the reference
    simulator is timed on a sample of the same initial states (speed against error).

    Exit status: 0; 2 bad input (missing file, dx/du or dt mismatch); 3 predictions
    non-finite and --predictions given (nothing written).
    """
    from mpnode.data import read_trajectories, write_trajectories
    from mpnode.evaluate import prediction_file
    from mpnode.model import Model

    model = Model.load(model_file)
    traj = read_trajectories(data)
    result, report = run_eval(model, traj, data, allow_dt_mismatch, reference_sample)
    report["model"] = model_file
    if as_json:
        click.echo(json.dumps(report, indent=2, allow_nan=False))
    else:
        click.echo(format_report(report, model_file))
    if predictions:
        write_trajectories(predictions, prediction_file(traj, result.predictions, os.path.abspath(model_file),
                                                        {"predicted_from": os.path.abspath(data)}))
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
def simulate_cmd(model_file, scene, output, trajectories, horizon, seed):
    """Roll MODEL out on SCENE (built-in name or .toml): any graph, any number of nodes.

    Initial states come from the scene's sampler, drawn exactly as `mpnode generate`
    draws them (trajectory b from SeedSequence(seed, spawn_key=(b,))), so a generated
    file with the same scene and seed holds the reference trajectories of the same
    initial states.  The output uses the model's dt; its attributes name the model.
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
    start = time.perf_counter()
    pred = rollout_all(model, x0, graphs, gi, s.horizon)
    seconds = time.perf_counter() - start

    src = SimpleNamespace(graphs=graphs, dt=model.spec.dt, system=s.system, u=None, graph_index=gi)
    attrs = {"scene": s.name, "seed": s.seed, "description": f"MP-NODE rollout of {s.description}",
             **s.graph.describe()}
    write_trajectories(output, prediction_file(src, pred, os.path.abspath(model_file), attrs))
    click.echo(f"wrote {output}: {s.name}, B={s.trajectories}, T={s.horizon}, N={s.graph.n_nodes}, "
               f"rollout {seconds:.3g} s ({s.trajectories * s.graph.n_nodes * s.horizon / max(seconds, 1e-12):.3g} "
               f"node-steps/s)")

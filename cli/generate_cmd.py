"""`mpnode generate SCENE -o FILE` and `mpnode scenes`: make trajectory files from the reference systems."""
import os
import sys
import time
from dataclasses import replace

import click

from mpnode.base.errors import InputError

from .main import claim_outputs, main, scheduler_option


@main.command("generate")
@click.argument("scene")
@click.option("-o", "--output", required=True, type=click.Path(),
              help="Trajectory file (HDF5) to write; written atomically, absent if generation fails.  A scene set: "
                   "a folder or a file-name prefix (below).")
@click.option("--trajectories", "-B", type=click.IntRange(min=1),
              help="Number of trajectories B (scene default otherwise).")
@click.option("--horizon", "-T", type=click.IntRange(min=1), help="Saved steps per trajectory T (x has T+1 states).")
@click.option("--dt", type=click.FloatRange(min=0, min_open=True), help="Time between saved states.")
@click.option("--seed", type=int,
              help="Seed of the initial states (trajectory b uses SeedSequence(seed, spawn_key=(b,))) and of what "
                   "each trajectory draws for itself (the _het scenes' graphs, weights and node attributes); "
                   "parameters shared by all (lorenz H, kuramoto omega) keep the scene's system_seed.")
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True,
              help="Processes integrating trajectories (local pool, or --scheduler local); the data do not depend "
                   "on it.")
@click.option("--jitter", type=click.FloatRange(0, 0.9), default=0.0, metavar="F",
              help="Data as they come: each observation's time moves by up to F/2 dt either way (the scene is "
                   "integrated on a grid 20 times finer; needs a system without controls).")
@click.option("--drop", type=click.FloatRange(0, 0.95), default=0.0, metavar="P",
              help="Data as they come: the fraction P of the values goes missing (NaN), each on its own.")
@click.option("--noise", type=click.FloatRange(0, 10), default=0.0, metavar="REL",
              help="Data as they come: Gaussian measurement noise, its std REL times each dimension's std.")
@click.option("--hide", metavar="DIMS", default="",
              help="Data as they come: state dimensions nobody measures (indices or state names, comma-separated).")
@click.option("--excitation", type=click.FloatRange(min=0), metavar="N",
              help="Quadrotor scenes: every second step each quadrotor's thrusts get random offsets its state "
                   "does not decide (collective: std N newtons over both steps; torques: a doublet a quarter that "
                   "size), so that a model trained on the file learns what the thrusts do, as model-predictive "
                   "control needs; the scene's value otherwise (built-in: 0).")
@scheduler_option
def generate(scene, output, trajectories, horizon, dt, seed, workers, scheduler, jitter, drop, noise, hide,
             excitation):
    """Integrate the reference system of SCENE and write the trajectories to FILE.

    SCENE is a built-in name (list them with `mpnode scenes`) or a path to a
    .toml scene file (schema: data_gen.scenes).  A scene set (e.g. quad3-5) writes one
    file per member scene: -o DIR/ gives DIR/quad3.h5, ...; -o swarm (or swarm.h5)
    gives swarm_quad3.h5, ...; -B then sets every member's B (default: each its own),
    and member i draws with seed --seed + i.  Nothing is written until every
    member is made.  Each trajectory is
    integrated with scipy solve_ivp (DOP853, rtol = atol = 1e-9 unless the scene
    says otherwise) and saved at t = k*dt.  A trajectory that fails (solver error,
    non-finite state, a pendulum reaching |cos theta| < 1e-6) is re-drawn from a
    fresh initial state; the count is stored as the attribute `redrawn`.

    Exit status: 0 written; 2 bad scene, option or output path (also: a dt too long for
    the system, more trajectories than memory holds, FILE being written by another run);
    3 trajectories kept failing (nothing written); 4 the system refused (FILE could not be
    written: permission, full disk, read-only folder; nothing is left behind).

    With --scheduler the trajectories are integrated on Dask in chunks; the arrays come
    back here and only this process writes FILE: the file is the same, bit for bit.
    """
    from data_gen import SETS, load_scene
    from data_gen.degrade import fine_scene
    from data_gen.scenes import check_scene
    from mpnode.base.atomic import check_outputs
    from mpnode.data import write_trajectories

    if scene in SETS:
        shape = {k: v for k, v in dict(horizon=horizon, dt=dt).items() if v is not None}
        scenes = SETS[scene].scenes(trajectories, seed, **shape)
        if excitation is not None:
            scenes = [replace(s, excitation=excitation) for s in scenes]
        outputs = set_paths(output, scenes)
    elif os.path.isdir(output):
        raise InputError("--output", output, "is a folder", "a file name (a folder only for a scene set)")
    else:
        overrides = dict(trajectories=trajectories, horizon=horizon, dt=dt, seed=seed, excitation=excitation)
        scenes = [replace(load_scene(scene), **{k: v for k, v in overrides.items() if v is not None})]
        outputs = [output]
    flags = {f"--output ({s.name})" if len(scenes) > 1 else "--output": out for s, out in zip(scenes, outputs)}
    check_outputs(flags, [scene])
    degradations = [_degradation(s, jitter, drop, noise, hide) for s in scenes]
    for s, d in zip(scenes, degradations):
        check_scene(fine_scene(s, d), scene)  # the options too (dt, the memory B and T need), before any work
    claim_outputs(flags)
    made = [_generate(s, d, workers, scheduler) for s, d in zip(scenes, degradations)]  # all before any is written
    for out, (traj, line) in zip(outputs, made):
        write_trajectories(out, traj)
        click.echo(f"wrote {out}: {line}")


def _degradation(s, jitter, drop, noise, hide):
    """The Degradation the data-as-they-come options ask of scene ``s``."""
    from data_gen.degrade import Degradation

    return Degradation(jitter, drop, noise, _dims(hide, s), s.seed)


def _generate(s, degradation, workers, scheduler):
    """(the trajectories of scene ``s``, degraded as asked, and the line that describes them)."""
    from data_gen import generate as run
    from data_gen.degrade import degrade, fine_scene

    start = time.perf_counter()
    with click.progressbar(length=s.trajectories, label=s.name, file=sys.stderr) as bar:
        traj = run(fine_scene(s, degradation), workers=workers, progress=bar.update, scheduler=scheduler)
    if degradation.any:
        traj = degrade(traj, degradation, s.dt)
    return traj, (f"{s.name}, B={traj.n_trajectories}, T={traj.horizon}, N={traj.n_nodes}, dx={traj.state_dim}, "
                  f"{len(traj.graphs)} graph(s), seed {s.seed}, {traj.attrs['redrawn']} re-drawn, "
                  f"{time.perf_counter() - start:.1f} s")


def set_paths(output, scenes):
    """The files of a scene set's members: DIR/<scene>.h5 when ``output`` is a folder (an existing
    one, or a path ending in /), else <output without .h5>_<scene>.h5 (``-o swarm`` or ``-o
    swarm.h5``: swarm_quad3.h5, swarm_quad4.h5, ...)."""
    if os.path.isdir(output) or output.endswith(os.sep):
        return [os.path.join(output, f"{s.name}.h5") for s in scenes]
    prefix = output[:-3] if output.endswith(".h5") else output
    return [f"{prefix}_{s.name}.h5" for s in scenes]


def _dims(hide, scene):
    """--hide's dimensions as indices (names are the system's state names)."""
    from data_gen.systems import get_system

    names = list(get_system(scene.system).state_names or [])
    out = []
    for item in (h.strip() for h in hide.split(",") if h.strip()):
        if item.isdigit():
            out.append(int(item))
        elif item in names:
            out.append(names.index(item))
        else:
            raise InputError("--hide", item, "is neither a dimension index nor a state name",
                             f"indices 0..{len(names) - 1 if names else 'dx-1'}" + (f" or {', '.join(names)}" if names else ""))
    return tuple(out)


@main.command("scenes")
def scenes():
    """List the built-in scenes, one per line: name, system, N, B, T, dt, description;
    then the scene sets (several scenes trained on together, one file each).

    Any of them can be passed to `mpnode generate` and `mpnode train`; B, T, dt and the
    seed can be overridden there.  For anything else write a .toml scene file.
    """
    from data_gen import BUILTIN

    from data_gen import SETS

    width = max(map(len, [*BUILTIN, *SETS]))
    for name, s in {**BUILTIN, **SETS}.items():
        click.echo(f"{name:<{width}}  {s.summary()}")

"""`mpnode generate SCENE -o FILE` and `mpnode scenes`: make trajectory files from the reference systems."""
import sys
import time
from dataclasses import replace

import click

from .main import claim_outputs, main, scheduler_option


@main.command("generate")
@click.argument("scene")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Trajectory file (HDF5) to write; written atomically, absent if generation fails.")
@click.option("--trajectories", "-B", type=click.IntRange(min=1),
              help="Number of trajectories B (scene default otherwise).")
@click.option("--horizon", "-T", type=click.IntRange(min=1), help="Saved steps per trajectory T (x has T+1 states).")
@click.option("--dt", type=click.FloatRange(min=0, min_open=True), help="Time between saved states.")
@click.option("--seed", type=int,
              help="Seed of the initial states (trajectory b uses SeedSequence(seed, spawn_key=(b,))); "
                   "drawn parameters (lorenz H, kuramoto omega) keep the scene's system_seed.")
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
@scheduler_option
def generate(scene, output, trajectories, horizon, dt, seed, workers, scheduler, jitter, drop, noise, hide):
    """Integrate the reference system of SCENE and write the trajectories to FILE.

    SCENE is a built-in name (list them with `mpnode scenes`) or a path to a
    .toml scene file (schema: data_gen.scenes).  Each trajectory is
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
    from data_gen import generate as run
    from data_gen import load_scene
    from data_gen.degrade import Degradation, degrade, fine_scene
    from data_gen.scenes import check_scene
    from mpnode.base.atomic import check_outputs
    from mpnode.data import write_trajectories

    check_outputs({"--output": output}, [scene])
    s = load_scene(scene)
    overrides = dict(trajectories=trajectories, horizon=horizon, dt=dt, seed=seed)
    s = replace(s, **{k: v for k, v in overrides.items() if v is not None})
    degradation = Degradation(jitter, drop, noise, _dims(hide, s), s.seed)
    check_scene(fine_scene(s, degradation), scene)  # the options too (dt, the memory B and T need), before any work
    claim_outputs({"--output": output})
    start = time.perf_counter()
    with click.progressbar(length=s.trajectories, label=s.name, file=sys.stderr) as bar:
        traj = run(fine_scene(s, degradation), workers=workers, progress=bar.update, scheduler=scheduler)
    if degradation.any:
        traj = degrade(traj, degradation, s.dt)
    write_trajectories(output, traj)
    click.echo(f"wrote {output}: {s.name}, B={traj.n_trajectories}, T={traj.horizon}, N={traj.n_nodes}, "
               f"dx={traj.state_dim}, {len(traj.graphs)} graph(s), {traj.attrs['redrawn']} re-drawn, "
               f"{time.perf_counter() - start:.1f} s")


def _dims(hide, scene):
    """--hide's dimensions as indices (names are the system's state names)."""
    from data_gen.systems import get_system
    from mpnode.base.errors import InputError

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
    """List the built-in scenes, one per line: name, system, N, B, T, dt, description.

    Any of them can be passed to `mpnode generate`; B, T, dt and the seed can be
    overridden there.  For anything else write a .toml scene file.
    """
    from data_gen import BUILTIN

    width = max(map(len, BUILTIN))
    for name, s in BUILTIN.items():
        click.echo(f"{name:<{width}}  {s.summary()}")

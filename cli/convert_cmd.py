"""`mpnode convert FILE.npz -o FILE.h5`: your own arrays in, a trajectory file out."""
import textwrap

import click

from mpnode.data.npz import KEYS

from .main import claim_outputs, main

HELP = """Convert the NumPy archive FILE (.npz) into a trajectory file (HDF5).

Save your arrays with np.savez(FILE, x=x, edges=edges, dt=0.05, system="springs")
and convert; the result is checked against the trajectory format and written
atomically (the complete file or nothing).  The keys:

\b
""" + "\n".join(f"  {key}\n" + textwrap.fill(meaning, 78, initial_indent=" " * 6, subsequent_indent=" " * 6)
               for key, meaning in KEYS.items()) + """

An edge (s, r) means node r hears node s.  A graph that lists a node with itself
allows self-loops.  Edge weights (weights, or a third column of edges; a negative
one is kept as it is) and node attributes (node_attrs) make a format version 3
file.  A bad archive stops with exit status 2 and a message naming the key and
the fix; nothing is written.

Exit status: 0 written; 2 bad archive or option (also: OUTPUT being written by
another run); 4 the system refused (OUTPUT could not be written: permission, full
disk, read-only folder; nothing is left behind).
"""


@main.command("convert", help=HELP)
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Trajectory file to write (atomic; never one of the inputs).")
@click.option("--dt", type=click.FloatRange(min=0, min_open=True),
              help="Time between saved states, when the archive has neither dt nor t.")
@click.option("--system", help="A name for the system, when the archive has no key system.")
def convert(file, output, dt, system):
    from mpnode.base.atomic import check_outputs
    from mpnode.data import summarize, write_trajectories
    from mpnode.data.npz import read_npz

    check_outputs({"--output": output}, [file])
    claim_outputs({"--output": output})
    traj = read_npz(file, dt=dt, system=system)
    write_trajectories(output, traj)
    s = summarize(traj)
    click.echo(f"wrote {output}: {s['system']}, B={s['B']}, T={s['T']}, N={s['N']}, dx={s['dx']}, du={s['du']}, "
               f"dt={s['dt']:g}, {len(s['graphs'])} graph(s) with "
               + ", ".join(str(g["edges"]) for g in s["graphs"]) + " directed edges"
               + (", weighted" if traj.weighted else ""))
    if traj.attr_dim:
        click.echo(f"node attributes: {', '.join(traj.attr_names)}")
    layout = ("state_names", "state_groups", "control_names", "t0")
    for group, keys in (("root attributes", [k for k in traj.attrs if k not in layout]), ("aux/", list(traj.aux))):
        if keys:
            click.echo(f"kept as {group}: {', '.join(keys)}")

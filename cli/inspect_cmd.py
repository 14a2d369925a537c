"""`mpnode inspect FILE`: validate a trajectory file and describe what it holds."""
import json

import click

from .main import main


@main.command("inspect")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text (for scripts).")
def inspect(file, as_json):
    """Check FILE against the trajectory format and summarize it.

    Every rule of the format (version 1) is checked; a file that breaks one is
    reported as "Error: FILE: FIELD: problem (expected ...)" with exit status 2.
    A valid file prints the system, the sizes B (trajectories), T (steps),
    N (nodes), dx/du (state/control size per node), dt, the dtype, every graph
    with its node and edge count, the stored parameters and other attributes.
    """
    from mpnode.data import read_trajectories, summarize

    summary = summarize(read_trajectories(file))
    if as_json:
        click.echo(json.dumps({"file": file, **summary}, indent=2, allow_nan=False))
    else:
        click.echo(_text(file, summary))


def _text(file, s):
    """The summary as aligned 'label: value' lines for people."""
    lines = [
        f"file:        {file}",
        f"system:      {s['system']}",
        f"sizes:       B={s['B']} trajectories, T={s['T']} steps, N={s['N']} nodes, dx={s['dx']}, du={s['du']}",
        f"dt:          {s['dt']} (each trajectory spans {s['duration']:g})",
        f"dtype:       x {s['x_dtype']}" + (f", u {s['u_dtype']}" if s["u_dtype"] else ""),
        f"graphs:      {len(s['graphs'])}",
    ]
    for g, info in enumerate(s["graphs"]):
        loops = ", self-loops allowed" if info["self_loops"] else ""
        used = info["trajectories"]
        lines.append(f"  graphs/{g}: {info['nodes']} nodes, {info['edges']} directed edges{loops}, "
                     f"used by {used} " + ("trajectory" if used == 1 else "trajectories"))
    for group in ("params", "aux"):
        lines.append(f"{group + ':':<13}" + ("" if s[group] else "none"))
        for name, d in s[group].items():
            value = f" = {d['value']}" if "value" in d else ""
            lines.append(f"  {name}: {d['dtype']} {d['shape']}{value}")
    lines.append("attributes:  " + ("" if s["attrs"] else "none"))
    lines += [f"  {key} = {value!r}" for key, value in s["attrs"].items()]
    return "\n".join(line.rstrip() for line in lines)

"""`mpnode inspect FILE`: validate a trajectory file or a model file and describe what it holds."""
import json

import click

from .main import main


@main.command("inspect")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text (for scripts).")
def inspect(file, as_json):
    """Check FILE against its format and summarize it.

    A trajectory file: every rule of the trajectory format is checked; a valid file
    prints the system, the sizes B (trajectories), T (steps), N (nodes), dx/du
    (state/control size per node), dt, the dtype, every graph with its node and edge
    count, the edge weights' range (smallest, largest, share negative) and each node
    attribute's range, the stored parameters and other attributes.  A model file: its kind
    (mpnode, l2s or node), sizes, aggregation, integration settings, parameter count
    and the attributes training recorded (data, recipe, epoch, validation loss).
    A file that breaks a rule is reported as "Error: FILE: FIELD: problem (expected ...)"
    with exit status 2; a file the system will not let us read (permission, an I/O
    error) with exit status 4.
    """
    from mpnode.base.h5 import file_format
    from mpnode.data import read_trajectories, summarize
    from mpnode.model import Model

    if file_format(file) == "mpnode.model":
        summary, text = Model.load(file).summary(), _model_text
    else:
        summary, text = summarize(read_trajectories(file)), _text
    click.echo(json.dumps({"file": file, **summary}, indent=2, allow_nan=False, default=str) if as_json
               else text(file, summary))


def _aggregation_text(name, s):
    """'mean', or 'scaled (over mean in-degree 8)': an aggregation and the divisor it uses."""
    return name + (f" (over mean in-degree {s['mean_degree']:g})" if name == "scaled" else "")


def _model_text(file, s):
    nodes = f", trained on systems of N={s['n_nodes']} nodes only" if s["n_nodes"] else ", any graph"
    agg = "" if s["kind"] == "node" else "aggregation " + _aggregation_text(s["aggregation"], s)
    own = s["linear_aggregation"]
    linear = ", linear aggregate path (W_agg" + (f", reads the {_aggregation_text(own, s)} aggregate" if own else "") \
        + (", adds to dx/dt only" if s["linear_target"] == "state" else "")
    lines = [f"file:        {file}",
             f"kind:        {s['kind']}{nodes}",
             f"sizes:       dx={s['state_dim']}, du={s['control_dim']}, dm={s['message_dim']}, H={s['hidden']}, "
             f"{s['parameters']} parameters ({s['dtype']})",
             f"messages:    {agg}" + (", self-messages" if s["self_messages"] else "")
             + (", clamped to zero" if s["zero_messages"] else "")
             + (linear + ")" if s["linear_aggregate"] else ""),
             f"integration: RK4, dt={s['dt']:g}, {s['substeps']} substep(s) per dt"
             + (f"; kinematics {s['kinematics']} (fixed, not learned)" if s["kinematics"] else ""),
             "arrays:      " + ", ".join(f"{k} {v}" for k, v in s["arrays"].items())
             + (" per member" if "ensemble" in s else ""),
             *_ensemble_text(s.get("ensemble")),
             "attributes:  " + ("" if s["attrs"] else "none")]
    lines += [f"  {key} = {value!r}" for key, value in s["attrs"].items()]
    return "\n".join(line.rstrip() for line in lines)


def _ensemble_text(e):
    """An ensemble's lines: its members (seed, epoch, validation loss) and the spread's scale."""
    if e is None:
        return []
    lines = [f"ensemble:    {e['members']} members; spread scale (calibrated on validation data) "
             + ", ".join(f"{v:.3g}" for v in e["spread_scale"])]
    for i, seed in enumerate(e.get("member_seed", [])):
        more = "".join(f", {label} {e[key][i]:.4g}" for key, label in (("member_epoch", "epoch"),
                       ("member_val_loss", "validation loss")) if key in e)
        lines.append(f"  member {i}: seed {seed}{more}")
    return lines


def _sampling_text(m):
    """How the data were observed, for people: regular or not, the gaps, what was observed."""
    steps = f"{m['steps_min']}" if m["steps_min"] == m["steps_max"] else f"{m['steps_min']} to {m['steps_max']}"
    kind = "regular (one dt)" if m["regular"] else (f"irregular: gaps {m['gap_min']:.4g} smallest, "
                                                      f"{m['gap_median']:.4g} median, {m['gap_max']:.4g} largest")
    per_dim = ", ".join(f"{v:.0%}" for v in m["observed_per_dim"])
    per_node = ", ".join(f"{v:.0%}" for v in m["observed_per_node"][:12]) + (
        ", ..." if len(m["observed_per_node"]) > 12 else "")
    lines = [f"sampling:    {kind}; {steps} steps per trajectory",
             f"observed:    per dimension {per_dim}; per node {per_node}"]
    if m["unmeasured_dims"]:
        lines.append(f"  never measured: dimension(s) {m['unmeasured_dims']} (a model carries them as hidden states)")
    if m["truth"]:
        lines.append("  the clean truth behind the observations is kept (mpnode eval scores against it)")
    return lines


def _network_text(w, attrs):
    """The weights' range and each node attribute's, for people (nothing for plain graphs)."""
    lines = []
    if w is not None:
        span = "no edges" if w["min"] is None else f"{w['min']:.4g} to {w['max']:.4g}, {w['negative']:.0%} negative"
        lines.append(f"weights:     {span}")
    if attrs:
        lines.append(f"node attrs:  {len(attrs)} per node")
        lines += [f"  {name}: {r['min']:.4g} to {r['max']:.4g}" for name, r in attrs.items()]
    return lines


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
    lines += _sampling_text(s["sampling"])
    lines += _network_text(s["weights"], s["node_attrs"])
    for group in ("params", "aux"):
        lines.append(f"{group + ':':<13}" + ("" if s[group] else "none"))
        for name, d in s[group].items():
            value = f" = {d['value']}" if "value" in d else ""
            lines.append(f"  {name}: {d['dtype']} {d['shape']}{value}")
    lines.append("attributes:  " + ("" if s["attrs"] else "none"))
    lines += [f"  {key} = {value!r}" for key, value in s["attrs"].items()]
    return "\n".join(line.rstrip() for line in lines)

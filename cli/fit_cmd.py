"""`mpnode fit-network MODEL DATA`: which node or line of a network changed (mpnode.fit_network)."""
import json

import click

from .main import claim_outputs, main


@main.command("fit-network")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--what", type=click.Choice(["node_attrs", "edge_weights"]), default="node_attrs", show_default=True,
              help="Fit the node attributes or the edge weights (the other held at its nominal value).")
@click.option("--attrs", "attrs", multiple=True, metavar="NAME",
              help="An attribute to fit (repeat for several; default all the model's).")
@click.option("--nominal", type=click.Path(dir_okay=False), metavar="NOMINAL.h5",
              help="A trajectory file whose first graph and node attributes are the nominal network "
                   "(default DATA's own).")
@click.option("--reference", type=click.Path(dir_okay=False), metavar="BEFORE.h5",
              help="Trajectories observed on the nominal network (before the change): fitted alike, and the "
                   "departures measured from that fit, so that what MODEL gets wrong drops out.")
@click.option("--window", type=click.IntRange(min=1), metavar="K",
              help="Roll out windows of K steps, each from its own first observation, instead of whole "
                   "trajectories: a model that drifts over a long rollout is still right over a short one.")
@click.option("--iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="L-BFGS-B iterations at most.")
@click.option("--top", type=click.IntRange(min=1), default=5, show_default=True,
              help="The most departed nodes (lines) printed.")
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Write the whole fit as JSON here (atomic): fitted and nominal values, departures, ranking.")
def fit_network_cmd(model_file, data, what, attrs, nominal, reference, window, iterations, top, output):
    """Fit the node attributes or edge weights of the network behind DATA's
    trajectories through MODEL, starting from the nominal network, and print
    the nodes (lines) that departed most from it, relative to their nominal
    values: the bus or line that changed, if the model is good enough to tell.

    The fit minimises the mean squared error of MODEL's rollouts from DATA's
    first observations against the later ones, with exact gradients (one
    rollout and one VJP per evaluation) and bounds: an attribute that is
    positive everywhere, and weights that are all >= 0, stay so.  Both
    directions of an undirected line are one parameter.  With --reference,
    observations from before the change are fitted alike and the departures
    measured between the two fits.  docs/fit-network.md has a worked example.

    Exit status: 0 fitted; 2 bad model, data, option or output path (nothing
    written); 4 the system refused (the output could not be written; nothing
    is left behind).
    """
    from mpnode.base.atomic import atomic_path, check_outputs
    from mpnode.data import read_trajectories
    from mpnode.evaluation.network_fit import fit_network

    outputs = {"--output": output} if output else {}
    check_outputs(outputs, [model_file, data] + [p for p in (nominal, reference) if p])
    claim_outputs(outputs)
    planned = read_trajectories(nominal) if nominal else None
    node_attrs = None if planned is None or planned.node_attrs is None else planned.node_attrs[0]
    graph = None if planned is None else planned.graphs[0]
    fit = fit_network(model_file, data, what, attrs=list(attrs) or None, node_attrs=node_attrs, graph=graph,
                      iterations=iterations, reference=reference, window=window)
    click.echo(f"loss {fit.loss_nominal:.4g} at the nominal network, {fit.loss:.4g} fitted "
               f"({fit.iterations} iterations, {fit.seconds:.1f} s; {fit.message.lower()})")
    click.echo("most departed from " + ("the reference's fit" if reference else "nominal") + " first:")
    for line in fit.describe(top):
        click.echo(f"  {line}")
    if output:
        with atomic_path(output) as tmp, open(tmp, "w") as f:
            json.dump({"model": model_file, "data": data, "nominal_file": nominal, "reference_file": reference,
                       **fit.to_dict()}, f)
        click.echo(f"wrote {output}")

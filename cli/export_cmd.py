"""`mpnode export MODEL -o OUT.onnx|OUT.py`: a model on one graph as a file that runs without mpnode."""
import functools

import click

from .main import claim_outputs, main


@main.command("export")
@click.argument("model_file", metavar="MODEL", type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="OUT.onnx (an ONNX graph) or OUT.py (a NumPy module); written atomically.")
@click.option("--graph", "graph_file", metavar="DATA", type=click.Path(exists=True, dir_okay=False),
              help="A trajectory file: the export is for its first graph (its edge weights the default ones).")
@click.option("--nodes", type=click.IntRange(min=1), help="Or: the complete graph on N nodes.")
@click.option("--steps", "-T", type=click.IntRange(min=1),
              help="ONNX only: the rollout's number of steps T (default 1: one step).")
def export_cmd(model_file, output, graph_file, nodes, steps):
    """Write MODEL (any kind) on one graph as a file that runs without mpnode.

    \b
    OUT.onnx  the rollout of T steps (--steps, default 1) as an ONNX graph (opset 17):
              inputs x0 (B, N, dx) and, for a model with controls, u (B, T, N, du);
              output x (B, T+1, N, dx); data units, the model's dtype, B free.
              Needs the onnx extra: pip install 'mpnode[onnx]'.
    OUT.py    a Python module needing numpy alone, weights inside:
              rollout(x0, steps, u=None) returns what Model.rollout returns.

    A model trained with node attributes or on weighted graphs takes them as
    inputs too, each with a default: node_attrs (1 or B, N, dp), default every
    node at the training mean of each attribute; edge_weights (E,) in the
    graph's CSR order, default the graph's own (1 on every edge of --nodes).
    OUT.py: rollout(..., node_attrs=None, edge_weights=None); ONNX: inputs
    whose initializers hold the defaults (feed them by name to override;
    onnxruntime lists them in get_overridable_initializers()).

    What is exported: the model's rollout on that graph, every dt, from a given full state
    x0 (its normalisation, RK4 substeps, messages starting at 0), N and, for ONNX, T fixed.
    What is not: training, gradients, step Jacobians, other graphs or sizes (export again),
    outputs at times of one's own, a model's initial-state encoder (estimate x0 from
    observations with Model.initial_state first; a model with latent dimensions takes
    them in x0 too), a step that continues from given messages (mpnode.Simulator does
    that).  The ONNX aggregation is a dense (N, N) MatMul: meant for graphs up to a few
    thousand nodes.

    Exit status: 0 written; 2 bad model, graph, option or output path (also: OUT being
    written by another run; nothing written); 4 the system refused (OUT could not be
    written: permission, full disk, read-only folder; nothing is left behind).
    """
    from mpnode.export.files import export_file

    claim = functools.partial(claim_outputs, {"--output": output})
    click.echo(export_file(model_file, output, graph_file, nodes, steps, claim=claim))

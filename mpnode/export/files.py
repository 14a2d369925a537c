"""Export from files: what `mpnode export` calls (checks first, then one atomic write)."""
import os

from mpnode.base.atomic import check_outputs
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph

#: the formats by the output's extension
FORMATS = {".onnx": "ONNX graph", ".py": "NumPy module"}


def export_file(model_path, output, graph_path=None, nodes=None, steps=None, claim=None):
    """Write ``model_path``'s model on a graph to ``output`` (.onnx or .py); returns a one-line summary.

    graph_path : a trajectory file whose first graph the export is for (its edge weights the
    default ones of a model of weighted graphs; left out for a model trained without); or
    ``nodes``: the complete graph on that many nodes (every edge weight 1).  steps : the ONNX
    rollout's T (default 1; the NumPy module takes it at run time).  Raises InputError (flag or file, field, fix) before
    writing anything; then calls ``claim()`` if given (the command's lock on ``output``).
    """
    from mpnode.model import Model
    from mpnode.model.ensemble import Ensemble

    ext = os.path.splitext(os.fspath(output))[1].lower()
    if ext not in FORMATS:
        raise InputError("--output", output, f"has extension {ext or '(none)'}",
                         "a file name ending in .onnx (an ONNX graph) or .py (a NumPy module)")
    if ext == ".onnx":
        from .onnx_model import require_onnx

        require_onnx("--output", output)
    elif steps is not None:
        raise InputError("--steps", str(steps), "is given for a NumPy module, whose rollout takes steps when called",
                         "no --steps with -o OUT.py (or an .onnx output)")
    if (graph_path is None) == (nodes is None):
        raise InputError("export", "--graph", "and --nodes are both given" if nodes else "nor --nodes is given",
                         "one of them: --graph DATA (the file's first graph) or --nodes N (a complete graph)")
    check_outputs({"--output": output}, [model_path] + ([graph_path] if graph_path else []))
    if claim is not None:
        claim()
    model = Model.load(model_path)
    if isinstance(model, Ensemble):
        raise InputError(model_path, "ensemble_size", f"is an ensemble of {model.size} models",
                         "one model's file (an exported module computes one rollout, not a mean and a spread)")
    graph = _graph(graph_path, nodes, model)
    model.check_nodes(graph.n_nodes, graph_path or "--nodes", "nodes")
    if ext == ".py":
        from .numpy_module import write_numpy_module

        write_numpy_module(model, graph, output)
        extra = "".join(f", {name}=None" for name, _ in _network_inputs(model, graph))
        return (f"wrote {output}: NumPy module, rollout(x0, steps, u=None{extra}) of the {model.kind} model on "
                f"{graph.n_nodes} nodes{_defaults(model, graph)}")
    from .onnx_model import write_onnx

    steps = 1 if steps is None else steps
    write_onnx(model, graph, output, steps)
    s, n = model.spec, graph.n_nodes
    du = s.control_dim - s.attr_dim
    u = f", u (B, {steps}, {n}, {du})" if du else ""
    more = "".join(f", {name} {shape}" for name, shape in _network_inputs(model, graph))
    return (f"wrote {output}: ONNX rollout of {steps} step(s) of the {model.kind} model on {n} nodes, "
            f"{model.dtype}: inputs x0 (B, {n}, {s.state_dim}){u}{more}; output x (B, {steps + 1}, "
            f"{n}, {s.state_dim}){_defaults(model, graph)}")


def _network_inputs(model, graph):
    """(name, shape) of the inputs a model of node attributes or weighted graphs adds."""
    out = [("node_attrs", f"(1 or B, {graph.n_nodes}, {model.spec.attr_dim})")] if model.spec.attr_dim else []
    if model.spec.aggregation.weight_scale is not None and model.kind != "node":
        out.append(("edge_weights", f"({graph.n_edges},)"))
    return out


def _defaults(model, graph):
    """What those inputs default to, as a sentence's end ("" without them)."""
    said = {"node_attrs": f"node_attrs the training mean of {', '.join(model.attr_names)}",
            "edge_weights": "edge_weights the graph's" + ("" if graph.weighted else " (1 on every edge)")}
    parts = [said[name] for name, _ in _network_inputs(model, graph)]
    return f"; defaults: {', '.join(parts)}" if parts else ""


def _graph(graph_path, nodes, model):
    """The graph to export for; its weights left out for a model trained on unweighted graphs."""
    if nodes is not None:
        return Graph.complete(nodes)
    from mpnode.data import read_trajectories

    graph = read_trajectories(graph_path).graphs[0]
    return graph if model.spec.aggregation.weight_scale is not None else graph.reweighted(None)

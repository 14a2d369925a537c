"""What a model hears of a network beside the states: node attributes and edge weights.

A node's static attributes (a pendulum's length, an oscillator's natural frequency) reach the
network as control columns held over every step, after the controls: training, evaluation and
rollouts then treat them as they treat controls (normalised alike, their cotangents from the
same reverse pass).  Edge weights stay on the graph: the kernels weigh each neighbour's message
by its edge's weight over the model's ``weight_scale`` (mpnode.engine.spec.Aggregation).
"""
from dataclasses import replace

import numpy as np

from mpnode.base.errors import InputError


def attrs_as_controls(traj):
    """``traj`` with its node attributes appended to its controls, held over every step (and named
    after them in ``control_names``); ``traj`` itself when it has none."""
    if traj.node_attrs is None:
        return traj
    b, t, n = traj.n_trajectories, traj.horizon, traj.n_nodes
    held = np.broadcast_to(np.asarray(traj.node_attrs, dtype=np.float64)[:, None], (b, t, n, traj.attr_dim))
    u = held if traj.u is None else np.concatenate([np.asarray(traj.u, dtype=np.float64), held], axis=3)
    attrs = dict(traj.attrs)
    names = list(attrs.get("control_names", [f"u[{i}]" for i in range(traj.control_dim)]))
    attrs["control_names"] = names + list(traj.attr_names)
    return replace(traj, u=np.ascontiguousarray(u), node_attrs=None, attr_names=None, attrs=attrs)


def without_attrs(traj):
    """``traj`` as data of identical nodes on unweighted graphs: attributes and weights left out."""
    if traj.node_attrs is None and not traj.weighted:
        return traj
    return replace(traj, node_attrs=None, attr_names=None, graphs=[g.reweighted(None) for g in traj.graphs])


def weight_scale(datasets):
    """The mean size |w| of the edge weights of ``datasets``' graphs (what the model divides them
    by), or None when no graph is weighted."""
    weights = [np.abs(g.weights) for traj in datasets for g in traj.graphs if g.weights is not None]
    if not weights:
        return None
    w = np.concatenate(weights)
    scale = float(np.mean(w)) if w.size else 1.0
    return scale if scale > 0 else 1.0


def attr_names_of(datasets, sources):
    """The node attributes' names, the same in every file (InputError naming the file that differs)."""
    first = list(datasets[0].attr_names or [])
    for traj, src in zip(datasets[1:], sources[1:]):
        names = list(traj.attr_names or [])
        if names != first:
            raise InputError(src, "attr_names", f"are {names or 'none'} but {sources[0]} has {first or 'none'}",
                             "files of one system: the same node attributes, in the same order")
    if len({bool(traj.weighted) for traj in datasets}) > 1:
        src = next(s for traj, s in zip(datasets, sources) if traj.weighted != datasets[0].weighted)
        raise InputError(src, "graphs/weights", "differ from the first file's in having edge weights",
                         "every training file weighted, or none")
    return first


def check_training_inputs(model, data):
    """InputError unless ``data`` (a TrainingData) has the node attributes and the weighting that
    ``model`` was trained with (fine-tuning continues the model it is given)."""
    src = data.sources[0]
    if data.attr_names != model.attr_names:
        raise InputError(src, "node_attrs", f"are {', '.join(data.attr_names) or 'none'}",
                         f"the node attributes the model was trained with: {', '.join(model.attr_names) or 'none'}")
    if (data.weight_scale is None) != (model.spec.aggregation.weight_scale is None) and model.kind != "node":
        has = "weighted" if data.weight_scale is not None else "unweighted"
        raise InputError(src, "graphs/weights", f"are {has}, unlike the graphs the model was trained on",
                         "training data weighted as the model's were (trajectory format version 3 holds weights)")


def for_model(model, traj, source, ignore_attrs=False):
    """``traj`` as ``model`` hears it (attributes as controls) after checking that its attributes and
    weights are the model's; ``ignore_attrs`` leaves out attributes and weights a model without
    them was not trained with.  InputError naming ``source`` and the field otherwise."""
    have, want = list(traj.attr_names or []), model.attr_names
    weighted_model = model.spec.aggregation.weight_scale is not None
    if have and not want:
        if not ignore_attrs:
            raise InputError(source, "node_attrs", f"holds node attributes ({', '.join(have)}) but the model was "
                             "trained without any", "data without node attributes, or --ignore-attrs to leave them out")
        traj = replace(traj, node_attrs=None, attr_names=None)
    elif want and have != want:
        raise InputError(source, "node_attrs", f"are {', '.join(have) if have else 'missing'}",
                         f"the node attributes the model was trained with: {', '.join(want)}, in that order")
    if model.kind == "node":  # a whole-system NODE sees every node at once and no edge: weights or none, as in training
        return attrs_as_controls(traj)
    if traj.weighted and not weighted_model:
        if not ignore_attrs:
            raise InputError(source, "graphs/weights", "holds edge weights but the model was trained on unweighted "
                             "graphs", "unweighted graphs, or --ignore-attrs to leave the weights out")
        traj = replace(traj, graphs=[g.reweighted(None) for g in traj.graphs])
    elif weighted_model and not traj.weighted:
        raise InputError(source, "graphs/weights", "are missing, but the model was trained on weighted graphs",
                         "graphs with a weight on every edge (trajectory format version 3)")
    return attrs_as_controls(traj)

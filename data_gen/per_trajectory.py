"""What each trajectory of a scene draws for itself: its graph (a scene of `GraphDraws`), the
weights of its edges and the attributes of its nodes (the systems whose nodes and edges differ,
docs/systems.md#networks-whose-nodes-and-edges-differ).

Trajectory b draws them from its own generator, `parameter_rng` (seed, b) =
``SeedSequence(seed, spawn_key=(b, 1))``: like its initial state (spawn_key ``(b,)``), they
depend on the scene's seed and b alone, not on the workers or on B, and the fresh seed of a
test set draws fresh ones.  Scenes whose trajectories draw nothing keep their few shared graphs.
"""
from dataclasses import dataclass, field

import numpy as np

from .graphs import GraphDraws
from .systems import get_system


@dataclass
class SceneGraphs:
    """The graphs of a scene's trajectories and what their nodes carry.

    graphs : list of Graph (weighted where the system's edges differ);  graph_index : (B,)
    node_attrs : (B, N, dp) or None;  attr_names : dp names
    attrs, aux : what the file records of how they were made (root attributes, aux datasets)
    """

    graphs: list
    graph_index: np.ndarray
    attrs: dict
    aux: dict = field(default_factory=dict)
    node_attrs: np.ndarray = None
    attr_names: tuple = ()

    def trajectory_fields(self):
        """The node attributes as Trajectories takes them; nothing when the nodes are alike."""
        if self.node_attrs is None:
            return {}
        return {"node_attrs": self.node_attrs, "attr_names": list(self.attr_names)}


def parameter_rng(seed, b):
    """The generator of trajectory b's graph, weights and node attributes (module docstring)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(b, 1)))


def scene_graphs(scene):
    """The SceneGraphs of ``scene``: its built graphs, trajectory b on graph b mod G, when nothing is
    drawn per trajectory; else one graph per trajectory, drawn as the module docstring says; a
    scene on a whole network (data_gen.grids.GridCase) runs every trajectory on its one graph and
    attributes."""
    system = get_system(scene.system)
    B = scene.trajectories
    scalars = {**system.defaults, **scene.params}
    if hasattr(scene.graph, "network"):  # a whole network given (a real grid): every trajectory runs on it
        graph, attrs, record = scene.graph.network(scalars, scene.name)
        return SceneGraphs([graph], np.zeros(B, dtype=np.int64), {**scene.graph.describe(), **record},
                           node_attrs=np.repeat(attrs[None], B, axis=0), attr_names=system.attr_names)
    drawn = isinstance(scene.graph, GraphDraws)
    if not drawn and system.draw_trajectory is None:
        graphs = scene.graph.build()
        return SceneGraphs(graphs, np.arange(B) % len(graphs), scene.graph.describe())
    fixed = None if drawn else scene.graph.build()
    graphs, picks, attrs = zip(*(_trajectory(scene, system, scalars, fixed, b) for b in range(B)))
    out = SceneGraphs(list(graphs), np.arange(B), scene.graph.describe())
    if drawn:
        out.aux = {"graph_family": np.array([p[0] for p in picks], dtype=np.int64),
                   "graph_seed": np.array([p[1] for p in picks], dtype=np.int64)}
    if system.draw_trajectory is not None:
        out.node_attrs, out.attr_names = np.stack(attrs).astype(np.float64), system.attr_names
    return out


def _trajectory(scene, system, scalars, fixed, b):
    """(graph, (family, networkx seed) or None, node attributes or None) of trajectory b: its graph
    drawn or graph b mod G of ``fixed``, weighted by the system's draw."""
    rng = parameter_rng(scene.seed, b)
    if fixed is None:
        graph, family, seed = scene.graph.draw(rng)
        pick = (family, seed)
    else:
        graph, pick = fixed[b % len(fixed)], None
    if system.draw_trajectory is None:
        return graph, pick, None
    weights, node = system.draw_trajectory(scalars, graph, rng)
    return graph.reweighted(weights), pick, node

"""Initial-state samplers: ``sampler(rng, system, n_nodes) -> x0, shape (N, dx)``.

A sampler draws only from the generator it is given, so a trajectory's initial state
depends on its own seed alone (not on the worker or on the other trajectories).
"""
import math

import numpy as np

from mpnode.base.errors import InputError

from .swing import disturbed


def uniform(rng, system, n_nodes):
    """The spec's default: every coordinate uniform in (system.low, system.high) per dimension; a
    system that keeps them otherwise (kuramoto_het: a phase as its cosine and sine) maps them
    with its ``state_of``."""
    x = rng.uniform(system.low, system.high, size=(n_nodes, len(system.low)))
    return x if system.state_of is None else system.state_of(x)


def hotspots(rng, system, n_nodes):
    """Gene: three random rectangles of the sqrt(N) x sqrt(N) grid at uniform(30, 50), zero elsewhere.

    Rectangles may overlap; each covers rows r0..r1 and columns c0..c1 (inclusive) with the
    corners drawn uniformly on the grid.  Nodes are numbered row after row.
    """
    side = math.isqrt(n_nodes)
    grid = np.zeros((side, side))
    for _ in range(3):
        r0, r1 = np.sort(rng.integers(0, side, size=2))
        c0, c1 = np.sort(rng.integers(0, side, size=2))
        grid[r0:r1 + 1, c0:c1 + 1] = rng.uniform(30.0, 50.0, size=(r1 - r0 + 1, c1 - c0 + 1))
    return grid.reshape(n_nodes, 1)


SAMPLERS = {"uniform": uniform, "hotspots": hotspots, "disturbed": disturbed}


def draw_initial(sampler, rng, system, graph, node_attrs, params):
    """x0 (N, dx) of one trajectory on ``graph``; a sampler that starts from the network's own state
    (``needs_network``: swing's operating point) also gets the graph, the trajectory's node
    attributes (N, dp) and the scalar parameters."""
    if getattr(sampler, "needs_network", False):
        return sampler(rng, system, graph.n_nodes, graph=graph, node_attrs=node_attrs, params=params)
    return sampler(rng, system, graph.n_nodes)


def get_sampler(name, system, n_nodes, source, field):
    """The sampler called ``name``, checked to make sense for ``system`` on ``n_nodes`` nodes."""
    if name not in system.samplers:
        raise InputError(source, field, f"sampler {name!r} is not defined for {system.name}",
                         "one of " + ", ".join(system.samplers))
    if name == "hotspots" and math.isqrt(n_nodes) ** 2 != n_nodes:
        raise InputError(source, field, f"hotspots needs a square grid but N = {n_nodes}", "N a perfect square")
    return SAMPLERS[name]


def trajectory_rng(seed, b):
    """The generator of trajectory b: SeedSequence(seed, spawn_key=(b,)) -- trajectory b's
    randomness depends on the seed and b alone (not on workers, chunks or B)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(b,)))


def initial_states(scene):
    """(x0 (B, N, dx), graphs, graph_index (B,)) of ``scene``, drawn exactly as `generate` draws
    them: trajectory b from `trajectory_rng` (seed, b) with the scene's sampler, on graph b mod G
    (or, where trajectories draw their own, on its weighted graph: data_gen.per_trajectory)."""
    from .per_trajectory import scene_graphs
    from .systems import get_system

    system = get_system(scene.system)
    if system.generator is not None:
        raise InputError(scene.name, "system", f"{system.name} is a closed-loop system whose initial states come "
                         "with its controls", "a scene of a system without controls")
    made = scene_graphs(scene)
    graphs, gi = made.graphs, made.graph_index
    sampler = get_sampler(scene.initial, system, scene.graph.n_nodes, scene.name, "initial")
    params = {**system.defaults, **scene.params}
    attrs = made.node_attrs if made.node_attrs is not None else [None] * scene.trajectories
    x0 = np.stack([draw_initial(sampler, trajectory_rng(scene.seed, b), system, graphs[gi[b]], attrs[b], params)
                   for b in range(scene.trajectories)])
    return x0, graphs, gi


def closed_loop_start(scene):
    """(x0 (B, N, dx), graphs, graph_index (B,), controls) of a closed-loop scene: its initial states
    and its controller, controls(k, x (B, N, dx)) -> u (B, N, du), drawn as `generate` draws them,
    to run a learned model in the scene's loop."""
    from .systems import get_system

    system = get_system(scene.system)
    if system.controllers is None:
        raise InputError(scene.name, "system", f"{system.name} has no controller", "a closed-loop scene")
    graphs = scene.graph.build()
    x0, controls = system.controllers(scene)
    return x0, graphs, np.arange(scene.trajectories) % len(graphs), controls

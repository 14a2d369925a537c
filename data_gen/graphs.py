"""Graphs the reference systems run on, built with networkx from a seed and kept as CSR.

A `GraphSpec` names a builder and its arguments, so a scene (and the file it produces)
says exactly which call made each graph; `build` returns `mpnode.base.graph.Graph` objects
(CSR: sparse graphs stay sparse).
"""
from dataclasses import dataclass, field, replace

import networkx as nx
import numpy as np

from mpnode.base.errors import InputError
from mpnode.base.graph import Graph

#: the most lines a bus of power_grid_graph has (the IEEE 300-bus case's busiest has 11)
GRID_MAX_DEGREE = 12
#: the mean degree of power_grid_graph is uniform in this range (the IEEE cases': 2.4 to 3.0)
GRID_MEAN_DEGREE = (2.2, 3.2)


def power_grid_graph(n, seed=None):
    """A random connected grid of n buses, meshed as transmission grids are: a tree grown by
    attaching each new bus to one before it with probability proportional to its degree + 1, then
    lines between buses two or three lines apart (local loops) up to a mean degree uniform in
    GRID_MEAN_DEGREE; no bus gets more than GRID_MAX_DEGREE lines.  A networkx Graph."""
    rng = np.random.default_rng(seed)
    g = nx.empty_graph(n)
    degree = np.zeros(n)
    for k in range(1, n):
        w = np.where(degree[:k] < GRID_MAX_DEGREE, degree[:k] + 1, 0)
        i = int(rng.choice(k, p=w / w.sum()))
        g.add_edge(k, i)
        degree[[k, i]] += 1
    target = max(n - 1, round(rng.uniform(*GRID_MEAN_DEGREE) * n / 2))
    for _ in range(100 * n):  # each try closes a loop, unless the bus drawn has no room or no bus near
        if g.number_of_edges() >= target:
            break
        u = int(rng.integers(n))
        near = [v for v, d in nx.single_source_shortest_path_length(g, u, cutoff=3).items()
                if d >= 2 and degree[v] < GRID_MAX_DEGREE]
        if near and degree[u] < GRID_MAX_DEGREE:
            v = near[int(rng.integers(len(near)))]
            g.add_edge(u, v)
            degree[[u, v]] += 1
    return g


#: builder -> (graph function, names of its arguments after n, in call order)
RANDOM_BUILDERS = {
    "gnp": (nx.gnp_random_graph, ("p",)),
    "gnm": (nx.gnm_random_graph, ("m",)),
    "barabasi_albert": (nx.barabasi_albert_graph, ("m",)),
    "watts_strogatz": (nx.watts_strogatz_graph, ("k", "p")),
    "power_grid": (power_grid_graph, ()),
}
#: builders that need no seed: every node hears every other, or an explicit edge list
FIXED_BUILDERS = ("complete", "edges")
BUILDERS = tuple(RANDOM_BUILDERS) + FIXED_BUILDERS


@dataclass(frozen=True)
class GraphSpec:
    """How to build the graph(s) of a scene.

    builder : one of BUILDERS
    n_nodes : N
    args : the builder's arguments after N, e.g. {"k": 5, "p": 0.5} for watts_strogatz
    seeds : one networkx seed per graph (random builders); a file gets one graph per seed
    edges : (sender, receiver) pairs, shape (E, 2), for builder "edges"
    directed : for "edges": False adds each pair in both directions
    """

    builder: str
    n_nodes: int
    args: dict = field(default_factory=dict)
    seeds: tuple = ()
    edges: tuple = ()
    directed: bool = False

    @property
    def n_graphs(self):
        return len(self.seeds) if self.builder in RANDOM_BUILDERS else 1

    def calls(self):
        """One human-readable line per graph saying exactly how it was built."""
        if self.builder == "complete":
            return [f"complete graph on {self.n_nodes} nodes, no self-loops"]
        if self.builder == "edges":
            kind = "directed" if self.directed else "undirected"
            return [f"{kind} edge list on {self.n_nodes} nodes: {[list(e) for e in self.edges]}"]
        return [self.call(s) for s in self.seeds]

    def call(self, seed):
        """The networkx call of a random builder with ``seed`` (a number, or where it is kept)."""
        fn, names = RANDOM_BUILDERS[self.builder]
        args = "".join(f"{a}={self.args[a]!r}, " for a in names)
        module = "networkx" if fn.__module__.startswith("networkx") else fn.__module__
        return f"{module}.{fn.__name__}(n={self.n_nodes}, {args}seed={seed})"

    def build(self):
        """The graphs, one per seed (or the single fixed graph): list of Graph."""
        if self.builder == "complete":
            return [Graph.complete(self.n_nodes)]
        if self.builder == "edges":
            # Graph.from_edges takes (receiver, sender); a scene lists (sender, receiver)
            pairs = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)[:, ::-1]
            return [Graph.from_edges(self.n_nodes, pairs, directed=self.directed)]
        fn, names = RANDOM_BUILDERS[self.builder]
        return [Graph.from_networkx(fn(self.n_nodes, *(self.args[a] for a in names), seed=s)) for s in self.seeds]

    def describe(self):
        """Root attributes recording what was built (the CSR itself goes to graphs/<g>)."""
        out = {"graph_builder": self.builder, "graph_calls": self.calls()}
        if self.builder in RANDOM_BUILDERS:
            out["graph_seeds"] = np.asarray(self.seeds, dtype=np.int64)
            out.update({f"graph_{a}": v for a, v in self.args.items()})
        if self.builder == "watts_strogatz":
            # networkx joins each node to k//2 neighbours per side: an odd k builds a ring of degree k-1
            out["graph_ring_degree"] = 2 * (self.args["k"] // 2)
        return out


@dataclass(frozen=True)
class GraphDraws:
    """A random graph of its own for every trajectory, so that a model meets many graphs of a
    family, not a few.

    families : GraphSpec of random builders on the same N, their seeds unused: trajectory b picks
        one uniformly and a networkx seed, both from its own generator (data_gen.per_trajectory)
    """

    families: tuple
    builder = "per_trajectory"

    @property
    def n_nodes(self):
        return self.families[0].n_nodes

    def draw(self, rng):
        """(Graph, family index, networkx seed) of one trajectory, from its generator ``rng``."""
        family = int(rng.integers(len(self.families)))
        seed = int(rng.integers(2**31))
        return replace(self.families[family], seeds=(seed,)).build()[0], family, seed

    def calls(self):
        """One line per family: its networkx call, the seed that of the trajectory."""
        return [spec.call("aux/graph_seed[b]") for spec in self.families]

    def describe(self):
        """Root attributes recording the families (each trajectory's pick: aux/graph_family, graph_seed)."""
        return {"graph_builder": self.builder, "graph_calls": self.calls()}


def symmetric_weights(graph, low, high, rng):
    """(E,) edge weights uniform in [low, high], one draw per pair of nodes (pairs in sorted order),
    so that an undirected edge weighs the same in both rows, as a spring or a mutual coupling does."""
    pairs = np.sort(graph.edges(), axis=1)
    unique, which = np.unique(pairs, axis=0, return_inverse=True)
    return rng.uniform(low, high, size=len(unique))[which.reshape(-1)]


def check_args(builder, args, source, field):
    """Raise InputError unless ``args`` are exactly the arguments ``builder`` takes."""
    if builder not in BUILDERS:
        raise InputError(source, field, f"unknown graph builder {builder!r}", "one of " + ", ".join(BUILDERS))
    wanted = set(RANDOM_BUILDERS[builder][1]) if builder in RANDOM_BUILDERS else set()
    if set(args) != wanted:
        raise InputError(source, field, f"{builder} got arguments {sorted(args)}",
                         f"exactly {sorted(wanted)}" if wanted else "no further arguments")


# ---- the spec's graphs (systems.md) ------------------------------------------------
def gene_graph(kind, n_nodes, seeds):
    """gene: er = gnp(N, 0.5), ba = barabasi_albert(N, N/2), ws = watts_strogatz(N, N/2, 0.5)."""
    half = n_nodes // 2
    return {
        "er": GraphSpec("gnp", n_nodes, {"p": 0.5}, tuple(seeds)),
        "ba": GraphSpec("barabasi_albert", n_nodes, {"m": half}, tuple(seeds)),
        "ws": GraphSpec("watts_strogatz", n_nodes, {"k": half, "p": 0.5}, tuple(seeds)),
    }[kind]


def kuramoto_graph(kind, n_nodes, seeds):
    """kuramoto: ba = barabasi_albert(N, 5), er = gnm(N, 5) (5 edges), ws = watts_strogatz(N, 5, 0.5)."""
    return {
        "er": GraphSpec("gnm", n_nodes, {"m": 5}, tuple(seeds)),
        "ba": GraphSpec("barabasi_albert", n_nodes, {"m": 5}, tuple(seeds)),
        "ws": GraphSpec("watts_strogatz", n_nodes, {"k": 5, "p": 0.5}, tuple(seeds)),
    }[kind]

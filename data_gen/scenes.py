"""Scenes: everything that decides a generated data set, by name or from a TOML file.

A Scene is system + parameters + graph + initial-state sampler + B, T, dt + seeds.
The built-in scenes are the data sets of the MP-NODE paper (docs/systems.md), and networks whose
nodes and edges differ, each trajectory drawing its own (data_gen.per_trajectory); a scene set
(``SETS``) names several of them whose files are trained on together.
Anything else is a TOML file with this schema (example: scenes/example_gene_ring.toml)::

    description  = "one line"   # optional
    system       = "gene"       # required: coupled_pendulum | coupled_pendulum_force | spring_pendulums |
                                #   spring_pendulums_het | lorenz | gene | kuramoto | kuramoto_het | swing |
                                #   quadrotor_load
    trajectories = 1000         # optional, B >= 1
    horizon      = 50           # optional, T >= 1 steps
    dt           = 0.05         # optional, > 0
    seed         = 0            # optional, initial states (trajectory b uses spawn_key (b,)), and what each
                                # trajectory draws for itself (spawn_key (b, 1): weights, node attributes)
    system_seed  = 0            # optional, drawn parameters shared by all (lorenz H, kuramoto omega)
    initial      = "uniform"    # optional: uniform (the spec's ranges) | hotspots (gene, square N)
                                # | equilibrium (quadrotor_load, which must say so)
                                # | disturbed (swing, which must say so: its operating point, disturbed)
    integrator   = "DOP853"     # optional: a scipy solve_ivp method
    rtol         = 1e-9         # optional
    atol         = 1e-9         # optional
    excitation   = 0.5          # optional, quadrotor_load only (default 0): std (N) of a random offset
                                # of each quadrotor's collective thrust, held for a few steps, so
                                # that the data show what the thrusts do apart from the state
    [params]                    # optional: the system's scalar parameters, spec names (e.g. b, f, h; the
                                # ranges a trajectory draws from, e.g. l_min, l_max)
    [graph]                     # required
    builder  = "edges"          # complete | edges | gnp | gnm | barabasi_albert | watts_strogatz | power_grid
    nodes    = 8                # N
    edges    = [[0, 1], [1, 2]] # edges only: [sender, receiver] pairs
    directed = false            # edges only, optional: false adds both directions
    seeds    = [1, 2]           # random builders: one graph per seed (or seed = 1)
    p = 0.5; m = 5; k = 4       # random builders: their networkx arguments (gnp: p, gnm: m,
                                # barabasi_albert: m, watts_strogatz: k, p)

Unknown keys, wrong types and missing keys raise InputError(file, key, problem, expected).
"""
import math
import os
from dataclasses import dataclass, field, replace

from mpnode.base.errors import InputError
from mpnode.base.memory import check_memory
from mpnode.base.tomlfile import load_toml

from .graphs import (
    BUILDERS,
    RANDOM_BUILDERS,
    GraphDraws,
    GraphSpec,
    check_args,
    gene_graph,
    kuramoto_graph,
)
from .grids import CASES, GridCase
from .initial import get_sampler
from .systems import get_system

#: the scipy solve_ivp methods a scene may name
INTEGRATORS = ("RK23", "RK45", "DOP853", "Radau", "BDF", "LSODA")
#: memory per state entry of a scene's trajectories: float64 states, and as much again for the
#: checks and copies on the way to the file (mpnode.base.memory)
BYTES_PER_ENTRY = 16


@dataclass(frozen=True)
class Scene:
    """A data set to generate; see the module docstring for the meaning of each field."""

    name: str
    description: str
    system: str
    graph: GraphSpec
    params: dict = field(default_factory=dict)
    initial: str = "uniform"
    trajectories: int = 1000
    horizon: int = 50
    dt: float = 0.05
    seed: int = 0
    system_seed: int = 0
    integrator: str = "DOP853"
    rtol: float = 1e-9
    atol: float = 1e-9
    excitation: float = 0.0

    def summary(self):
        """One line for `mpnode scenes`."""
        return (f"{self.system}, N={self.graph.n_nodes}, B={self.trajectories}, T={self.horizon}, "
                f"dt={self.dt:g}: {self.description}")


def _lorenz(k, coupling, level, horizon=50):
    span = "" if horizon == 50 else f", {horizon * Scene.dt:g} s per trajectory"
    return Scene(f"lorenz{k}{level}", f"{k} Lorenz oscillators, linear coupling ||H||_F = {coupling:g}{span}",
                 "lorenz", GraphSpec("complete", k), {"coupling": coupling}, horizon=horizon)


def _gene(n, kind, seeds=(1,), initial="uniform"):
    multi = len(seeds) > 1
    graphs = f"{len(seeds)} {kind.upper()} graphs (seeds {seeds[0]}..{seeds[-1]})" if multi else f"{kind.upper()} graph"
    hot = initial == "hotspots"
    start = ", starting from three hot spots on the grid (the paper's NDCN setup)" if hot else ""
    return Scene(f"gene{n}_{kind}" + ("_multi" if multi else "") + ("_hot" if hot else ""),
                 f"Michaelis-Menten gene regulation on {n} nodes, {graphs}{start}", "gene",
                 gene_graph(kind, n, seeds), initial=initial)


def _kuramoto(kind):
    return Scene(f"kuramoto10_{kind}", f"10 Kuramoto nodes (3 phases each), {kind.upper()} graph",
                 "kuramoto", kuramoto_graph(kind, 10, (1,)))


def _kuramoto_het(n, families, what, suffix=""):
    return Scene(f"kuramoto_het{n}{suffix}", f"{n} Kuramoto oscillators of their own frequencies, coupled along "
                 f"weighted edges, on a fresh {what} graph per trajectory", "kuramoto_het", GraphDraws(families))


def _spring_pendulums_het(n):
    chain = GraphSpec("edges", n, edges=tuple((i, i + 1) for i in range(n - 1)))
    return Scene(f"spring_pendulums_het{n}", f"a chain of {n} pendulums of their own lengths and masses, joined by "
                 "springs of their own stiffness, all drawn per trajectory", "spring_pendulums_het", chain)


def _grid(n):
    return Scene(f"grid{n}", f"a random connected power grid of {n} buses (swing equation), its lines, powers and "
                 "machines drawn per trajectory, disturbed from its operating point", "swing",
                 GraphDraws((GraphSpec("power_grid", n),)), initial="disturbed", horizon=100)


def _ieee(number):
    return Scene(f"ieee{number}", f"the IEEE {number}-bus case (swing equation; PYPOWER, the extra grids), disturbed "
                 "from its operating point", "swing", GridCase(number, CASES[number]), initial="disturbed",
                 horizon=100)


def _quad(n):
    return Scene(f"quad{n}", f"{n} quadrotors carry a cable-suspended load towards a doorway (closed loop, "
                 "5 s of the 10 s transport)", "quadrotor_load", GraphSpec("complete", n), initial="equilibrium",
                 horizon=50, dt=0.1, integrator="LSODA", rtol=1e-9, atol=1e-9)


BUILTIN = {
    s.name: s
    for s in [
        Scene("coupled_pendulum", "two pendulums joined by a spring", "coupled_pendulum",
              GraphSpec("edges", 2, edges=((0, 1),))),
        Scene("pendulum_force", "the coupled pendulums pushed by random horizontal forces on the bobs (controls)",
              "coupled_pendulum_force", GraphSpec("edges", 2, edges=((0, 1),))),
        _lorenz(3, 0.01, ""), _lorenz(7, 0.01, ""), _lorenz(10, 0.01, ""),
        _lorenz(10, 1.0, "_medium"), _lorenz(10, 5.0, "_high"), _lorenz(10, 0.01, "_10s", horizon=200),
        *(_gene(n, kind) for n in (16, 64) for kind in ("er", "ba", "ws")),
        _gene(16, "ba", seeds=(1, 2, 3, 4, 5)),
        *(_gene(n, kind, initial="hotspots") for n in (16, 64) for kind in ("er", "ba", "ws")),
        _gene(16, "ba", seeds=(1, 2, 3, 4, 5), initial="hotspots"),
        *(_kuramoto(kind) for kind in ("er", "ba", "ws")),
        _kuramoto_het(10, (GraphSpec("gnp", 10, {"p": 0.4}), GraphSpec("watts_strogatz", 10, {"k": 4, "p": 0.3})),
                      "Erdos-Renyi or Watts-Strogatz"),
        _kuramoto_het(50, (GraphSpec("barabasi_albert", 50, {"m": 2}),), "Barabasi-Albert", "_ba"),
        _spring_pendulums_het(4), _spring_pendulums_het(10),
        *(_grid(n) for n in (10, 20, 30, 40)), *(_ieee(number) for number in CASES),
        *(_quad(n) for n in (3, 4, 5, 6, 8, 12)),
    ]
}


@dataclass(frozen=True)
class SceneSet:
    """Several built-in scenes whose data are trained on together: one file per member (a
    trajectory file holds one node count), e.g. swarms of 3, 4 and 5 quadrotors, which is what
    carries a module to a swarm size it has not seen (docs/scenes.md, "Scene sets").

    members : ((scene name, trajectories), ...);  test : the scene `mpnode train SET` evaluates
    the model on at the end (a size none of the members has)
    """

    name: str
    description: str
    members: tuple
    test: str

    def scenes(self, trajectories=None, seed=None, **overrides):
        """The member scenes, each with its own trajectories (or ``trajectories`` for every one)
        and member i with seed ``seed + i`` (default: the scene's own seed + i), so that no two
        files share a draw; ``overrides`` (horizon, dt) apply to every member."""
        out = []
        for i, (name, count) in enumerate(self.members):
            scene = BUILTIN[name]
            out.append(replace(scene, trajectories=trajectories or count,
                               seed=(scene.seed if seed is None else seed) + i, **overrides))
        return out

    def summary(self):
        """One line for `mpnode scenes`."""
        parts = ", ".join(f"{name} x {count}" for name, count in self.members)
        return f"scene set: {parts}; evaluated on {self.test}: {self.description}"


#: the built-in scene sets (name -> SceneSet)
SETS = {
    s.name: s
    for s in [
        SceneSet("quad3-5", "one module for any swarm size, trained on 3, 4 and 5 carriers",
                 (("quad3", 500), ("quad4", 300), ("quad5", 300)), test="quad6"),
        SceneSet("grids10-30", "one bus module for any power grid, trained on random grids of 10, 20 and 30 buses",
                 (("grid10", 400), ("grid20", 300), ("grid30", 300)), test="grid40"),
    ]
}


def load_scene(name_or_path):
    """A built-in scene by name, or the scene in a TOML file (a path ending in .toml)."""
    if name_or_path in BUILTIN:
        return BUILTIN[name_or_path]
    if str(name_or_path).endswith(".toml"):
        return read_scene(name_or_path)
    if name_or_path in SETS:
        raise InputError("SCENE", name_or_path, "is a scene set (several files), which this command does not take",
                         "one of its scenes: " + ", ".join(name for name, _ in SETS[name_or_path].members))
    raise InputError("SCENE", name_or_path, "is neither a built-in scene nor a .toml file",
                     "one of " + ", ".join(BUILTIN) + " (see `mpnode scenes`), or a path to a .toml scene")


def check_scene(scene, source):
    """Raise InputError(source, key, ...) unless ``scene`` can be generated (graphs not built)."""
    system = get_system(scene.system, source, "system")
    for key, value in scene.params.items():
        if key not in system.defaults:
            raise InputError(source, f"params.{key}", f"is not a parameter of {system.name}",
                             "one of " + ", ".join(system.defaults))
    _check_graph(scene.graph, source)
    for key, value in (("trajectories", scene.trajectories), ("horizon", scene.horizon),
                       ("graph.nodes", scene.graph.n_nodes)):
        if value < 1:
            raise InputError(source, key, f"is {value}", "an integer >= 1")
    for key, value in (("dt", scene.dt), ("rtol", scene.rtol), ("atol", scene.atol)):
        if not (value > 0 and math.isfinite(value)):
            raise InputError(source, key, f"is {value}", "a finite number > 0")
    if not math.isfinite(scene.dt * scene.horizon):
        raise InputError(source, "dt", f"times horizon {scene.horizon} overflows", "a finite duration")
    system.check_dt(scene.params, scene.dt, source)
    entries = scene.trajectories * (scene.horizon + 1) * scene.graph.n_nodes * system.state_dim
    check_memory(entries * BYTES_PER_ENTRY, source, "trajectories", f"B = {scene.trajectories} trajectories of "
                 f"T = {scene.horizon} steps on {scene.graph.n_nodes} nodes", "fewer trajectories (-B, --trajectories) "
                 "or a shorter horizon (-T, --horizon)")
    for key, value in (("seed", scene.seed), ("system_seed", scene.system_seed)):
        if value < 0:  # numpy's SeedSequence takes non-negative integers only
            raise InputError(source, key, f"is {value}", "an integer >= 0")
    for key, value in scene.params.items():
        if not math.isfinite(value):
            raise InputError(source, f"params.{key}", f"is {value}", "a finite number")
    for spec in _graph_families(scene.graph):
        _check_graph_ranges(spec, source)
    system.check_ranges(scene.params, source)
    if scene.integrator not in INTEGRATORS:
        raise InputError(source, "integrator", f"unknown method {scene.integrator!r}",
                         "one of " + ", ".join(INTEGRATORS))
    _check_excitation(scene.excitation, system, source)
    if system.generator is None:
        get_sampler(scene.initial, system, scene.graph.n_nodes, source, "initial")
    elif scene.initial not in system.samplers:  # closed-loop systems draw their own initial states
        raise InputError(source, "initial", f"initial state {scene.initial!r} is not defined for {system.name}",
                         "one of " + ", ".join(system.samplers))


def _check_excitation(value, system, source):
    """The thrust excitation: a finite number >= 0, and above 0 only for the quadrotors' thrusts."""
    if not (value >= 0 and math.isfinite(value)):
        raise InputError(source, "excitation", f"is {value}", "a finite number >= 0 (N)")
    if value > 0 and system.name != "quadrotor_load":
        raise InputError(source, "excitation", f"is {value} for {system.name}, which has no thrusts to excite",
                         "0, or a quadrotor_load scene")


def _graph_families(graph):
    """The GraphSpecs of a scene's graph: each family a GraphDraws picks from, or the one spec (none for a
    real grid, which is checked when it is read)."""
    if isinstance(graph, GridCase):
        return ()
    return graph.families if isinstance(graph, GraphDraws) else (graph,)


def _check_graph(graph, source):
    """The builders' arguments and seeds of a scene's graph (a GraphDraws: random builders on one N)."""
    drawn = isinstance(graph, GraphDraws)
    for spec in _graph_families(graph):
        check_args(spec.builder, spec.args, source, "graph")
        if drawn and (spec.builder not in RANDOM_BUILDERS or spec.n_nodes != graph.n_nodes):
            raise InputError(source, "graph", f"draws from {spec.builder} on {spec.n_nodes} nodes",
                             f"random builders on {graph.n_nodes} nodes each")
        if spec.builder in RANDOM_BUILDERS and not spec.seeds and not drawn:
            raise InputError(source, "graph.seeds", "is empty", "at least one seed")


def _check_graph_ranges(spec, source):
    """The random builders' arguments in the ranges networkx builds sensible graphs for."""
    n, args = spec.n_nodes, spec.args
    ranges = {"p": (0.0, 1.0, "a probability in [0, 1]"),
              "m": ((1, n - 1, f"an integer in 1..{n - 1} (N - 1)") if spec.builder == "barabasi_albert"
                    else (0, n * (n - 1) // 2, f"an integer in 0..{n * (n - 1) // 2} (all pairs)")),
              "k": (0, n, f"an integer in 0..{n} (N)")}
    for name, value in args.items():
        lo, hi, expected = ranges[name]
        if not lo <= value <= hi:  # NaN fails too
            raise InputError(source, f"graph.{name}", f"is {value} for {spec.builder} on {n} nodes", expected)


# ---- TOML -----------------------------------------------------------------------------
_TOP = {"description": str, "system": str, "trajectories": int, "horizon": int, "dt": float,
        "seed": int, "system_seed": int, "initial": str, "integrator": str, "rtol": float,
        "atol": float, "excitation": float, "params": dict, "graph": dict}
_GRAPH = {"builder": str, "nodes": int, "edges": list, "directed": bool, "seed": int, "seeds": list,
          "p": float, "m": int, "k": int}
_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", dict: "a table", list: "an array",
               bool: "true or false"}


def read_scene(path):
    """The Scene described by the TOML file ``path`` (schema in the module docstring)."""
    source = os.fspath(path)
    doc = load_toml(source, "a TOML scene file")
    _check_keys(doc, _TOP, source, "", required=("system", "graph"))
    g = doc["graph"]
    _check_keys(g, _GRAPH, source, "graph.", required=("builder", "nodes"))
    builder = g["builder"]
    if builder not in BUILDERS:
        raise InputError(source, "graph.builder", f"unknown builder {builder!r}", "one of " + ", ".join(BUILDERS))
    system = get_system(doc["system"], source, "system")
    params = doc.get("params", {})
    _check_keys(params, dict.fromkeys(system.defaults, float), source, "params.")
    scene = Scene(
        name=os.path.splitext(os.path.basename(source))[0],
        description=doc.get("description", f"scene file {source}"),
        system=system.name,
        graph=_graph_spec(g, source),
        params={k: float(v) for k, v in params.items()},
        **{k: (float(doc[k]) if _TOP[k] is float else doc[k])
           for k in ("initial", "trajectories", "horizon", "dt", "seed", "system_seed", "integrator", "rtol", "atol",
                     "excitation")
           if k in doc},
    )
    check_scene(scene, source)
    return scene


def _graph_spec(g, source):
    builder, n = g["builder"], g["nodes"]
    allowed = {"builder", "nodes"} | (
        {"edges", "directed"} if builder == "edges"
        else {"seed", "seeds", *RANDOM_BUILDERS[builder][1]} if builder in RANDOM_BUILDERS else set())
    for key in g:
        if key not in allowed:
            raise InputError(source, f"graph.{key}", f"does not apply to builder {builder!r}",
                             "only " + ", ".join(sorted(allowed)))
    if builder == "edges":
        edges = g.get("edges")
        if edges is None:
            raise InputError(source, "graph.edges", "is missing", "an array of [sender, receiver] pairs")
        for e in edges:
            if not (isinstance(e, list) and len(e) == 2 and all(_is(v, int) for v in e)):
                raise InputError(source, "graph.edges", f"contains {e!r}", "[sender, receiver] pairs of integers")
            if not all(0 <= v < n for v in e):
                raise InputError(source, "graph.edges", f"pair {e} names a node outside 0..{n - 1}",
                                 f"ids in 0..{n - 1}")
        return GraphSpec("edges", n, edges=tuple(map(tuple, edges)), directed=g.get("directed", False))
    if builder == "complete":
        return GraphSpec("complete", n)
    if ("seed" in g) == ("seeds" in g):
        raise InputError(source, "graph.seeds", "give exactly one of seed and seeds", "seed = 1 or seeds = [1, 2]")
    seeds = g["seeds"] if "seeds" in g else [g["seed"]]
    if not seeds or not all(_is(s, int) for s in seeds):
        raise InputError(source, "graph.seeds", f"is {seeds!r}", "a non-empty array of integers")
    names = RANDOM_BUILDERS[builder][1]
    missing = [a for a in names if a not in g]
    if missing:
        raise InputError(source, f"graph.{missing[0]}", "is missing", f"{builder} needs {', '.join(names)}")
    return GraphSpec(builder, n, {a: g[a] for a in names}, tuple(seeds))


def _is(value, kind):
    """TOML type check: bool is not an int, and an integer is a fine float."""
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def _check_keys(table, types, source, prefix, required=()):
    for key in required:
        if key not in table:
            raise InputError(source, prefix + key, "is missing", _TYPE_NAMES[types[key]])
    for key, value in table.items():
        if key not in types:
            raise InputError(source, prefix + key, "is not a known key", "one of " + ", ".join(types))
        if not _is(value, types[key]):
            raise InputError(source, prefix + key, f"is {value!r}", _TYPE_NAMES[types[key]])

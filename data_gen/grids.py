"""Real power grids: the IEEE test cases PYPOWER ships, turned into swing-equation networks
(data_gen.swing; docs/systems.md#the-ieee-cases).

PYPOWER (BSD, NumPy and SciPy only) is the optional extra ``grids``: it is imported only when a case
is read, so ``import mpnode`` and every other scene run without it.  A case is a dict of MATPOWER
tables (bus, branch, gen, baseMVA); any such dict converts (`case_network`), so a user's own case
works the same way.  Conversion: one node per bus; each in-service branch (line or transformer) a
line of susceptance 1 / x (per unit on the case's base), parallel branches adding; a bus's power
P_i = (in-service generation - load) / baseMVA, the imbalance (losses, or a dispatch that is only a
guess) put on the slack bus; a bus whose lines' susceptances add to 0 or less (the series
capacitor's middle bus in case300) is Kron-reduced away when it carries no power.
"""
from dataclasses import dataclass

import numpy as np

from mpnode.base.errors import InputError
from mpnode.base.graph import Graph

from .swing import grid_attrs, operating_point, pieces

#: the cases of the scenes: IEEE number -> buses kept (case300 loses its series capacitor's middle bus)
CASES = {14: 14, 30: 30, 39: 39, 57: 57, 118: 118, 300: 299}
EXTRA = "pip install 'mpnode[grids]'"
# MATPOWER's columns (pypower.idx_bus, idx_brch, idx_gen), fixed by the format
BUS_I, BUS_TYPE, PD = 0, 1, 2
F_BUS, T_BUS, BR_X, BR_STATUS = 0, 1, 3, 10
GEN_BUS, PG, GEN_STATUS = 0, 1, 7
SLACK, ISOLATED = 3, 4


def load_case(number, source):
    """PYPOWER's case dict of the IEEE ``number``-bus case; InputError naming the extra when PYPOWER
    is not installed."""
    try:
        from pypower import api
    except ImportError:
        raise InputError(source, "grid", f"the IEEE {number}-bus case comes from PYPOWER, which is not installed",
                         f"the extra grids: {EXTRA}") from None
    return getattr(api, f"case{number}")()


def bus_names(attrs, n):
    """["bus 1", "bus 2", ...]: a file's n buses by the numbers of the case they come from (the
    attribute grid_bus_numbers), or None when the file records none for n buses."""
    numbers = attrs.get("grid_bus_numbers")
    numbers = None if numbers is None else np.atleast_1d(numbers)
    if numbers is None or len(numbers) != n:
        return None
    return [f"bus {int(b)}" for b in numbers]


def case_network(case, source):
    """(weighted Graph of B_ij, balanced powers (N,), generator buses (N,) bool, record) of a
    MATPOWER-format case dict (module docstring).  InputError naming ``source`` and the field for an
    isolated bus, a branch of zero reactance, no slack bus, or a grid in several pieces.  record: root
    attributes saying what became of the case (bus numbers kept, buses removed, slack, imbalance)."""
    bus, branch, gen = (np.atleast_2d(np.asarray(case[k], dtype=np.float64)) for k in ("bus", "branch", "gen"))
    base = float(case["baseMVA"])
    numbers = bus[:, BUS_I].astype(np.int64)
    index = {int(b): i for i, b in enumerate(numbers)}
    B, pairs = _susceptances(branch, index, len(numbers), source)
    _check_buses(bus, pairs, numbers, source)
    power, generator = _powers(bus, gen, index, base)
    slack = _slack(bus, source)
    imbalance = power.sum()
    power[slack] -= imbalance
    B, power, generator, keep = _reduce(B, power, generator)
    graph = _graph(B)
    _check_connected(graph, source)
    record = {"grid_bus_numbers": numbers[keep], "grid_removed_buses": numbers[~keep],
              "grid_slack_bus": int(numbers[slack]), "grid_imbalance_on_slack": float(imbalance)}
    return graph, power, generator, record


def _susceptances(branch, index, n, source):
    """(B (N, N) dense, summed over parallel branches; (from, to) index pairs of the branches in service)."""
    B = np.zeros((n, n))
    on = branch[:, BR_STATUS] > 0 if branch.shape[1] > BR_STATUS else np.ones(len(branch), bool)
    pairs = []
    for k in np.flatnonzero(on):
        f, t, x = int(branch[k, F_BUS]), int(branch[k, T_BUS]), branch[k, BR_X]
        if f not in index or t not in index:
            raise InputError(source, f"branch {k}", f"joins bus {f} and bus {t}, not both in the bus table",
                             "branches between listed buses")
        if x == 0 or not np.isfinite(x):
            raise InputError(source, f"branch {k} (bus {f} - bus {t})/x", f"is {x}: a line of zero reactance "
                             "would carry any power at no angle", "a finite, non-zero reactance (pu)")
        i, j = index[f], index[t]
        if i != j:
            B[i, j] += 1 / x
            B[j, i] += 1 / x
            pairs.append((i, j))
    return B, pairs


def _check_buses(bus, pairs, numbers, source):
    """InputError for a bus no branch in service reaches, or one the case marks isolated (type 4)."""
    reached = np.zeros(len(numbers), bool)
    reached[np.asarray(pairs, dtype=np.int64).reshape(-1)] = True
    lonely = np.flatnonzero(~reached | (bus[:, BUS_TYPE] == ISOLATED))
    if len(lonely):
        raise InputError(source, "bus", f"bus {numbers[lonely[0]]} is isolated (no line in service reaches it)",
                         "a grid whose every bus has a line")


def _powers(bus, gen, index, base):
    """(P (N,) = (generation - load) / baseMVA, generator buses (N,) bool), generators in service only."""
    power = -bus[:, PD] / base
    generator = np.zeros(len(power), bool)
    for row in gen:
        if row[GEN_STATUS] > 0:
            i = index[int(row[GEN_BUS])]
            power[i] += row[PG] / base
            generator[i] = True
    return power, generator


def _slack(bus, source):
    """The index of the case's slack bus (type 3), which takes the imbalance."""
    slack = np.flatnonzero(bus[:, BUS_TYPE] == SLACK)
    if not len(slack):
        raise InputError(source, "bus", "has no slack bus (type 3) to put the imbalance of generation and load on",
                         "a case with one slack bus, as every MATPOWER case has")
    return int(slack[0])


def _reduce(B, power, generator):
    """Kron-reduce the buses whose lines' susceptances add to 0 or less and that carry no power:
    such a bus (a series capacitor's middle) cannot swing about a synchronous state, and its
    neighbours j, k see it as a line of B_ij B_ik / sum_l B_il.  Returns the reduced arrays and the
    kept buses (N,) bool."""
    keep = np.ones(len(power), bool)
    for i in np.flatnonzero((B.sum(axis=1) <= 0) & (power == 0)):
        s = B[i].sum()
        B = B + np.outer(B[i], B[i]) / s
        B[i, :] = B[:, i] = 0.0
        keep[i] = False
    np.fill_diagonal(B, 0.0)
    return B[keep][:, keep], power[keep], generator[keep], keep


def _graph(B):
    """The weighted graph of the lines B_ij != 0 (both directions)."""
    r, s = np.nonzero(B)
    return Graph.from_edges(len(B), np.stack([r, s], axis=1), directed=True, weights=B[r, s])


def _check_connected(graph, source):
    """InputError for a grid in several pieces (each would need its own balance and slack)."""
    count = pieces(graph)
    if count > 1:
        raise InputError(source, "branch", f"leaves the grid in {count} pieces", "one connected grid")


@dataclass(frozen=True)
class GridCase:
    """The graph of a scene on a real grid: the IEEE ``number``-bus case from PYPOWER, its lines'
    susceptances and its buses' attributes the same in every trajectory (nothing drawn).

    n_nodes : the buses kept (CASES), known without reading the case
    inertia_factors : ((node, factor), ...): those buses' inertia M_i times factor, their damping
        and every other bus as the rule makes them (a machine changed)
    lines_out : ((node, node), ...): those lines out of service, the machines' inertia and damping
        still the rule's on the whole grid (a line tripped does not change a machine)
    Both change the case a fitted network is tested against (docs/fit-network.md); nodes are
    indices 0..N-1 (``grid_bus_numbers`` gives each one's bus number).
    """

    number: int
    n_nodes: int
    inertia_factors: tuple = ()
    lines_out: tuple = ()
    builder = "pypower_case"

    def calls(self):
        return [f"pypower.api.case{self.number}(), converted by data_gen.grids.case_network"]

    def describe(self):
        """Root attributes recording where the grid came from."""
        return {"graph_builder": self.builder, "graph_calls": self.calls(), "grid_case": f"case{self.number}"}

    def network(self, p, source):
        """(weighted Graph, node attributes (N, 3), record) of the case under the scalar parameters
        ``p`` (the inertia rule) and the changes, refused with an InputError naming ``source`` unless
        it has a stable synchronous state."""
        graph, power, generator, record = case_network(load_case(self.number, source), source)
        if graph.n_nodes != self.n_nodes:
            raise InputError(source, "grid", f"PYPOWER's case{self.number} gives {graph.n_nodes} buses",
                             f"{self.n_nodes} (the case as this version of mpnode knows it)")
        attrs = grid_attrs(graph, power, generator, p)
        graph, attrs, changes = self._changed(graph, attrs, source)
        _check_connected(graph, source)
        operating_point(graph, power, source, inertia=attrs[:, 0])
        return graph, attrs, {**record, **changes}

    def _changed(self, graph, attrs, source):
        """The graph and attributes with ``inertia_factors`` and ``lines_out`` applied, and the
        root attributes recording them."""
        attrs, changes = attrs.copy(), {}
        for node, factor in self.inertia_factors:
            _check_node(node, graph.n_nodes, source, "inertia_factors")
            if not (np.isfinite(factor) and factor > 0):
                raise InputError(source, "inertia_factors", f"scales node {node}'s inertia by {factor}",
                                 "a finite factor > 0")
            attrs[int(node), 0] *= factor
        if self.inertia_factors:
            changes["grid_inertia_factors"] = np.asarray(self.inertia_factors, dtype=np.float64)
        if self.lines_out:
            pairs = np.asarray(self.lines_out, dtype=np.int64).reshape(-1, 2)
            edges = graph.edges()
            out = np.zeros(graph.n_edges, bool)
            for i, j in pairs:
                _check_node(i, graph.n_nodes, source, "lines_out")
                _check_node(j, graph.n_nodes, source, "lines_out")
                hit = ((edges[:, 0] == i) & (edges[:, 1] == j)) | ((edges[:, 0] == j) & (edges[:, 1] == i))
                if not hit.any():
                    raise InputError(source, "lines_out", f"names {i}-{j}, which is no line", "lines of the grid")
                out |= hit
            graph = Graph.from_edges(graph.n_nodes, edges[~out], directed=True, weights=graph.weights[~out])
            changes["grid_lines_out"] = pairs
        return graph, attrs, changes


def _check_node(node, n, source, field):
    if not 0 <= int(node) < n:
        raise InputError(source, field, f"names node {node}", f"nodes 0..{n - 1}")


def grid_ranges(graph, attrs):
    """What a grid spans, to set a family of grids beside the real cases (docs/systems.md#swing):
    {quantity: (low, high)} of the degrees (each bus's lines), the mean degree, the line
    susceptances B_ij, the non-zero |P_i|, M_i, D_i, and the largest line angle at the operating point."""
    degree = graph.degrees()
    power = np.abs(attrs[:, 2])
    theta = operating_point(graph, attrs[:, 2], inertia=attrs[:, 0])
    r, s = graph.edges().T
    angle = np.abs(theta[r] - theta[s]).max()
    return {"degree": (degree.min(), degree.max()), "mean degree": (degree.mean(), degree.mean()),
            "B (pu)": (graph.weights.min(), graph.weights.max()), "|P| (pu)": (power[power > 0].min(), power.max()),
            "M (pu s^2)": (attrs[:, 0].min(), attrs[:, 0].max()), "D (pu s)": (attrs[:, 1].min(), attrs[:, 1].max()),
            "largest line angle (rad)": (angle, angle)}


def joint_ranges(ranges):
    """The ranges of several grids together: {quantity: (lowest low, highest high)}."""
    return {k: (min(r[k][0] for r in ranges), max(r[k][1] for r in ranges)) for k in ranges[0]}

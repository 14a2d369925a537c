"""Test helpers for the engine: the float64 NumPy reference of every model kind, test graphs
and problems.

The reference is the library's NumPy path (mpnode.engine.numpy_path), written from the
semantics of the model format (docs/model-format.md) and sharing nothing with
mpnode.engine.kernels; test_engine checks its aggregation on its own.
"""
import numpy as np
import pytest

from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import layouts
from mpnode.engine import numpy_path as numpy_engine
from mpnode.engine.spec import Aggregation, FieldSpec, default_aggregation


# ---------------------------------------------------------------------------
# Drivers and precisions
# ---------------------------------------------------------------------------
def _slow_if_float32_stagewise(driver, dtype):
    return [pytest.mark.slow] if (driver, np.dtype(dtype)) == ("stagewise", np.float32) else []


#: ``driver`` (the conftest fixture, indirect) and ``dtype`` for a test that runs in both precisions.
#: float32's stagewise drivers are tested in the slow tier: they are the largest compile a cold default
#: tier would pay for one path (docs/evidence/test-suite.md); float64 runs the same source through every
#: property of the default tier
DRIVERS_AND_DTYPES = [pytest.param(d, t, id=f"{d}-{np.dtype(t).name}", marks=_slow_if_float32_stagewise(d, t))
                      for d in ("blocks", "stagewise") for t in (np.float32, np.float64)]
#: ``driver`` for a test in float32 alone
DRIVERS_IN_FLOAT32 = [pytest.param(d, id=d, marks=_slow_if_float32_stagewise(d, np.float32))
                      for d in ("blocks", "stagewise")]


# ---------------------------------------------------------------------------
# Graphs
# ---------------------------------------------------------------------------
def make_graph(rng, n, n_chords=None):
    """A random graph on n >= 5 nodes with every awkward case in it.

    Nodes 0..n-3 form an undirected path plus random undirected chords (so tile
    boundaries get crossed when n > 128); node n-2 hears node 0 but node 0 does not
    hear it, and node 1 hears n-2 but n-2 does not hear 1 (directed edges); node n-1
    is isolated (empty row, hears and is heard by nobody).
    """
    core = n - 2
    pairs = []
    for i in range(core - 1):
        pairs += [(i, i + 1), (i + 1, i)]
    n_chords = core // 2 if n_chords is None else n_chords
    for _ in range(n_chords):
        a, b = rng.integers(0, core, size=2)
        if a != b:
            pairs += [(a, b), (b, a)]
    pairs += [(n - 2, 0), (1, n - 2)]  # (receiver, sender): directed
    return Graph.from_edges(n, pairs, directed=True)


def permute_graph(graph, perm):
    """Relabel node i as perm[i]: edge (r, s) becomes (perm[r], perm[s])."""
    e = graph.edges()
    return Graph.from_edges(graph.n_nodes, perm[e], directed=True)


# ---------------------------------------------------------------------------
# The reference: mpnode.engine.numpy_path (written from the model format, no kernels), in float64
# ---------------------------------------------------------------------------
def rollout_ref(spec, theta, x0, graph, u, n_steps, with_messages=False):
    """The float64 NumPy rollout (mpnode.engine.numpy_path): x (n_steps+1, M, dx), or (x, m)."""
    return numpy_engine.rollout(spec, np.asarray(theta, dtype=np.float64), np.asarray(x0, dtype=np.float64),
                                graph, u, n_steps, with_messages)


def params(spec, theta):
    """Named views into a flat parameter vector (or its cotangent)."""
    return layouts.split(theta, layouts.param_shapes(spec))


def loss_ref(pred, target, kind, n_nodes):
    """Huber(delta=1) or squared error of pred - target at steps 1..T, summed, / n_nodes."""
    e = pred[1:] - target[1:]
    if kind == "huber":
        a = np.abs(e)
        v = np.where(a <= 1, 0.5 * e * e, a - 0.5)
    else:
        v = e * e
    return v.sum() / n_nodes


def random_theta(rng, spec, scale=1.0, dtype=np.float64):
    """Glorot-like weights and non-zero biases and psi (zeros would hide bugs)."""
    parts = []
    for shape in layouts.param_shapes(spec).values():
        fan = shape[0] + (shape[1] if len(shape) > 1 else 0)
        parts.append(rng.uniform(-1, 1, size=shape).ravel() * scale * np.sqrt(6.0 / fan))
    return np.concatenate(parts).astype(dtype)


# ---------------------------------------------------------------------------
# Test problems
# ---------------------------------------------------------------------------
AGGREGATION_OPTIONS = ("aggregation", "linear_aggregate", "linear_aggregation", "linear_target", "mean_degree")


def random_model(options, dx, du, dtype, seed=0):
    """A Model of ``options`` (FieldSpec fields) with random weights, non-zero biases, W_agg too,
    normalisation constants that are not 0/1, and two substeps."""
    from mpnode.model import Model

    rng = np.random.default_rng(seed)
    spec = spec_(state_dim=dx, control_dim=du, hidden=8, dt=0.1, substeps=2, **{"message_dim": 0, **options})
    return Model(random_theta(rng, spec, dtype=dtype), spec, x_mean=rng.standard_normal(dx),
                 x_std=1 + rng.random(dx), u_mean=rng.standard_normal(du), u_std=1 + rng.random(du))


def spec_(**kw):
    """A FieldSpec of small sizes; the aggregation may be given as the model options (flat)."""
    agg = {k: kw.pop(k) for k in AGGREGATION_OPTIONS if k in kw and not isinstance(kw[k], Aggregation)}
    base = dict(state_dim=2, control_dim=2, message_dim=3, hidden=8, dt=0.1, substeps=3)
    base.update(kw)
    if agg:
        rule = agg.pop("aggregation", None) or default_aggregation(base.get("kind", "mpnode"))
        base["aggregation"] = Aggregation.from_options(rule, **agg)
    return FieldSpec(**base)


def mixed_graph(seed=0, big=230):
    """A batch: four copies of one 9-node graph, then one ``big``-node graph (nodes 36..).

    Each graph has an isolated node and directed edges (engine_helpers.make_graph).  The
    copies make a dense block, the big graph a CSR block that crosses TILE = 192 inside
    the block; as one graph it spans two tiles, so the stagewise driver meets edges
    across tiles.
    """
    rng = np.random.default_rng(seed)
    g9 = make_graph(rng, 9)
    return block_diagonal([g9, g9, g9, g9, make_graph(rng, big)])


def problem(spec, graph, T, seed=1, dtype=np.float64):
    rng = np.random.default_rng(seed)
    M = graph.n_nodes
    theta = random_theta(rng, spec, dtype=dtype)
    x0 = rng.standard_normal((M, spec.state_dim))
    u = rng.standard_normal((T, M, spec.control_dim)) if spec.control_dim else None
    return theta, x0, u


def rel(a, b):
    return np.linalg.norm(np.ravel(a) - np.ravel(b)) / max(np.linalg.norm(np.ravel(b)), 1e-300)

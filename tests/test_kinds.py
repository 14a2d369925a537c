"""Every model kind and aggregation (and the linear aggregate path) through the engine, in
float64, on both drivers.

- rollouts against the NumPy reference of engine_helpers (written from the model format);
- the rollout's vector-Jacobian product with an *arbitrary* cotangent (the engine's one
  reverse entry point) against central finite differences of <g, rollout(theta, x0, u)>,
  for the parameters (every parameter array, psi included), the initial state and the
  controls, on graphs with an isolated node and directed edges.
"""
import dataclasses

import numpy as np
import pytest
from engine_helpers import mixed_graph, problem, rollout_ref, spec_

from mpnode import engine
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import layouts
from mpnode.engine import plan as engine_plan
from mpnode.engine.spec import Aggregation

KIND_SPECS = {
    "mpnode-mean": spec_(),
    "mpnode-sum": spec_(aggregation="sum"),
    "mpnode-scaled-self": spec_(aggregation="scaled", mean_degree=2.5, self_messages=True),
    "mpnode-scaled-linear": spec_(aggregation="scaled", mean_degree=2.5, linear_aggregate=True),
    "mpnode-mean-self-linear": spec_(self_messages=True, linear_aggregate=True),
    "mpnode-mean-linear-scaled": spec_(linear_aggregate=True, linear_aggregation="scaled", mean_degree=2.5),
    "mpnode-scaled-self-linear-mean": spec_(aggregation="scaled", mean_degree=2.5, self_messages=True,
                                            linear_aggregate=True, linear_aggregation="mean"),
    "mpnode-mean-linear-scaled-state": spec_(linear_aggregate=True, linear_aggregation="scaled", mean_degree=2.5,
                                             linear_target="state"),
    "mpnode-sum-linear-state": spec_(aggregation="sum", linear_aggregate=True, linear_target="state"),
    "l2s-sum": spec_(kind="l2s", message_dim=0),
    "l2s-mean-self": spec_(kind="l2s", message_dim=0, aggregation="mean", self_messages=True),
    "l2s-scaled": spec_(kind="l2s", message_dim=0, aggregation="scaled", mean_degree=3.0),
}


def node_spec(n_nodes):
    return spec_(kind="node", message_dim=0, n_nodes=n_nodes, hidden=6)


@pytest.mark.parametrize("name", KIND_SPECS)
def test_rollout_matches_reference(driver, name):
    spec = KIND_SPECS[name]
    graph = mixed_graph(3, big=220)
    theta, x0, u = problem(spec, graph, 3, seed=4)
    got = engine.forward(spec, theta, x0, graph, u, 3)
    want = rollout_ref(spec, theta, x0, graph, u, 3)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert np.abs(got[-1] - got[0]).max() > 1e-2  # it moves


def test_node_rollout_matches_reference():
    """A plain NODE over whole systems: B systems of N nodes, the graph is not used."""
    spec = node_spec(4)
    graph = block_diagonal([Graph.complete(4)] * 5)
    theta, x0, u = problem(spec, graph, 4, seed=5)
    np.testing.assert_allclose(engine.forward(spec, theta, x0, graph, u, 4),
                               rollout_ref(spec, theta, x0, graph, u, 4), rtol=1e-12, atol=1e-12)


def test_node_refuses_states_that_are_not_whole_systems():
    spec = node_spec(4)
    graph = Graph.from_edges(6, [])
    theta, x0, u = problem(spec, graph, 2)
    with pytest.raises(ValueError, match="whole systems of 4"):
        engine.forward(spec, theta, x0, graph, u, 2)


def test_aggregations_differ_as_the_format_says():
    """sum = mean * degree; scaled = sum / mean_degree: the first stage's messages show it."""
    graph = mixed_graph(6)
    for kind, dm in (("mpnode", 3), ("l2s", 0)):
        spec = spec_(kind=kind, message_dim=dm, substeps=1)
        theta, x0, u = problem(spec, graph, 2, seed=7)
        outs = {agg: engine.forward(dataclasses.replace(spec, aggregation=Aggregation(
                                        agg, mean_degree=2.0 if agg == "scaled" else None)),
                                    theta, x0, graph, u, 2) for agg in ("mean", "sum", "scaled")}
        assert not np.allclose(outs["mean"], outs["sum"])
        assert not np.allclose(outs["sum"], outs["scaled"])


def test_the_linear_path_reads_its_own_aggregate():
    """mean for the MLP, scaled sum for the linear path: not the rollout of either alone, and
    the same in a renumbered (reverse Cuthill-McKee) stagewise run, whose weights move too."""
    graph = mixed_graph(6, big=220)
    spec = KIND_SPECS["mpnode-mean-linear-scaled"]
    theta, x0, u = problem(spec, graph, 3, seed=7)
    got = engine.forward(spec, theta, x0, graph, u, 3)
    same = dataclasses.replace(spec, aggregation=Aggregation("mean", linear="mean"))
    assert not np.allclose(got, engine.forward(same, theta, x0, graph, u, 3))
    assert engine_plan.plan_for(graph, spec, np.float64, driver="stagewise", ordering="rcm").order is not None
    np.testing.assert_allclose(engine.forward(spec, theta, x0, graph, u, 3, driver="stagewise", ordering="rcm"),
                               got, rtol=1e-12, atol=1e-12)


def check_vjp(spec, graph, T, seed, n_dirs=2):
    """The VJP of the rollout with a random cotangent against central finite differences."""
    rng = np.random.default_rng(seed)
    theta, x0, u = problem(spec, graph, T, seed=seed)
    x, vjp = engine.forward_with_vjp(spec, theta, x0, graph, u, T)
    np.testing.assert_allclose(x, rollout_ref(spec, theta, x0, graph, u, T), rtol=1e-12, atol=1e-12)
    g = rng.standard_normal(x.shape)
    gtheta, gx0, gu = vjp(g, controls=True)
    assert gtheta.shape == theta.shape and gx0.shape == x0.shape and gu.shape == u.shape
    same = vjp(g)  # without the controls: the same gradients, bit for bit
    assert np.array_equal(same[0], gtheta) and np.array_equal(same[1], gx0)

    def L(th, x0_, u_=u):
        return float(np.sum(g * engine.forward(spec, th, x0_, graph, u_, T)))

    # <g, rollout> is smooth: step 1e-4 along unit directions leaves truncation ~1e-8 relative
    eps = 1e-4
    for _ in range(n_dirs):
        for which, grad in (("theta", gtheta), ("x0", gx0), ("u", gu)):
            d = rng.standard_normal(grad.shape)
            d /= np.linalg.norm(d)
            step = {which: eps * d}
            plus = L(theta + step.get("theta", 0), x0 + step.get("x0", 0), u + step.get("u", 0))
            minus = L(theta - step.get("theta", 0), x0 - step.get("x0", 0), u - step.get("u", 0))
            fd = (plus - minus) / (2 * eps)
            got = np.sum(grad * d)
            assert abs(fd - got) < 1e-6 * abs(fd), (which, fd, got)
    # the controls of the last step and of the first, one entry each: u is held over a step,
    # its cotangent sums the four stages and every substep
    eps = 1e-5
    for t in (0, T - 1):
        i = np.unravel_index(int(np.argmax(np.abs(gu[t]))), gu[t].shape)
        e = np.zeros_like(u)
        e[(t,) + i] = eps
        fd = (L(theta, x0, u + e) - L(theta, x0, u - e)) / (2 * eps)
        assert abs(fd - gu[(t,) + i]) < 1e-6 * abs(fd), (t, i, fd, gu[(t,) + i])
    # every parameter array on its own: its largest gradient entry
    eps = 1e-5
    offsets = np.cumsum([0] + [int(np.prod(s)) for s in layouts.param_shapes(spec).values()])
    for name, lo, hi in zip(layouts.param_shapes(spec), offsets[:-1], offsets[1:]):
        if name == "psi" and spec.self_messages:  # every node hears itself: no empty row uses psi
            assert not np.any(gtheta[lo:hi])
            continue
        assert np.any(gtheta[lo:hi]), f"{name} gets no gradient"
        i = lo + int(np.argmax(np.abs(gtheta[lo:hi])))
        e = np.zeros_like(theta)
        e[i] = eps
        fd = (L(theta + e, x0) - L(theta - e, x0)) / (2 * eps)
        assert abs(fd - gtheta[i]) < 1e-6 * abs(fd), (name, fd, gtheta[i])
    return gtheta, gx0


@pytest.mark.parametrize("name", KIND_SPECS)
def test_rollout_vjp_with_any_cotangent_matches_finite_differences(driver, name):
    """On mixed_graph: isolated nodes (L2S: psi must get its gradient), directed edges, a dense
    and a CSR block (stagewise: tiles crossed by edges)."""
    gtheta, gx0 = check_vjp(KIND_SPECS[name], mixed_graph(8, big=220), 3, seed=9)
    # the isolated node's initial state gets a gradient only through its own dynamics
    assert np.all(np.isfinite(gx0))


def test_node_vjp_matches_finite_differences():
    check_vjp(node_spec(3), block_diagonal([Graph.complete(3)] * 4), 3, seed=10)


@pytest.mark.parametrize("name", ["mpnode-mean-self-linear", "l2s-mean-self", "node", "mpnode-irregular"])
def test_the_reverse_pass_from_kept_stage_caches_matches_the_recomputing_one(monkeypatch, name):
    """The block driver's reverse pass reads every step's stage caches from the forward when
    they fit in rollout.KEEP_CACHES_BYTES, and recomputes them from the kept states otherwise:
    the same numbers either way (parameters, initial state, controls), for every kind, on
    dense and CSR blocks, with substeps, and with each node's own output times (output
    intervals of 6, 1 and 0 RK4 steps).  The same to rounding, not to the bit: the two reverse
    passes are two compiled drivers, and LLVM may order a sum differently in each."""
    from mpnode.engine import kernels, rollout

    spec = node_spec(4) if name == "node" else KIND_SPECS.get(name, spec_())
    graph = block_diagonal([Graph.complete(4)] * 5) if name == "node" else mixed_graph(6, big=220)
    T = 4
    theta, x0, u = problem(spec, graph, T, seed=9)
    iv = None
    if name == "mpnode-irregular":
        iv = spec.dt * np.random.default_rng(10).uniform(0.3, 1.7, (T, graph.n_nodes))
        iv[1] *= 0.2
        iv[2] = 0
    gx = np.random.default_rng(11).standard_normal((T + 1, graph.n_nodes, spec.state_dim))
    real_vjp = kernels.vjp_blocks

    def poisoned_vjp(*args):  # (theta, dims, l2s, b0, b1, ...): called once per block
        states, kept = args[15], args[16]
        assert (states is None) != (kept is None)  # the caches read, or the states to recompute them from
        if kept is not None and args[3] == 0:  # block 0 reads them poisoned; another block may have read its own
            for c in kept:
                c.fill(np.nan)
        return real_vjp(*args)

    def gradients(budget, poison=False):
        monkeypatch.setattr(rollout, "KEEP_CACHES_BYTES", budget)
        monkeypatch.setattr(kernels, "vjp_blocks", poisoned_vjp if poison else real_vjp)
        x, vjp = engine.forward_with_vjp(spec, theta, x0, graph, u, T, driver="blocks", intervals=iv)
        return (x,) + vjp(gx, controls=True)

    kept, recomputed = gradients(2**30), gradients(0)
    for a, b in zip(kept, recomputed):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    assert np.abs(kept[1]).max() > 0 and np.abs(kept[3]).max() > 0
    assert np.isnan(gradients(2**30, poison=True)[1]).any()  # the reverse pass read the kept caches
    for a, b in zip(gradients(0, poison=True), recomputed):  # and without them, it recomputed
        np.testing.assert_array_equal(a, b)


def test_kept_stage_caches_are_reused_once_no_vjp_holds_them(monkeypatch):
    """A training step's caches are reused by the next step's rollout once its VJP is gone (no
    fresh pages per batch), and a VJP still alive keeps its own."""
    from mpnode.engine import rollout

    monkeypatch.setattr(rollout, "_caches_buffers", {})
    spec, graph = spec_(), mixed_graph(6, big=220)
    theta, x0, u = problem(spec, graph, 3, seed=12)
    gx = np.ones((4, graph.n_nodes, spec.state_dim))
    def buffer():  # its address: a reference held here would itself count as a user
        return rollout._caches_buffers[theta.dtype].ctypes.data

    _, first = engine.forward_with_vjp(spec, theta, x0, graph, u, 3)
    taken = buffer()
    want = first(gx)
    _, second = engine.forward_with_vjp(spec, theta, 2 * x0, graph, u, 3)
    assert buffer() != taken  # the first VJP is alive: the second rollout has a buffer of its own ...
    for a, b in zip(first(gx), want):  # ... and left the first's as it was
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(second(gx)[0], want[0])
    del first, second
    taken = buffer()
    _, third = engine.forward_with_vjp(spec, theta, x0, graph, u, 3)
    assert buffer() == taken  # no VJP holds it any more: reused
    for a, b in zip(third(gx), want):
        np.testing.assert_array_equal(a, b)

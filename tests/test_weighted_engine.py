"""Weighted edges in the engine: the compiled rollouts against the NumPy reference on weighted
graphs (dense blocks, CSR blocks, one large graph stagewise), an unweighted graph's code path
untouched, and the edge weights' cotangent against central finite differences in float64."""
import numpy as np
import pytest

from engine_helpers import make_graph, problem, rollout_ref, spec_
from mpnode import engine
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine.spec import Aggregation


def weighted(graph, rng):
    """``graph`` with weights of both signs, none near 0."""
    w = rng.uniform(0.3, 1.8, graph.n_edges) * rng.choice([-1.0, 1.0], graph.n_edges, p=[0.3, 0.7])
    return Graph(graph.indptr, graph.indices, self_loops=graph.self_loops, weights=w)


def weighted_batch(seed=0, big=230):
    """Four copies of one weighted 9-node graph (the same object: a dense block whose matrix holds
    the weights) and one weighted ``big``-node graph (a CSR block crossing a tile boundary)."""
    rng = np.random.default_rng(seed)
    g9 = weighted(make_graph(rng, 9), rng)
    return block_diagonal([g9, g9, g9, g9, weighted(make_graph(rng, big), rng)])


SPECS = {
    "mean": spec_(),
    "sum-self": spec_(aggregation=Aggregation("sum"), self_messages=True),
    "scaled-weight-scale": spec_(aggregation=Aggregation("mean", "scaled", "state", mean_degree=2.5,
                                                         weight_scale=1.7)),
    "l2s": spec_(kind="l2s", message_dim=0, aggregation=Aggregation("sum", weight_scale=0.8)),
}


@pytest.mark.parametrize("name", SPECS)
@pytest.mark.parametrize("driver", ["blocks", "stagewise"])
def test_weighted_rollout_matches_reference(name, driver):
    spec = SPECS[name]
    graph = weighted_batch()
    theta, x0, u = problem(spec, graph, 3)
    got = engine.forward(spec, theta, x0, graph, u, 3, driver=driver)
    np.testing.assert_allclose(got, rollout_ref(spec, theta, x0, graph, u, 3), rtol=1e-12, atol=1e-12)
    plain = Graph(graph.indptr, graph.indices, parts=graph.parts)
    unweighted = rollout_ref(spec, theta, x0, plain, u, 3) if spec.aggregation.weight_scale is None else None
    if unweighted is not None:  # the weights must matter, or the comparison would prove little
        assert np.abs(got - unweighted).max() > 1e-2


@pytest.mark.parametrize("driver", ["blocks", "stagewise"])
def test_weights_of_one_give_the_unweighted_rollout_bit_for_bit(driver):
    spec = spec_()
    rng = np.random.default_rng(3)
    g9, big = make_graph(rng, 9), make_graph(rng, 230)
    plain = block_diagonal([g9, g9, big])
    ones = [Graph(g.indptr, g.indices, weights=np.ones(g.n_edges)) for g in (g9, big)]
    weighted_ones = block_diagonal([ones[0], ones[0], ones[1]])
    theta, x0, u = problem(spec, plain, 3)
    np.testing.assert_array_equal(engine.forward(spec, theta, x0, weighted_ones, u, 3, driver=driver),
                                  engine.forward(spec, theta, x0, plain, u, 3, driver=driver))


def _edge_fd_check(spec, graph, seed):
    """The edge weights' cotangent of <gx, rollout> against central differences: two random
    directions and the largest single entries, each to 1e-6 relative."""
    rng = np.random.default_rng(seed)
    T = 3
    theta, x0, u = problem(spec, graph, T, seed=seed)
    gx = rng.standard_normal((T + 1, graph.n_nodes, spec.state_dim))
    _, vjp = engine.forward_with_vjp(spec, theta, x0, graph, u, T)
    gtheta, gx0, gw = vjp(gx, edge_weights=True)
    assert gw.shape == (graph.n_edges,) and np.abs(gw).max() > 0

    def value(w):
        g = Graph(graph.indptr, graph.indices, self_loops=graph.self_loops, weights=w)
        return np.sum(gx * engine.forward(spec, theta, x0, g, u, T))

    w0, eps = graph.weights, 1e-5
    for _ in range(2):
        d = rng.standard_normal(w0.size)
        d /= np.linalg.norm(d)
        fd = (value(w0 + eps * d) - value(w0 - eps * d)) / (2 * eps)
        assert abs(fd - gw @ d) < 1e-6 * abs(fd), (fd, gw @ d)
    for p in np.argsort(-np.abs(gw))[:4]:
        e = np.zeros_like(w0)
        e[p] = eps
        fd = (value(w0 + e) - value(w0 - e)) / (2 * eps)
        assert abs(fd - gw[p]) < 1e-6 * abs(fd), (p, fd, gw[p])
    # asking for the edge weights changes none of the other cotangents
    gtheta2, gx02 = vjp(gx)
    np.testing.assert_allclose(gtheta, gtheta2, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(gx0, gx02, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", SPECS)
def test_edge_weight_cotangent_matches_finite_differences(name):
    _edge_fd_check(SPECS[name], weighted_batch(5, big=40), seed=5)


def test_edge_weight_cotangent_of_an_unweighted_graph_is_at_weights_one():
    """Asked of an unweighted graph, the cotangent is that of weights all 1 (where a fit starts)."""
    spec = spec_()
    rng = np.random.default_rng(9)
    g = make_graph(rng, 12)
    ones = Graph(g.indptr, g.indices, weights=np.ones(g.n_edges))
    theta, x0, u = problem(spec, g, 3)
    gx = rng.standard_normal((4, 12, spec.state_dim))
    gw_plain = engine.forward_with_vjp(spec, theta, x0, g, u, 3)[1](gx, edge_weights=True)[2]
    gw_ones = engine.forward_with_vjp(spec, theta, x0, ones, u, 3)[1](gx, edge_weights=True)[2]
    np.testing.assert_allclose(gw_plain, gw_ones, rtol=1e-12, atol=1e-14)
    _edge_fd_check(spec, ones, seed=9)


def test_edge_weight_cotangent_needs_the_block_drivers():
    spec = spec_()
    g = weighted_batch(1, big=20)
    theta, x0, u = problem(spec, g, 2)
    _, vjp = engine.forward_with_vjp(spec, theta, x0, g, u, 2, driver="stagewise")
    with pytest.raises(ValueError, match="block drivers"):
        vjp(np.ones((3, g.n_nodes, spec.state_dim)), edge_weights=True)

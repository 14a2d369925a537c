"""Node attributes and edge weights wherever a model goes after training: the Simulator and its
Jacobians, MPC, `mpnode simulate`, `eval --predictions`, `finetune` and ensembles; and every
mismatch between a model and its inputs refused on the command line in one sentence."""
from dataclasses import replace

import networkx as nx
import numpy as np
import pytest
from click.testing import CliRunner
from network_helpers import relaxing_nodes, ring

from cli.main import main
from mpnode import InputError, Simulator
from mpnode.control.mpc import ShootingMPC
from mpnode.data import read_trajectories, write_trajectories
from mpnode.model import Model
from mpnode.model.config import ModelConfig
from mpnode.model.ensemble import Ensemble

QUICK = ["--batch-size", "8", "--lr", "1e-2", "--hidden", "8", "--message-dim", "2"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def attributed(du=0, seed=0, weight_scale=1.5, names=("rate",)):
    """An untrained float64 model of one state dimension that hears node attributes ``names``
    after du controls, on graphs weighted by ``weight_scale`` (None: unweighted)."""
    return Model.create(1, du, dt=0.1, message_dim=2, hidden=8, seed=seed, attr_names=list(names),
                        weight_scale=weight_scale, config=ModelConfig(dtype="float64"))


def plain_of(model):
    """The same network with its attributes as ordinary controls (what it hears, by hand)."""
    return Model(model.theta, replace(model.spec, attr_dim=0), model.x_mean, model.x_std, model.u_mean, model.u_std)


def weighted_ring(n=4, seed=0):
    return ring(n, np.random.default_rng(seed).uniform(0.2, 3.0, n * 2))


# ---- the Simulator ---------------------------------------------------------------------------

@pytest.mark.parametrize("shared", [True, False], ids=["attrs-shared", "attrs-per-copy"])
def test_simulator_steps_are_the_rollout_with_attributes_bit_for_bit(shared):
    m, g = attributed(du=1), weighted_ring()
    rng = np.random.default_rng(1)
    x0, u = rng.uniform(-1, 1, (3, 4, 1)), rng.uniform(-1, 1, (3, 6, 4, 1))
    a = rng.uniform(0.2, 2, (4, 1)) if shared else rng.uniform(0.2, 2, (3, 4, 1))
    sim = Simulator(m, g, node_attrs=a)
    xs = [sim.reset(x0)] + [sim.step(u[:, t]) for t in range(6)]
    np.testing.assert_array_equal(np.stack(xs, 1), m.rollout(x0, g, u, node_attrs=a))


def test_a_weighted_networkx_graph_is_heard_by_its_weights():
    m, g = attributed(), weighted_ring()
    nxg = nx.DiGraph()
    nxg.add_nodes_from(range(4))
    for i in range(4):  # node i hears g.indices[p] with weight g.weights[p]
        for p in range(g.indptr[i], g.indptr[i + 1]):
            nxg.add_edge(int(g.indices[p]), i, weight=float(g.weights[p]))
    x0, a = np.random.default_rng(2).uniform(-1, 1, (2, 4, 1)), np.full((4, 1), 0.7)
    sim = Simulator(m, nxg, node_attrs=a)
    assert sim.graph.equals(g)
    sim.reset(x0)
    for _ in range(4):
        x = sim.step()
    np.testing.assert_array_equal(x, m.rollout(x0, g, steps=4, node_attrs=a)[:, -1])


def test_an_ensemble_simulator_hears_the_attributes_too():
    members = [attributed(seed=s) for s in (0, 1)]
    ens, g = Ensemble(members), weighted_ring()
    x0, a = np.random.default_rng(3).uniform(-1, 1, (2, 4, 1)), np.random.default_rng(4).uniform(0.2, 2, (2, 4, 1))
    sim = Simulator(ens, g, node_attrs=a)
    sim.reset(x0)
    for _ in range(3):
        sim.step()
    each = np.stack([m.rollout(x0, g, steps=3, node_attrs=a)[:, -1] for m in members])
    np.testing.assert_allclose(sim.state, each.mean(axis=0), rtol=1e-13, atol=1e-14)
    assert sim.spread is not None and sim.spread.max() > 0


def test_an_ensemble_rolls_out_with_node_attributes_as_its_members_do():
    members = [attributed(seed=s) for s in (0, 1)]
    ens, g = Ensemble(members), weighted_ring()
    x0, a = np.random.default_rng(5).uniform(-1, 1, (2, 4, 1)), np.random.default_rng(6).uniform(0.2, 2, (2, 4, 1))
    each = np.stack([m.rollout(x0, g, steps=5, node_attrs=a) for m in members])
    np.testing.assert_allclose(ens.rollout(x0, g, steps=5, node_attrs=a), each.mean(axis=0), rtol=1e-13, atol=1e-14)
    mean, spread = ens.predict(x0, g, steps=5, node_attrs=a)
    np.testing.assert_allclose(mean, each.mean(axis=0), rtol=1e-13, atol=1e-14)
    assert spread.shape == mean.shape and spread.max() > 0
    other = np.stack([m.rollout(x0, g, steps=5, node_attrs=a[::-1]) for m in members])
    assert not np.allclose(other, each)  # the attributes reach every member


def test_the_simulator_refuses_attributes_and_weights_that_are_not_the_models():
    a = np.ones((4, 1))
    with pytest.raises(InputError, match="node_attrs: is missing.*rate"):
        Simulator(attributed(), weighted_ring())
    with pytest.raises(InputError, match="without node attributes"):
        Simulator(Model.create(1, dt=0.1, hidden=8), ring(4), node_attrs=a)
    with pytest.raises(InputError, match="has edge weights but the model was trained on unweighted"):
        Simulator(attributed(weight_scale=None), weighted_ring(), node_attrs=a)
    with pytest.raises(InputError, match="has no edge weights"):
        Simulator(attributed(), ring(4), node_attrs=a)
    sim = Simulator(attributed(), weighted_ring(), node_attrs=np.ones((2, 4, 1)))
    with pytest.raises(InputError, match="node_attrs: has shape"):  # two sets of attributes for three copies
        sim.reset(np.zeros((3, 4, 1)))


@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
def test_the_step_jacobians_keep_the_controls_and_give_the_attributes_apart(sparse):
    """Node-major columns: node j's controls then attributes in the network's input; Ju holds the
    controls' columns of every node, Ja the attributes', each as the plain model gives them."""
    m, g = attributed(du=2, names=("rate", "gain")), weighted_ring(5)
    m.u_mean, m.u_std = np.array([0.1, -0.2, 0.3, 0.0]), np.array([1.5, 0.5, 2.0, 3.0])
    rng = np.random.default_rng(5)
    x0, u, a = rng.uniform(-1, 1, (2, 5, 1)), rng.uniform(-1, 1, (2, 5, 2)), rng.uniform(0.2, 2, (2, 5, 2))
    sim, plain = Simulator(m, g, node_attrs=a), Simulator(plain_of(m), g)
    sim.reset(x0), plain.reset(x0)
    sim.step(u), plain.step(np.concatenate([u, a], axis=2))
    jx, ju, ja = sim.jacobians(u, sparse=sparse, attrs=True)
    px, pu = plain.jacobians(np.concatenate([u, a], axis=2), sparse=sparse)
    dense = (lambda js: np.stack([j.toarray() for j in js])) if sparse else np.asarray
    pu = dense(pu).reshape(2, 5, 5, 4)  # (B, N*dx, node, its 4 inputs)
    assert dense(ju).shape == (2, 5, 10) and dense(ja).shape == (2, 5, 10)
    np.testing.assert_array_equal(dense(jx), dense(px))
    np.testing.assert_array_equal(dense(ju), pu[..., :2].reshape(2, 5, 10))
    np.testing.assert_array_equal(dense(ja), pu[..., 2:].reshape(2, 5, 10))
    assert np.abs(dense(ja)).max() > 1e-3
    jx2, ju2 = sim.jacobians(u, sparse=sparse)
    np.testing.assert_array_equal(dense(ju2), dense(ju))


# ---- MPC -------------------------------------------------------------------------------------

def test_mpc_plans_the_controls_alone_and_predicts_with_the_attributes():
    m, g = attributed(du=1), weighted_ring()
    rng = np.random.default_rng(6)
    x0, a = rng.uniform(-1, 1, (2, 4, 1)), rng.uniform(0.2, 2, (2, 4, 1))
    mpc = ShootingMPC(m, g, horizon=5, iterations=3, node_attrs=a)
    mpc.reset(x0, np.zeros((2, 4, 1)))
    assert mpc.plan.shape == (2, 5, 4, 1)
    U = rng.uniform(-1, 1, (2, 5, 4, 1))
    z0 = [z.copy() for z in mpc._z]
    X, vjp = mpc._predict(z0, U)
    np.testing.assert_allclose(X, m.rollout(x0, g, U, node_attrs=a), rtol=1e-12, atol=1e-13)
    dX = rng.standard_normal(X.shape)
    grad = vjp(dX)
    assert grad.shape == U.shape
    e = np.zeros_like(U)
    e[1, 2, 3, 0] = 1e-6
    fd = (np.sum(dX * mpc._predict(z0, U + e)[0]) - np.sum(dX * mpc._predict(z0, U - e)[0])) / 2e-6
    assert fd == pytest.approx(grad[1, 2, 3, 0], rel=1e-6, abs=1e-9)
    u = mpc.control(x0, lambda X, U: (float(np.sum(X ** 2) + np.sum(U ** 2)), 2 * X, 2 * U))
    assert u.shape == (2, 4, 1) and np.all(np.isfinite(u))
    with pytest.raises(InputError, match="node_attrs: is missing"):
        ShootingMPC(m, g, horizon=5)
    with pytest.raises(InputError, match="no controls to optimise"):
        ShootingMPC(attributed(), g, horizon=5, node_attrs=a)


# ---- the command line ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The relaxing nodes' files: training and test data with attributes and weights, the test
    data without attributes, without weights, with other attribute names; and untrained models
    of each kind of input."""
    d = tmp_path_factory.mktemp("network_cli")
    test = relaxing_nodes(B=6, seed=9)
    write_trajectories(d / "train.h5", relaxing_nodes(B=24, seed=0))
    write_trajectories(d / "test.h5", test)
    write_trajectories(d / "no_attrs.h5", replace(test, node_attrs=None, attr_names=None))
    write_trajectories(d / "no_weights.h5", replace(test, graphs=[g.reweighted(None) for g in test.graphs]))
    write_trajectories(d / "bare.h5", replace(test, node_attrs=None, attr_names=None,
                                              graphs=[g.reweighted(None) for g in test.graphs]))
    write_trajectories(d / "renamed.h5", replace(test, attr_names=["decay"]))
    attributed().save(d / "attrs.h5")
    attributed(weight_scale=None).save(d / "attrs_unweighted.h5")
    Model.create(1, dt=0.1, message_dim=2, hidden=8).save(d / "plain.h5")
    Model.create(1, dt=0.1, message_dim=2, hidden=8, weight_scale=1.5).save(d / "weights_only.h5")
    return d


@pytest.fixture(scope="module")
def trained(files):
    """A model trained two epochs on the training file: it hears the rate and the weights."""
    res = run("train", files / "train.h5", "-o", files / "trained.h5", "--epochs", 2, *QUICK)
    assert res.exit_code == 0, res.output
    return files / "trained.h5"


def test_training_on_a_file_with_attributes_and_weights_hears_both(trained):
    m = Model.load(trained)
    assert m.attr_names == ["rate"] and m.spec.attr_dim == 1 and m.spec.aggregation.weight_scale > 0


def test_recipe_auto_sums_the_weighted_neighbours_of_a_system_it_does_not_name(files, trained, tmp_path):
    assert Model.load(trained).spec.aggregation.mlp == "sum"  # "relaxing": no row of its own
    res = run("train", files / "train.h5", "-o", tmp_path / "plain.h5", "--epochs", 1, *QUICK, "--ignore-attrs")
    assert res.exit_code == 0 and "aggregation mean" in res.output, res.output  # no weights heard: the paper's
    write_trajectories(tmp_path / "k.h5", replace(relaxing_nodes(B=8), system="kuramoto_het"))
    res = run("train", tmp_path / "k.h5", "-o", tmp_path / "k_model.h5", "--epochs", 1, *QUICK)
    assert res.exit_code == 0 and Model.load(tmp_path / "k_model.h5").spec.aggregation.mlp == "mean", res.output


def test_the_predictions_file_keeps_the_datas_network(files, trained, tmp_path):
    out = tmp_path / "pred.h5"
    res = run("eval", trained, files / "test.h5", "--predictions", out, "--reference-sample", 0)
    assert res.exit_code == 0, res.output
    pred, test = read_trajectories(out), read_trajectories(files / "test.h5")
    assert pred.attr_names == ["rate"] and pred.u is None  # the data's controls: none, not the held rates
    np.testing.assert_array_equal(pred.node_attrs, test.node_attrs)
    assert all(p.equals(t) for p, t in zip(pred.graphs, test.graphs)) and pred.weighted
    np.testing.assert_array_equal(pred.graph_index, test.graph_index)
    m = Model.load(trained)
    x0 = m.initial_state(test.x[:, :1])  # where eval starts: the first observation in the model's dtype
    np.testing.assert_array_equal(pred.x, m.rollout(x0, [test.graph_of(b) for b in range(6)], steps=20,
                                                    node_attrs=test.node_attrs))
    res = run("eval", trained, out, "--reference-sample", 0)  # a model reads its predictions as it read the data
    assert res.exit_code == 0, res.output


def test_simulate_from_a_file_holds_the_attributes_past_its_end(files, trained, tmp_path):
    out = tmp_path / "sim.h5"
    res = run("simulate", trained, files / "test.h5", "-o", out, "-T", 30)
    assert res.exit_code == 0, res.output
    sim, test = read_trajectories(out), read_trajectories(files / "test.h5")
    assert sim.horizon == 30 and sim.attr_names == ["rate"] and sim.u is None and sim.weighted
    np.testing.assert_array_equal(sim.node_attrs, test.node_attrs)
    m = Model.load(trained)
    x0 = m.initial_state(test.x[:, :1])
    want = m.rollout(x0, [test.graph_of(b) for b in range(6)], steps=30, node_attrs=test.node_attrs)
    np.testing.assert_array_equal(sim.x, want)


def test_simulate_of_a_scene_whose_trajectories_draw_their_network(tmp_path):
    from data_gen import initial_states, load_scene
    from data_gen.per_trajectory import scene_graphs

    scene = replace(load_scene("kuramoto_het10"), trajectories=3, horizon=5, seed=4)
    made = scene_graphs(scene)
    m = Model.create(2, dt=scene.dt, message_dim=2, hidden=8, attr_names=list(made.attr_names), weight_scale=1.0,
                     config=ModelConfig(dtype="float64"))
    m.save(tmp_path / "m.h5")
    res = run("simulate", tmp_path / "m.h5", "kuramoto_het10", "-o", tmp_path / "s.h5", "-B", 3, "-T", 5, "--seed", 4)
    assert res.exit_code == 0, res.output
    sim, x0 = read_trajectories(tmp_path / "s.h5"), initial_states(scene)[0]
    np.testing.assert_array_equal(sim.x[:, 0], x0)
    np.testing.assert_array_equal(sim.node_attrs, made.node_attrs)
    assert sim.attr_names == list(made.attr_names)
    assert all(s.equals(g) for s, g in zip(sim.graphs, made.graphs)) and sim.weighted
    np.testing.assert_array_equal(sim.x, m.rollout(x0, made.graphs, steps=5, node_attrs=made.node_attrs))
    plain = tmp_path / "plain.h5"
    Model.create(2, dt=scene.dt, message_dim=2, hidden=8).save(plain)
    res = run("simulate", plain, "kuramoto_het10", "-o", tmp_path / "p.h5", "-B", 3, "-T", 5)
    assert res.exit_code == 2 and "--ignore-attrs" in res.output, res.output
    res = run("simulate", plain, "kuramoto_het10", "-o", tmp_path / "p.h5", "-B", 3, "-T", 5, "--ignore-attrs")
    assert res.exit_code == 0, res.output
    assert read_trajectories(tmp_path / "p.h5").attr_names == list(made.attr_names)  # the network simulated


def test_finetune_keeps_what_the_model_hears(files, trained, tmp_path):
    out = tmp_path / "fine.h5"
    res = run("finetune", trained, files / "test.h5", "-o", out, "--epochs", 1, "--batch-size", 4)
    assert res.exit_code == 0, res.output
    m, parent = Model.load(out), Model.load(trained)
    assert m.attr_names == ["rate"] and m.spec == parent.spec
    assert not np.array_equal(m.theta, parent.theta)
    res = run("finetune", files / "plain.h5", files / "test.h5", "-o", tmp_path / "p.h5", "--epochs", 1,
              "--batch-size", 4, "--ignore-attrs")
    assert res.exit_code == 0, res.output
    assert Model.load(tmp_path / "p.h5").attr_names == []


@pytest.mark.parametrize("command", ["eval", "simulate", "finetune"])
@pytest.mark.parametrize("model, data, says", [
    ("attrs.h5", "no_attrs.h5", "node_attrs: are missing (expected the node attributes the model was trained with: "
                                "rate"),
    ("plain.h5", "bare.h5", None),
    ("plain.h5", "test.h5", "node_attrs: holds node attributes (rate) but the model was trained without any"),
    ("attrs.h5", "renamed.h5", "node_attrs: are decay (expected the node attributes the model was trained with: rate"),
    ("attrs_unweighted.h5", "test.h5", "graphs/weights: holds edge weights but the model was trained on unweighted"),
    ("attrs.h5", "no_weights.h5", "graphs/weights: are missing, but the model was trained on weighted graphs"),
    ("weights_only.h5", "bare.h5", "graphs/weights: are missing"),
], ids=["model-attrs-data-none", "neither", "data-attrs-model-none", "names-differ", "weighted-data",
        "unweighted-data", "weights-only-model"])
def test_inputs_that_are_not_the_models_exit_2_in_one_sentence_writing_nothing(files, tmp_path, command, model,
                                                                               data, says):
    out = tmp_path / "out.h5"
    args = {"eval": ["--predictions", out, "--reference-sample", 0], "simulate": ["-o", out],
            "finetune": ["-o", out, "--epochs", 1, "--batch-size", 4]}[command]
    res = run(command, files / model, files / data, *args)
    if says is None:
        assert res.exit_code == 0, res.output
        return
    assert res.exit_code == 2, res.output
    errors = [line for line in res.output.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith("Error: ") and says in errors[0], res.output
    assert "Traceback" not in res.output and not list(tmp_path.iterdir())


def test_ignore_attrs_leaves_them_out_for_a_model_without_and_only_then(files, tmp_path):
    res = run("eval", files / "plain.h5", files / "test.h5", "--ignore-attrs", "--predictions", tmp_path / "p.h5",
              "--reference-sample", 0)
    assert res.exit_code == 0, res.output
    assert read_trajectories(tmp_path / "p.h5").attr_names == ["rate"]  # the data's network, kept
    res = run("simulate", files / "plain.h5", files / "test.h5", "--ignore-attrs", "-o", tmp_path / "s.h5")
    assert res.exit_code == 0, res.output
    res = run("finetune", files / "attrs.h5", files / "test.h5", "--ignore-attrs", "-o", tmp_path / "f.h5",
              "--epochs", 1)
    assert res.exit_code == 2 and "ignore_attrs: is set, but the model hears node attributes (rate) and edge " \
                                  "weights" in res.output, res.output
    assert not (tmp_path / "f.h5").exists()


def test_a_whole_system_node_learns_and_is_evaluated_on_weighted_files(files, tmp_path):
    """A plain NODE sees every node at once and no edge: it trains on a weighted file, as it is,
    and evaluates on one."""
    res = run("train", files / "train.h5", "-o", tmp_path / "node.h5", "--model", "node", "--epochs", 1,
              "--batch-size", "8", "--hidden", "8")
    assert res.exit_code == 0, res.output
    assert Model.load(tmp_path / "node.h5").attr_names == ["rate"]
    res = run("eval", tmp_path / "node.h5", files / "test.h5", "--reference-sample", 0, "--json")
    assert res.exit_code == 0, res.output


def test_an_ensemble_trains_on_attributes_and_weights_and_is_evaluated(files, tmp_path):
    out = tmp_path / "ens.h5"
    res = run("train", files / "train.h5", "-o", out, "--ensemble", 2, "--epochs", 2, *QUICK)
    assert res.exit_code == 0, res.output
    ens = Model.load(out)
    assert isinstance(ens, Ensemble) and ens.attr_names == ["rate"] and ens.spec.aggregation.weight_scale > 0
    res = run("eval", out, files / "test.h5", "--predictions", tmp_path / "p.h5", "--reference-sample", 0, "--json")
    assert res.exit_code == 0, res.output
    pred = read_trajectories(tmp_path / "p.h5")
    assert pred.attr_names == ["rate"] and pred.x_std is not None and np.all(np.isfinite(pred.x_std))
    res = run("simulate", out, files / "test.h5", "-o", tmp_path / "s.h5")
    assert res.exit_code == 0, res.output

"""Scenes: the built-in table and the TOML schema (data_gen/scenes.py)."""
import os
from dataclasses import replace

import pytest

import data_gen
from data_gen import BUILTIN, SETS, generate, load_scene, read_scene
from data_gen.scenes import check_scene
from mpnode.base.errors import InputError

EXAMPLE = os.path.join(os.path.dirname(data_gen.__file__), "scenes", "example_gene_ring.toml")

EXPECTED = ["coupled_pendulum", "pendulum_force", "lorenz3", "lorenz7", "lorenz10", "lorenz10_medium", "lorenz10_high", "lorenz10_10s",
            "gene16_er", "gene16_ba", "gene16_ws", "gene64_er", "gene64_ba", "gene64_ws", "gene16_ba_multi",
            "gene16_er_hot", "gene16_ba_hot", "gene16_ws_hot", "gene64_er_hot", "gene64_ba_hot", "gene64_ws_hot",
            "gene16_ba_multi_hot", "kuramoto10_er", "kuramoto10_ba", "kuramoto10_ws", "kuramoto_het10",
            "kuramoto_het50_ba", "spring_pendulums_het4", "spring_pendulums_het10", "grid10", "grid20", "grid30",
            "grid40", "ieee14", "ieee30", "ieee39", "ieee57", "ieee118", "ieee300", "quad3", "quad4",
            "quad5", "quad6", "quad8", "quad12"]


def test_builtin_scenes():
    assert list(BUILTIN) == EXPECTED
    for name, s in BUILTIN.items():
        check_scene(s, name)
        assert s.name == name and s.description and "\n" not in s.description
        dt = 0.1 if s.system == "quadrotor_load" else 0.05  # quadrotor.md: dt = 0.1, T = 50
        horizon = 200 if name == "lorenz10_10s" else 50  # the paper's Fig. 5e: 10 s at dt = 0.05
        horizon = 100 if s.system == "swing" else horizon  # 5 s: the power grids' swings and their decay
        assert (s.dt, s.horizon, s.trajectories) == (dt, horizon, 1000)
    assert [BUILTIN[n].params["coupling"] for n in ("lorenz10", "lorenz10_medium", "lorenz10_high", "lorenz10_10s")] \
        == [0.01, 1.0, 5.0, 0.01]
    assert BUILTIN["gene16_ba_multi"].graph.seeds == (1, 2, 3, 4, 5)
    # the paper's gene data start from hot spots (NDCN): same graphs, other initial states
    for name in EXPECTED:
        if name.endswith("_hot"):
            hot, plain = BUILTIN[name], BUILTIN[name[:-4]]
            assert hot.initial == "hotspots" and plain.initial == "uniform" and hot.graph == plain.graph
    assert BUILTIN["gene64_ws"].graph.args == {"k": 32, "p": 0.5}


def test_example_file_loads_and_generates():
    s = load_scene(EXAMPLE)
    assert s.name == "example_gene_ring" and s.system == "gene" and s.seed == 7
    t = generate(replace(s, trajectories=2, horizon=3), workers=1)
    assert t.x.shape == (2, 4, 8, 1)
    assert all(d == 2 for d in t.graphs[0].degrees())  # a ring


def write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


GOOD_GRAPH = '[graph]\nbuilder = "watts_strogatz"\nnodes = 10\nk = 4\np = 0.5\nseeds = [1, 2]\n'


def test_random_graph_scene(tmp_path):
    s = read_scene(write(tmp_path, 'system = "kuramoto"\ndt = 1\n[params]\nK = 1\n' + GOOD_GRAPH))
    assert s.graph.builder == "watts_strogatz" and s.graph.seeds == (1, 2) and s.graph.args == {"k": 4, "p": 0.5}
    assert s.dt == 1.0 and isinstance(s.dt, float) and s.params == {"K": 1.0}


@pytest.mark.parametrize("text, field", [
    ('system = "kuramoto"\n' + GOOD_GRAPH + 'colour = 3\n', "graph.colour"),
    ('system = "kuramoto"\nspeed = 3\n' + GOOD_GRAPH, "speed"),
    ('system = "kuramoto"\ntrajectories = "many"\n' + GOOD_GRAPH, "trajectories"),
    ('system = "kuramoto"\ntrajectories = true\n' + GOOD_GRAPH, "trajectories"),
    ('system = "kuramoto"\ndt = -0.1\n' + GOOD_GRAPH, "dt"),
    ('system = "kuramoto"\nhorizon = 0\n' + GOOD_GRAPH, "horizon"),
    (GOOD_GRAPH, "system"),
    ('system = "kuramoto"\n', "graph"),
    ('system = "heat"\n' + GOOD_GRAPH, "system"),
    ('system = "kuramoto"\n[params]\nsigma = 1\n' + GOOD_GRAPH, "params.sigma"),
    ('system = "kuramoto"\ninitial = "hotspots"\n' + GOOD_GRAPH, "initial"),
    ('system = "kuramoto"\nintegrator = "Euler"\n' + GOOD_GRAPH, "integrator"),
    ('system = "kuramoto"\n[graph]\nbuilder = "watts_strogatz"\nnodes = 10\nk = 4\nseed = 1\n', "graph.p"),
    ('system = "kuramoto"\n[graph]\nbuilder = "gnm"\nnodes = 10\nm = 4\n', "graph.seeds"),
    ('system = "kuramoto"\n[graph]\nbuilder = "gnm"\nnodes = 10\nm = 4\nseed = 1\nedges = [[0, 1]]\n', "graph.edges"),
    ('system = "kuramoto"\n[graph]\nbuilder = "star"\nnodes = 10\n', "graph.builder"),
    ('system = "gene"\n[graph]\nbuilder = "edges"\nnodes = 3\n', "graph.edges"),
    ('system = "gene"\n[graph]\nbuilder = "edges"\nnodes = 3\nedges = [[0, 3]]\n', "graph.edges"),
    ('system = "gene"\n[graph]\nbuilder = "edges"\nnodes = 3\nedges = [[0, 1.5]]\n', "graph.edges"),
    ('system = "gene"\n[graph\n', "TOML"),
])
def test_bad_scene_files_name_file_and_key(tmp_path, text, field):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as e:
        read_scene(path)
    assert e.value.source == str(path) and e.value.field == field


def test_graph_the_physics_cannot_run_on(tmp_path):
    s = read_scene(write(tmp_path, 'system = "lorenz"\n[graph]\nbuilder = "edges"\nnodes = 3\nedges = [[0, 1]]\n'))
    with pytest.raises(InputError, match="complete"):
        generate(s, workers=1)


def test_missing_scene_file():
    with pytest.raises(InputError, match="does not exist"):
        load_scene("/nonexistent/scene.toml")


def test_a_scene_set_names_built_in_scenes_with_their_own_seeds():
    swarm = SETS["quad3-5"]
    scenes = swarm.scenes()
    assert [(s.name, s.graph.n_nodes, s.trajectories, s.seed) for s in scenes] == \
        [("quad3", 3, 500, 0), ("quad4", 4, 300, 1), ("quad5", 5, 300, 2)]
    assert BUILTIN[swarm.test].graph.n_nodes not in {s.graph.n_nodes for s in scenes}  # a size it never saw
    again = swarm.scenes(trajectories=7, seed=40, horizon=3)
    assert [(s.trajectories, s.seed, s.horizon) for s in again] == [(7, 40, 3), (7, 41, 3), (7, 42, 3)]
    assert not set(SETS) & set(BUILTIN)
    with pytest.raises(InputError, match="scene set"):
        load_scene("quad3-5")

"""How wrong may a model be and still name the node that changed?  With and without a reference.

The truth is a model itself (an MP-NODE of 16 hidden units, random weights, float64) on a ring of
12 nodes with three chords, weighted, each node with two attributes.  Each draw halves one random
node's first attribute and makes 20 trajectories of 30 steps with it; the fit runs through a copy
of the truth whose every weight is off by a relative error drawn with standard deviation ERROR
(`mpnode.fit_network`, the first attribute), once from the nominal values and once against the fit
of 20 trajectories of the unchanged network (`reference`).  Prints, per ERROR, the hits (the
changed node ranked first) of each way out of the draws and the median normalised MSE of the wrong
model's rollouts of the unchanged network (what `mpnode eval` would report of it), as one JSON
object; docs/evidence/fit-network.md quotes it.

    python benchmarks/studies/network_fit_error.py [--draws 10] [--errors 0.02,0.05,0.1,0.2,0.4]
"""
import argparse
import json

import numpy as np

import mpnode
from mpnode.base.graph import Graph
from mpnode.data import Trajectories
from mpnode.evaluation.network_fit import lines_of
from mpnode.model import Model
from mpnode.model.config import ModelConfig

N, B, T = 12, 20, 30


def network(rng):
    """(weighted Graph, node attributes (N, 2)) of the nominal network."""
    graph = Graph.from_edges(N, [(i, (i + 1) % N) for i in range(N)] + [(0, 6), (3, 9), (2, 7)])
    line_of, lines = lines_of(graph)
    weights = rng.uniform(0.5, 2.5, len(lines))[line_of]
    return graph.reweighted(weights), np.stack([rng.uniform(0.5, 2.0, N), rng.uniform(1.0, 3.0, N)], axis=1)


def made_by(truth, attrs, graph, seed):
    x0 = np.random.default_rng(seed).uniform(-1, 1, (B, N, 1))
    x = truth.rollout(x0, graph, steps=T, node_attrs=attrs)
    return Trajectories.from_arrays(x, graph, dt=0.1, system="made", node_attrs=attrs, attr_names=truth.attr_names)


def nmse(model, traj):
    """The normalised MSE of the model's rollouts of ``traj`` over steps 1..T (per-dimension variance of the data)."""
    pred = model.rollout(traj.x[:, 0], traj.graphs[0], steps=traj.horizon, node_attrs=traj.node_attrs)
    return float(np.mean((pred[:, 1:] - traj.x[:, 1:]) ** 2) / np.var(traj.x))


def main(draws, errors):
    truth = Model.create(1, 0, dt=0.1, message_dim=2, hidden=16, seed=5, attr_names=["a", "b"], weight_scale=1.5,
                         config=ModelConfig(dtype="float64"))
    graph, attrs = network(np.random.default_rng(0))
    out = {}
    for error in errors:
        hits, errors_seen = {"from_nominal": 0, "from_reference": 0}, []
        for k in range(draws):
            rng = np.random.default_rng(100 + k)
            wrong = truth.copy()
            wrong.theta = truth.theta * (1 + error * rng.standard_normal(truth.theta.size))
            node = int(rng.integers(N))
            changed = attrs.copy()
            changed[node, 0] *= 0.5
            after, before = made_by(truth, changed, graph, 1000 + k), made_by(truth, attrs, graph, 2000 + k)
            plain = mpnode.fit_network(wrong, after, attrs="a", node_attrs=attrs)
            against = mpnode.fit_network(wrong, after, attrs="a", node_attrs=attrs, reference=before)
            hits["from_nominal"] += int(plain.ranking[0] == node)
            hits["from_reference"] += int(against.ranking[0] == node)
            errors_seen.append(nmse(wrong, before))
        out[str(error)] = {**hits, "draws": draws, "nmse_median": float(np.median(errors_seen))}
        print(error, out[str(error)], flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--errors", default="0.02,0.05,0.1,0.2,0.4", help="relative weight errors, comma-separated")
    args = parser.parse_args()
    main(args.draws, [float(e) for e in args.errors.split(",")])

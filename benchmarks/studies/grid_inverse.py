"""Which bus or line changed: does a model trained on random grids name it on a real one?

Ten random draws on ieee39, each of two changes: one bus's inertia halved (a random bus), and one
line out of service (a random line whose loss leaves the grid connected and in step).  Each draw
generates 20 trajectories of the changed grid from fresh disturbances (data_gen.grids.GridCase's
inertia_factors / lines_out), fits the nominal grid's inertias (`mpnode.fit_network`,
what="node_attrs", attrs=[inertia]) or line susceptances (what="edge_weights") through the model,
and records where the changed bus (line) falls in the fit's ranking, 0 being first, two ways:
departures from the nominal values, and departures from the fit of 20 trajectories of the nominal
grid (observed before the change, from other disturbances; fitted once per kind, the `reference`).
Prints and writes one JSON object (default: beside the model, MODEL.grid_inverse.json): hits
(rank 0) out of the draws, the seconds per fit, and every draw.  The numbers in
docs/evidence/fit-network.md come from it.

    python benchmarks/studies/grid_inverse.py MODEL.h5 [--draws 10] [--trajectories 20] [--seed 0] [--window K]
"""
import argparse
import json
import time
from dataclasses import replace

import numpy as np

import mpnode
from data_gen.scenes import BUILTIN
from data_gen.simulate import generate
from data_gen.systems import get_system
from mpnode.base.errors import InputError
from mpnode.evaluation.network_fit import lines_of

INERTIA = "inertia (pu s^2)"


def nominal_grid(scene):
    """(Graph, node attributes (N, 3)) of the scene's case as it is."""
    scalars = {**get_system(scene.system).defaults, **scene.params}
    graph, attrs, _ = scene.graph.network(scalars, scene.name)
    return graph, attrs


def observed(scene, seed, trajectories, **change):
    """Trajectories of the scene's grid under ``change`` (GridCase's inertia_factors or lines_out)."""
    grid = replace(scene.graph, **change)
    return generate(replace(scene, graph=grid, trajectories=trajectories, seed=seed), workers=1)


def rank(departure, truth):
    """Where ``truth`` falls when the departures (N,) or (L,) are sorted, largest first (0: first)."""
    return int(np.flatnonzero(np.argsort(-departure, kind="stable") == truth)[0])


def record(fit, truth, generated, from_nominal):
    """One draw's entry: where the changed bus (line) ranks, from the reference's fit and from the
    nominal values (``from_nominal``: the departures from them), and what the fit found."""
    return {"changed": truth, "rank": rank(fit.departure, truth), "rank_from_nominal": rank(from_nominal, truth),
            "first": int(fit.ranking[0]), "departure_changed": float(fit.departure[truth]),
            "departure_first": float(fit.departure[fit.ranking[0]]), "loss_nominal": fit.loss_nominal,
            "loss": fit.loss, "iterations": fit.iterations, "evaluations": fit.evaluations,
            "fit_seconds": fit.seconds, "generate_seconds": generated}


def inertia_draw(model, scene, nominal, reference, rng, seed, trajectories, iterations, window):
    """Halve one random bus's inertia; fit the inertias."""
    graph, attrs = nominal
    bus = int(rng.integers(graph.n_nodes))
    start = time.perf_counter()
    data = observed(scene, seed, trajectories, inertia_factors=((bus, 0.5),))
    generated = time.perf_counter() - start
    fit = mpnode.fit_network(model, data, "node_attrs", attrs=[INERTIA], node_attrs=attrs, graph=graph,
                             iterations=iterations, reference=reference, window=window)
    from_nominal = np.abs(fit.fitted[:, 0] - attrs[:, 0]) / attrs[:, 0]
    return {**record(fit, bus, generated, from_nominal), "bus": bus, "fitted": float(fit.fitted[bus, 0]),
            "reference": float(fit.baseline[bus, 0]), "nominal": float(attrs[bus, 0])}


def line_draw(model, scene, nominal, reference, rng, seed, trajectories, iterations, window):
    """Take one random line out of service (drawn again while the grid falls apart or out of step);
    fit the susceptances."""
    graph, attrs = nominal
    line_of, lines = lines_of(graph)
    start = time.perf_counter()
    while True:
        line = int(rng.integers(len(lines)))
        try:
            data = observed(scene, seed, trajectories, lines_out=(tuple(int(v) for v in lines[line]),))
            break
        except InputError:  # a line whose loss splits the grid, or leaves it no synchronous state
            continue
    generated = time.perf_counter() - start
    fit = mpnode.fit_network(model, data, "edge_weights", node_attrs=attrs, graph=graph, iterations=iterations,
                             reference=reference, window=window)
    edge = np.unique(line_of, return_index=True)[1]  # the first edge of each line
    from_nominal = np.abs(fit.fitted[edge] - graph.weights[edge]) / graph.weights[edge]
    return {**record(fit, line, generated, from_nominal), "line": lines[line].tolist(),
            "fitted": float(fit.fitted[edge[line]]), "reference": float(fit.baseline[edge[line]]),
            "nominal": float(graph.weights[edge[line]])}


def summary(draws, reference):
    """Hits (rank 0) both ways and the seconds per fit of one kind of draw, and the reference's fit."""
    seconds = [d["fit_seconds"] for d in draws]
    return {"hits": sum(d["rank"] == 0 for d in draws), "draws": len(draws), "ranks": [d["rank"] for d in draws],
            "hits_from_nominal": sum(d["rank_from_nominal"] == 0 for d in draws),
            "ranks_from_nominal": [d["rank_from_nominal"] for d in draws],
            "fit_seconds_median": float(np.median(seconds)), "fit_seconds_max": float(np.max(seconds)),
            "reference_loss_nominal": reference.loss_nominal, "reference_loss": reference.loss,
            "reference_seconds": reference.seconds, "reference_largest_departure": float(reference.departure.max())}


def main(model_path, draws, trajectories, seed, iterations, window, output):
    model = mpnode.Model.load(model_path)
    scene = BUILTIN["ieee39"]
    nominal = nominal_grid(scene)
    rng = np.random.default_rng(seed)
    out = {"model": model_path, "scene": scene.name, "trajectories": trajectories, "seed": seed,
           "iterations": iterations, "window": window, "inertia": [], "line": []}
    before = observed(scene, seed * 1000, trajectories)
    graph, attrs = nominal
    references = (mpnode.fit_network(model, before, "node_attrs", attrs=[INERTIA], node_attrs=attrs, graph=graph,
                                     iterations=iterations, window=window),
                  mpnode.fit_network(model, before, "edge_weights", node_attrs=attrs, graph=graph,
                                     iterations=iterations, window=window))
    for k in range(draws):
        args = rng, seed * 1000 + 2 * k + 1, trajectories, iterations, window
        out["inertia"].append(inertia_draw(model, scene, nominal, references[0], *args))
        args = rng, seed * 1000 + 2 * k + 2, trajectories, iterations, window
        out["line"].append(line_draw(model, scene, nominal, references[1], *args))
        i, j = out["inertia"][-1], out["line"][-1]
        print(f"draw {k}: bus {i['bus']} ranked {i['rank']} ({i['rank_from_nominal']} from nominal), "
              f"line {j['line']} ranked {j['rank']} ({j['rank_from_nominal']} from nominal)", flush=True)
    out["summary"] = {"inertia_halved": summary(out["inertia"], references[0]),
                      "line_out": summary(out["line"], references[1])}
    with open(output, "w") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out["summary"], indent=1))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--trajectories", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=100, help="L-BFGS-B iterations per fit at most")
    parser.add_argument("--window", type=int, help="fit windows of this many steps (default: whole trajectories)")
    parser.add_argument("-o", "--output", help="the JSON written (default MODEL.grid_inverse.json)")
    args = parser.parse_args()
    main(args.model, args.draws, args.trajectories, args.seed, args.iterations, args.window,
         args.output or args.model + ".grid_inverse.json")

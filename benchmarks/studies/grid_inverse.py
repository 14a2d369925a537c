"""Which bus or line changed: does a model trained on random grids name it on a real one?

Ten random draws on ieee39, each of two changes: one bus's inertia halved (a random bus), and one
line out of service (a random line whose loss leaves the grid connected and in step).  Each draw
generates 20 trajectories of the changed grid from fresh disturbances (data_gen.grids.GridCase's
inertia_factors / lines_out), fits the nominal grid's inertias (`mpnode.fit_network`,
what="node_attrs", attrs=[inertia]) or line susceptances (what="edge_weights") through the model,
and records where the changed bus (line) falls in the fit's ranking, 0 being first.  Prints and
writes one JSON object (default: beside the model, MODEL.grid_inverse.json): hits (rank 0) out of
the draws, the seconds per fit, and every draw.  The numbers in docs/fit-network.md come from it.

    python benchmarks/studies/grid_inverse.py MODEL.h5 [--draws 10] [--trajectories 20] [--seed 0]
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


def record(fit, truth, generated):
    """One draw's entry: where the changed bus (line) ranks, and what the fit found."""
    return {"changed": truth, "rank": int(np.flatnonzero(fit.ranking == truth)[0]), "first": int(fit.ranking[0]),
            "departure_changed": float(fit.departure[truth]), "departure_first": float(fit.departure[fit.ranking[0]]),
            "loss_nominal": fit.loss_nominal, "loss": fit.loss, "iterations": fit.iterations,
            "evaluations": fit.evaluations, "fit_seconds": fit.seconds, "generate_seconds": generated}


def inertia_draw(model, scene, nominal, rng, seed, trajectories, iterations):
    """Halve one random bus's inertia; fit the inertias."""
    graph, attrs = nominal
    bus = int(rng.integers(graph.n_nodes))
    start = time.perf_counter()
    data = observed(scene, seed, trajectories, inertia_factors=((bus, 0.5),))
    generated = time.perf_counter() - start
    fit = mpnode.fit_network(model, data, "node_attrs", attrs=[INERTIA], node_attrs=attrs, graph=graph,
                             iterations=iterations)
    return {**record(fit, bus, generated), "bus": bus, "fitted": float(fit.fitted[bus, 0]),
            "nominal": float(attrs[bus, 0])}


def line_draw(model, scene, nominal, rng, seed, trajectories, iterations):
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
    fit = mpnode.fit_network(model, data, "edge_weights", node_attrs=attrs, graph=graph, iterations=iterations)
    edge = int(np.flatnonzero(line_of == line)[0])
    return {**record(fit, line, generated), "line": lines[line].tolist(), "fitted": float(fit.fitted[edge]),
            "nominal": float(graph.weights[edge])}


def summary(draws):
    """Hits (rank 0) and the seconds per fit of one kind of draw."""
    seconds = [d["fit_seconds"] for d in draws]
    return {"hits": sum(d["rank"] == 0 for d in draws), "draws": len(draws), "ranks": [d["rank"] for d in draws],
            "fit_seconds_median": float(np.median(seconds)), "fit_seconds_max": float(np.max(seconds))}


def main(model_path, draws, trajectories, seed, iterations, output):
    model = mpnode.Model.load(model_path)
    scene = BUILTIN["ieee39"]
    nominal = nominal_grid(scene)
    rng = np.random.default_rng(seed)
    out = {"model": model_path, "scene": scene.name, "trajectories": trajectories, "seed": seed,
           "iterations": iterations, "inertia": [], "line": []}
    for k in range(draws):
        out["inertia"].append(inertia_draw(model, scene, nominal, rng, seed * 1000 + 2 * k + 1, trajectories,
                                           iterations))
        out["line"].append(line_draw(model, scene, nominal, rng, seed * 1000 + 2 * k + 2, trajectories, iterations))
        print(f"draw {k}: bus {out['inertia'][-1]['bus']} ranked {out['inertia'][-1]['rank']}, "
              f"line {out['line'][-1]['line']} ranked {out['line'][-1]['rank']}", flush=True)
    out["summary"] = {"inertia_halved": summary(out["inertia"]), "line_out": summary(out["line"])}
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
    parser.add_argument("-o", "--output", help="the JSON written (default MODEL.grid_inverse.json)")
    args = parser.parse_args()
    main(args.model, args.draws, args.trajectories, args.seed, args.iterations,
         args.output or args.model + ".grid_inverse.json")

"""What each model kind costs on the reference systems: parameters, rollout and training-step time.

For every system (its node count, state and control sizes, the graph of its scene) and
each kind at the command line's default sizes (H = 32, message size 3), times a rollout
of B = 128 trajectories over T = 50 steps and a training step (loss + exact gradient) on
random weights and states, float32, 2 threads; medians of >= 7 calls (bench_engine.timed).
The numbers feed the README's model table.

    python benchmarks/bench_kinds.py [--json]
"""
import argparse
import json

import numpy as np
from bench_engine import timed

from data_gen import load_scene
from mpnode.engine import forward
from mpnode.model.model import Model, batch_graph, to_time_major
from mpnode.training.losses import value_and_grad

SYSTEMS = {"coupled_pendulum": "coupled_pendulum", "lorenz3": "lorenz3", "gene16": "gene16_ba",
           "kuramoto10": "kuramoto10_ba", "quad3": "quad3"}
KINDS = ("mpnode", "l2s", "node")
B, T = 128, 50


def measure(name, scene_name, kind):
    scene = load_scene(scene_name)
    graph = scene.graph.build()[0]
    n = graph.n_nodes
    dx = {"coupled_pendulum": 2, "lorenz": 3, "gene": 1, "kuramoto": 3, "quadrotor_load": 13}[scene.system]
    du = 4 if scene.system == "quadrotor_load" else 0
    model = Model.create(dx, du, message_dim=3, hidden=32, dt=scene.dt, kind=kind, n_nodes=n if kind == "node" else None)
    rng = np.random.default_rng(0)
    x = to_time_major(rng.standard_normal((B, T + 1, n, dx)).astype(np.float32))
    u = to_time_major(rng.standard_normal((B, T, n, du)).astype(np.float32)) if du else None
    flat = batch_graph(graph, B)
    _, roll, _ = timed(lambda: forward(model.spec, model.theta, x[0], flat, u, T))
    _, step, _ = timed(lambda: value_and_grad(model.spec, model.theta, x, flat, u))
    return {"system": name, "kind": kind, "nodes": n, "parameters": int(model.theta.size),
            "rollout_ms": round(roll, 2), "train_step_ms": round(step, 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if not args.json:
        print(f"{'system':<18}{'kind':<8}{'N':>4}{'params':>8}{'rollout ms':>12}{'train ms':>10}   (B={B}, T={T})")
    for name, scene in SYSTEMS.items():
        for kind in KINDS:
            r = measure(name, scene, kind)
            print(json.dumps(r) if args.json else
                  f"{name:<18}{kind:<8}{r['nodes']:>4}{r['parameters']:>8}{r['rollout_ms']:>12.2f}"
                  f"{r['train_step_ms']:>10.2f}", flush=True)


if __name__ == "__main__":
    main()

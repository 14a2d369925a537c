"""What the thrusts change, learned from pairs: segments that start from one state and differ only
in their thrusts (`torque_segments.py --draws 2`, segments 2j and 2j + 1 a pair).

``response``: how far a quad3 model's response to the thrusts is from the truth's, per step h of
the segments: the difference between a pair's predicted rollouts against the difference between
their true ones (all nodes and dimensions, normalised units), median over pairs of the relative
error and of the cosine.

``finetune``: continues a model with Adam on the pairs' plain loss plus LAM times the squared
error of that difference, so that the response (a small difference between two nearly equal
rollouts) weighs in the loss; KEEP files are trained on beside it with the plain loss (one batch
of each after every batch of pairs), so that the model still predicts what it did.

    python benchmarks/studies/mpc/pair_response.py response MODEL.h5 PAIRS.h5
    python benchmarks/studies/mpc/pair_response.py finetune MODEL.h5 OUT.h5 PAIRS.h5 [KEEP.h5 ...] \\
        [--steps 3000] [--lam 100] [--lr 1e-4] [--batch 32] [--seed 0]
"""
import argparse
import json
import time

import numpy as np

from mpnode import engine
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories
from mpnode.model import Model
from mpnode.model.model import batch_graph, to_time_major
from mpnode.training import losses
from mpnode.training.optim import Adam

N = 3  # quadrotors of a quad3 segment


def prepared(model, path, limit=None):
    """(x (T+1, B N, dx), u (T, B N, du), B): a file's segments, time-major, in the model's units."""
    t = read_trajectories(path)
    b = t.x.shape[0] if limit is None else min(limit, t.x.shape[0])
    x = to_time_major(model.normalize_x(np.asarray(t.x[:b])))
    return x, to_time_major(model.normalize_u(np.asarray(t.u[:b]))), b


def halves(a):
    """The two members of every pair of a time-major (T+1, 2P N, d) array: (T+1, P, N, d) each."""
    pairs = a.reshape(a.shape[0], -1, 2, N, a.shape[-1])
    return pairs[:, :, 0], pairs[:, :, 1]


def response(model_path, pairs_path, limit=2000):
    model = Model.load(model_path)
    x, u, b = prepared(model, pairs_path, limit - limit % 2)
    pred = engine.forward(model.spec, model.theta, x[0], batch_graph(Graph.complete(N), b), u, x.shape[0] - 1)
    (pa, pb), (xa, xb) = halves(pred), halves(x)
    want, got = xa - xb, pa - pb
    rows = []
    for h in range(1, x.shape[0]):
        size = np.sqrt((want[h] ** 2).sum(axis=(1, 2)))
        error = np.sqrt(((got[h] - want[h]) ** 2).sum(axis=(1, 2))) / size
        cosine = (got[h] * want[h]).sum(axis=(1, 2)) / (np.sqrt((got[h] ** 2).sum(axis=(1, 2))) * size)
        rows.append({"h": h, "relative_error": float(np.median(error)), "cosine": float(np.median(cosine))})
    print(json.dumps({"model": model_path, "pairs": b // 2, "response": rows}))


def finetune(model_path, out, pairs_path, keep, steps, lam, lr, batch, seed):
    model = Model.load(model_path)
    spec, theta, graph = model.spec, model.theta, Graph.complete(N)
    pairs, kept = prepared(model, pairs_path), [prepared(model, k) for k in keep]
    rng, opt = np.random.default_rng(seed), Adam(theta.size, lr)

    def rows(trajectories):
        return (np.asarray(trajectories)[:, None] * N + np.arange(N)).ravel()

    def pair_gradient():
        x, u, b = pairs
        j = rng.choice(b // 2, batch, replace=False)
        r = rows(np.ravel(np.stack([2 * j, 2 * j + 1], axis=1)))
        xb, m = x[:, r], len(r)
        pred, vjp = engine.forward_with_vjp(spec, theta, xb[0], batch_graph(graph, 2 * batch), u[:, r], xb.shape[0] - 1)
        value, g = losses.huber(pred, xb, m)
        (pa, pb), (xa, xb_) = halves(pred), halves(xb)
        d = (pa - pb) - (xa - xb_)
        d[0] = 0
        ga, gb = halves(g)
        ga += (2 * lam / m) * d
        gb -= (2 * lam / m) * d
        return value, lam * float(np.sum(d * d)) / m, vjp(g)[0]

    def kept_gradient(x, u, b):
        r = rows(rng.choice(b, batch, replace=False))
        return losses.value_and_grad(spec, theta, x[:, r], batch_graph(graph, batch), u[:, r], "huber")[1]

    start = time.perf_counter()
    for step in range(1, steps + 1):
        value, difference, g = pair_gradient()
        theta -= opt.update(np.asarray(g, dtype=np.float64)).astype(theta.dtype)
        for k in kept:  # each from the weights the step before left
            theta -= opt.update(np.asarray(kept_gradient(*k), dtype=np.float64)).astype(theta.dtype)
        if step % 500 == 0:
            print(json.dumps({"step": step, "pair_loss": value, "difference_loss": difference,
                              "seconds": round(time.perf_counter() - start, 1)}), flush=True)
    model.save(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("response")
    r.add_argument("model"), r.add_argument("pairs")
    f = sub.add_parser("finetune")
    f.add_argument("model"), f.add_argument("out"), f.add_argument("pairs"), f.add_argument("keep", nargs="*")
    f.add_argument("--steps", type=int, default=3000)
    f.add_argument("--lam", type=float, default=100.0, help="weight of the difference's squared error")
    f.add_argument("--lr", type=float, default=1e-4)
    f.add_argument("--batch", type=int, default=32, help="pairs of a pair batch; segments of a KEEP batch")
    f.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if a.command == "response":
        response(a.model, a.pairs)
    else:
        finetune(a.model, a.out, a.pairs, a.keep, a.steps, a.lam, a.lr, a.batch, a.seed)


if __name__ == "__main__":
    main()

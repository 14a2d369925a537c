"""Error by state block, quaternion norms and trivial baselines for the run.sh models.

usage: python analyze.py OUT   (after run.sh; prints markdown)
For every model and test file: the normalised MSE (mpnode eval's definition: squared error
over the test file's per-dimension variance, mean over steps 1..T) split into the blocks
position r, quaternion q, velocity v, body rates w; the position RMSE in metres at the last
step; and the predicted quaternions' norm |q| (the data's are 1 to 2e-16).  Baselines:
"hold x0" (every state stays at its initial value) and "file mean" (nMSE 1 by construction).
"""
import os
import sys

import numpy as np

from mpnode.data import read_trajectories
from mpnode.evaluation.evaluate import rollout_all
from mpnode.model import Model

BLOCKS = {"r": slice(0, 3), "q": slice(3, 7), "v": slice(7, 10), "w": slice(10, 13)}


def blocks(pred, x):
    var = x.reshape(-1, x.shape[-1]).var(axis=0)
    e = (pred[:, 1:].astype(np.float64) - x[:, 1:]) ** 2 / var  # (B, T, N, dx)
    out = {k: float(e[..., s].mean()) for k, s in BLOCKS.items()}
    out["all"] = float(e.mean())
    out["pos_rmse_T"] = float(np.sqrt(((pred[:, -1, :, 0:3] - x[:, -1, :, 0:3]) ** 2).sum(-1).mean()))
    return out


def main(out):
    tests = {k: read_trajectories(os.path.join(out, f"{k}_test.h5")) for k in ("q3", "q6")}
    runs = [(f"q3_m{m}", ("q3", "q6")) for m in (7, 13, 20)] + [(k, ("q6",)) for k in ("q6_finetuned", "q6_scratch", "q6_finetuned_t", "q6_scratch_t")]
    print("| model | test | nMSE all | r | q | v | w | pos. RMSE step T (m) | predicted abs(q): min / max |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k, t in tests.items():
        x = np.asarray(t.x, dtype=np.float64)
        hold = np.repeat(x[:, :1], x.shape[1], axis=1)
        b = blocks(hold, x)
        print(f"| baseline: hold x0 | {k} | {b['all']:.3g} | {b['r']:.3g} | {b['q']:.3g} | {b['v']:.3g} | {b['w']:.3g} "
              f"| {b['pos_rmse_T']:.3g} | 1 / 1 |")
    for name, keys in runs:
        path = os.path.join(out, name + ".h5")
        if not os.path.exists(path):
            continue
        model = Model.load(path)
        for k in keys:
            t = tests[k]
            x = np.asarray(t.x, dtype=np.float64)
            pred = rollout_all(model, x[:, 0], t.graphs, t.graph_index, t.horizon, np.asarray(t.u)).astype(np.float64)
            if not np.all(np.isfinite(pred)):
                print(f"| {name} | {k} | non-finite | | | | | | |")
                continue
            b = blocks(pred, x)
            qn = np.linalg.norm(pred[..., 3:7], axis=-1)
            print(f"| {name} | {k} | {b['all']:.3g} | {b['r']:.3g} | {b['q']:.3g} | {b['v']:.3g} | {b['w']:.3g} "
                  f"| {b['pos_rmse_T']:.3g} | {qn.min():.3f} / {qn.max():.3f} |")


if __name__ == "__main__":
    main(sys.argv[1])

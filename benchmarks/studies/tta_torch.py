"""Time to accuracy, the torch side: `mpnode train`'s recipe (batch 128) written in torch + torchdiffeq.

This file is a *peer*, not part of mpnode: it imports numpy, h5py, torch and torchdiffeq
and nothing of mpnode (it reads the trajectory file with h5py, docs/trajectory-format.md).
time_to_accuracy.py runs it beside `mpnode.runs.train` on the same file, and the
README's "Time to accuracy" section says what the comparison is made of.

The recipe is mpnode's (the paper's batch of 128; mpnode/train.py, batches.py, losses.py, optim.py,
layouts.py), step by step, so that both sides do the same arithmetic from the same start:
- split: the same random 70/30 split (numpy's generator seeded [seed, 2, 0]);
- z-score constants fitted on the training split (float64, population std), states
  stored in float32; Gaussian noise (std 1e-4) added once to the normalised training
  states from the generator seeded [seed, 3, 0];
- model: the MP-NODE per-node MLP [x, m'] -> [dx/dt, dm/dt] (H 32, two tanh layers),
  m' the mean of the neighbours' messages (0 for a node that hears nobody), messages
  start at 0; Glorot-uniform weights and zero biases drawn exactly as mpnode draws them;
- classic RK4 (1/6, 1/3, 1/3, 1/6) at the data's dt through torchdiffeq.odeint, one step
  per saved state, gradient by backpropagation through the solver (not the adjoint).
  torchdiffeq's own 'rk4' is the 3/8-rule variant; 'rk4_classic' below registers the
  classic step that torchdiffeq also ships;
  --method rk4 picks the 3/8 rule instead (same cost);
- loss: Huber (delta 1) on the normalised states, summed over steps 1..T and dimensions,
  divided by the batch's node count;
- batches of 128 trajectories, shuffled per epoch by the generator seeded [seed, 1, epoch]
  (mpnode's order, batch for batch); Adam (lr 1e-3, 0.9, 0.999, 1e-8) after clipping each
  parameter array's gradient norm to 500; the same bad-step rule (non-finite, or a loss
  above 100x the initial validation loss: back to the best weights and Adam state, learning
  rate halved, five in a row stop the run); learning rate halved after 500 epochs without a
  new best validation loss;
- with --curriculum (mpnode's --horizon-curriculum), the first --curriculum-epochs epochs
  train on consecutive windows of the first length (each from its own noisy true state, the
  last one ending at T), the next on the second, the rest on the full horizon;
- validation after every epoch: full-horizon rollouts of the validation split, normalised
  MSE as mpnode's Validator computes it (per-dimension variance of the validation states,
  error over steps 1..T, mean over dimensions).
Differences that remain: float32 Adam moments (mpnode keeps them in float64) and float32
sums in the loss (mpnode sums in float64).

    python benchmarks/studies/tta_torch.py DATA.h5 --thresholds 0.01,0.002 --time-limit 600 --threads 2

prints one line "RESULT {json}": per epoch [epoch, wall seconds from the start (before
reading the file) to the end of its validation, its validation nMSE, CPU seconds of the
process], and the first epoch reaching each threshold.  torch is imported by `main` (after the
thread variables are set), so this file imports without it.
"""
import argparse
import copy
import json
import math
import os
import sys
import time

import h5py
import numpy as np

T_IMPORT = time.perf_counter()


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="trajectory file (HDF5, mpnode's format, one graph, no controls)")
    ap.add_argument("--thresholds", default="0.01", help="validation nMSE thresholds, comma separated")
    ap.add_argument("--time-limit", type=float, default=600.0, help="seconds of training at most")
    ap.add_argument("--epochs", type=int, default=4000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--method", default="rk4_classic", choices=["rk4_classic", "rk4"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--curriculum", default="", help="window lengths, e.g. 5,10 (mpnode's --horizon-curriculum)")
    ap.add_argument("--curriculum-epochs", type=int, default=100)
    return ap.parse_args(argv)


H, DM = 32, 3
BATCH, VAL_SPLIT, NOISE = 128, 0.3, 1e-4
LR, BETAS, EPS, CLIP = 1e-3, (0.9, 0.999), 1e-8, 500.0
PATIENCE, LR_DECAY, MIN_LR, BLOWUP, MAX_BAD = 500, 0.5, 1e-6, 100.0, 5


# ---------------------------------------------------------------------------- data
def read(path):
    """(x (B, T+1, N, dx) as stored, indptr, indices, dt) of a one-graph file without controls."""
    with h5py.File(path, "r") as f:
        if "u" in f:
            sys.exit(f"{path}: has controls (u); this peer covers systems without controls")
        if len(f["graphs"]) != 1:
            sys.exit(f"{path}: has {len(f['graphs'])} graphs; this peer covers one-graph files")
        return f["x"][...], f["graphs/0/indptr"][...], f["graphs/0/indices"][...], float(f.attrs["dt"])


def split(n, seed):
    """mpnode.training.batches.split_indices for file 0: (train idx, val idx), sorted."""
    perm = np.random.default_rng([seed, 2, 0]).permutation(n)
    n_val = min(int(round(VAL_SPLIT * n)), n - 1)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def zscore_constants(x):
    """mpnode.training.batches.fit_normalization: per-dimension mean and population std (float64)."""
    d = x.shape[-1]
    flat = x.reshape(-1, d)
    mean = flat.sum(axis=0, dtype=np.float64) / flat.shape[0]
    std = np.sqrt(((flat - mean) ** 2).sum(axis=0) / flat.shape[0])
    std[~(std > 1e-12 * np.maximum(1.0, np.abs(mean)))] = 1.0
    return mean, std


def part(x, mean, std, dtype, noise_rng=None):
    """Normalised states in the model's dtype (plus noise), time-major (T+1, B, N, dx)."""
    xn = ((x - mean) / std).astype(dtype)
    if noise_rng is not None:
        xn = (xn + noise_rng.standard_normal(xn.shape) * NOISE).astype(dtype)
    return np.ascontiguousarray(xn.transpose(1, 0, 2, 3))


def edges(indptr, indices, copies):
    """(src, dst, 1/in-degree) of ``copies`` copies of the graph: row i lists whom i hears."""
    n = len(indptr) - 1
    dst1 = np.repeat(np.arange(n), np.diff(indptr))
    off = (np.arange(copies) * n)[:, None]
    deg = np.tile(np.diff(indptr), copies).astype(np.float64)
    inv = np.where(deg > 0, 1.0 / np.maximum(deg, 1.0), 0.0)
    return (indices[None, :] + off).reshape(-1), (dst1[None, :] + off).reshape(-1), inv


def window_starts(horizon, window):
    """mpnode.training.batches.window_starts: consecutive windows, one last window ending at T."""
    if window >= horizon:
        return [0]
    starts = list(range(0, horizon - window + 1, window))
    if starts[-1] + window < horizon:
        starts.append(horizon - window)
    return starts


def windows(x, window):
    """mpnode's Part.windows: (w+1, B * n_windows, N, dx), window j of trajectory b at b * n_windows + j."""
    t1, b, n, dx = x.shape
    starts = window_starts(t1 - 1, window)
    w = min(window, t1 - 1)
    stacked = np.stack([x[a:a + w + 1] for a in starts], axis=2)
    return np.ascontiguousarray(stacked).reshape(w + 1, b * len(starts), n, dx)


def epoch_batches(n, seed, epoch):
    """mpnode.training.batches.epoch_batches for one part: local index arrays, shuffled."""
    rng = np.random.default_rng([seed, 1, epoch])
    perm = rng.permutation(n)
    out = [perm[i:i + BATCH] for i in range(0, n, BATCH)]
    return [out[i] for i in rng.permutation(len(out))]


# ---------------------------------------------------------------------------- model
def glorot(dx, seed, dtype):
    """mpnode.engine.layouts.glorot_init for an MP-NODE model: the same numbers, in the same order."""
    rng = np.random.default_rng(seed)
    shapes = {"W1": (dx + DM, H), "b1": (H,), "W2": (H, H), "b2": (H,), "W3": (H, dx + DM), "b3": (dx + DM,)}
    out = {}
    for name, shape in shapes.items():
        if len(shape) == 2:
            limit = np.sqrt(6.0 / (shape[0] + shape[1]))
            out[name] = rng.uniform(-limit, limit, size=shape).astype(dtype)
        else:
            out[name] = np.zeros(shape, dtype=dtype)
    return out


def import_torch():
    """Import torch and torchdiffeq into this module's names, register the classic RK4 step
    ('rk4_classic') and define the `Field` on them; the thread variables must be set before."""
    global torch, torchdiffeq, odeint, Field
    import importlib

    import torch
    import torchdiffeq
    from torchdiffeq import odeint
    from torchdiffeq._impl.fixed_grid import RK4
    from torchdiffeq._impl.misc import Perturb
    from torchdiffeq._impl.rk_common import rk4_step_func

    class ClassicRK4(RK4):
        """torchdiffeq's fixed-grid RK4 with its classic (1/6, 1/3, 1/3, 1/6) step function."""

        def _step_func(self, func, t0, dt, t1, y0):
            f0 = func(t0, y0, perturb=Perturb.NEXT if self.perturb else Perturb.NONE)
            return rk4_step_func(func, t0, dt, t1, y0, f0=f0, perturb=self.perturb), f0

    importlib.import_module("torchdiffeq._impl.odeint").SOLVERS["rk4_classic"] = ClassicRK4

    class Field(torch.nn.Module):
        """f(t, z) of the batched graph; z = [x, m] of shape (M, dx + dm)."""

        def __init__(self, dx, params, dtype):
            super().__init__()
            self.dx = dx
            for k, v in params.items():
                setattr(self, k, torch.nn.Parameter(torch.tensor(v, dtype=dtype)))
            self.graph = None

        def use_graph(self, graph):
            self.graph = graph

        def forward(self, t, z):
            src, dst, inv = self.graph
            x, m = z[:, :self.dx], z[:, self.dx:]
            agg = torch.zeros_like(m).index_add_(0, dst, m.index_select(0, src)) * inv
            h = torch.tanh(torch.addmm(self.b1, torch.cat([x, agg], dim=1), self.W1))
            h = torch.tanh(torch.addmm(self.b2, h, self.W2))
            return torch.addmm(self.b3, h, self.W3)


# ---------------------------------------------------------------------------- training
class Run:
    def __init__(self, args):
        self.args = args
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        dtype = np.dtype(args.dtype)
        self.tdtype = getattr(torch, args.dtype)
        x, indptr, indices, dt = read(args.data)
        self.n_nodes, self.dx = x.shape[2], x.shape[3]
        tr, va = split(x.shape[0], args.seed)
        self.val_index = va
        mean, std = zscore_constants(x[tr])
        self.full = part(x[tr], mean, std, dtype, np.random.default_rng([args.seed, 3, 0]))
        self.curriculum = [int(w) for w in args.curriculum.split(",") if w.strip()]
        self.stage, self.train = None, None
        self.val = torch.from_numpy(part(x[va], mean, std, dtype))
        flat = self.val.reshape(-1, self.dx).double()
        self.val_var = flat.var(dim=0, unbiased=False).clamp_min(0)
        self.val_var[self.val_var == 0] = 1.0
        self.ts = torch.arange(x.shape[1], dtype=self.tdtype) * dt
        self.indptr, self.indices = indptr, indices
        self.graphs = {}
        self.field = Field(self.dx, glorot(self.dx, args.seed, dtype), self.tdtype)
        self.params = list(self.field.parameters())
        self.opt = torch.optim.Adam(self.params, lr=LR, betas=BETAS, eps=EPS)
        self.lr = LR

    def graph(self, copies):
        g = self.graphs.get(copies)
        if g is None:
            src, dst, inv = edges(self.indptr, self.indices, copies)
            g = self.graphs[copies] = (torch.from_numpy(src), torch.from_numpy(dst),
                                       torch.tensor(inv, dtype=self.tdtype)[:, None])
        return g

    def rollout(self, x):
        """Predicted states (T+1, M, dx) from x[0] (x: (T+1, b, N, dx) normalised)."""
        b = x.shape[1]
        self.field.use_graph(self.graph(b))
        x0 = x[0].reshape(b * self.n_nodes, self.dx)
        z0 = torch.cat([x0, torch.zeros(x0.shape[0], DM, dtype=x0.dtype)], dim=1)
        return odeint(self.field, z0, self.ts[:x.shape[0]], method=self.args.method)[:, :, :self.dx]

    def batch_loss(self, x):
        pred = self.rollout(x)
        target = x.reshape(x.shape[0], -1, self.dx)
        return torch.nn.functional.huber_loss(pred[1:], target[1:], reduction="sum", delta=1.0) / target.shape[1]

    def validate(self):
        """(loss per node, nMSE) of the current weights on the validation split."""
        with torch.no_grad():
            pred = self.rollout(self.val)
            target = self.val.reshape(self.val.shape[0], -1, self.dx)
            loss = torch.nn.functional.huber_loss(pred[1:].double(), target[1:].double(), reduction="sum", delta=1.0)
            e = pred[1:].double() - target[1:]
            count = e.shape[0] * e.shape[1]
            nmse = float(((e * e).sum(dim=(0, 1)) / count / self.val_var).mean())
            loss = float(loss) / target.shape[1]
            ok = math.isfinite(loss) and math.isfinite(nmse)
            return (loss, nmse) if ok else (math.inf, math.inf)

    def step(self, x):
        """One Adam step on batch x; returns a sentence when the step must be skipped."""
        self.opt.zero_grad(set_to_none=True)
        loss = self.batch_loss(x)
        lv = loss.detach().item()
        if not math.isfinite(lv):
            return "non-finite loss"
        if BLOWUP and lv > BLOWUP * self.ref_loss:
            return "loss blow-up"
        loss.backward()
        if not all(bool(torch.isfinite(p.grad).all()) for p in self.params):
            return "non-finite gradient"
        for p in self.params:  # mpnode's per-array clip
            n = float(p.grad.norm())
            if n > CLIP:
                p.grad.mul_(CLIP / n)
        backup = [p.detach().clone() for p in self.params]
        self.opt.step()
        if not all(bool(torch.isfinite(p).all()) for p in self.params):
            with torch.no_grad():
                for p, b in zip(self.params, backup):
                    p.copy_(b)
            return "non-finite weights"
        return None

    def keep_best(self, val):
        self.best_val, self.best_epoch, self.last_improve, self.bad = val, self.epoch, self.epoch, 0
        self.best = ([p.detach().clone() for p in self.params], copy.deepcopy(self.opt.state_dict()))

    def restore_best(self):
        with torch.no_grad():
            for p, b in zip(self.params, self.best[0]):
                p.copy_(b)
        self.opt.load_state_dict(copy.deepcopy(self.best[1]))

    def set_lr(self, lr):
        self.lr = lr
        for g in self.opt.param_groups:
            g["lr"] = lr

    def use_stage(self, epoch):
        """mpnode's horizon curriculum: the training windows of epoch ``epoch``'s stage (1-based)."""
        c = self.curriculum
        stage = min((epoch - 1) // self.args.curriculum_epochs, len(c)) if c else 0
        if stage != self.stage:
            self.stage = stage
            self.train = torch.from_numpy(self.full if stage >= len(c) else windows(self.full, c[stage]))

    def run_epoch(self):
        self.use_stage(self.epoch + 1)
        for sel in epoch_batches(self.train.shape[1], self.args.seed, self.epoch + 1):
            problem = self.step(self.train[:, torch.from_numpy(sel)])
            if problem is not None:
                self.restore_best()
                self.bad += 1
                self.set_lr(self.lr * 0.5)
                if self.bad >= MAX_BAD:
                    raise RuntimeError(f"diverged at epoch {self.epoch + 1} ({problem})")

    def end_of_epoch(self, val):
        if math.isfinite(val) and val < self.best_val:
            self.keep_best(val)
        elif self.epoch - self.last_improve >= PATIENCE and self.lr > MIN_LR:
            self.set_lr(self.lr * LR_DECAY)
            self.last_improve = self.epoch

    def fit(self, thresholds):
        self.epoch = 0
        v0, nmse0 = self.validate()
        self.ref_loss = v0
        self.best_val = math.inf
        self.keep_best(v0)
        history = [(0, time.perf_counter() - self.t0, nmse0, time.process_time() - self.c0)]
        reached = {}
        status = "epochs"
        while self.epoch < self.args.epochs:
            try:
                self.run_epoch()
            except RuntimeError as e:
                status = str(e)
                break
            self.epoch += 1
            val, nmse = self.validate()
            self.end_of_epoch(val)
            now = time.perf_counter() - self.t0
            history.append((self.epoch, now, nmse, time.process_time() - self.c0))
            for thr in thresholds:
                if thr not in reached and nmse <= thr:
                    reached[thr] = (self.epoch, now)
            if len(reached) == len(thresholds):
                status = "reached"
                break
            if now >= self.args.time_limit:
                status = "time_limit"
                break
        return status, reached, history


def main():
    args = parse_args()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(args.threads)  # before torch is imported
    import_torch()
    torch.set_num_threads(args.threads)
    thresholds = [float(t) for t in args.thresholds.split(",")]
    run = Run(args)
    status, reached, history = run.fit(thresholds)
    record = {"side": "torch", "data": os.path.abspath(args.data), "status": status, "threads": args.threads,
              "method": args.method, "dtype": args.dtype, "curriculum": run.curriculum,
              "curriculum_epochs": args.curriculum_epochs, "startup_seconds": run.t0 - T_IMPORT,
              "val_index_sum": int(run.val_index.sum()), "n_val": int(len(run.val_index)),
              "reached": {f"{k:g}": {"epoch": e, "seconds": s} for k, (e, s) in reached.items()},
              "history": [[e, round(s, 4), n, round(c, 4)] for e, s, n, c in history],
              "versions": {"torch": torch.__version__, "torchdiffeq": torchdiffeq.__version__}}
    sys.stdout.write("RESULT " + json.dumps(record) + "\n")


if __name__ == "__main__":
    main()

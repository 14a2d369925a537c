"""Full-batch L-BFGS after Adam: does a quasi-Newton stage fit the swarm faster than more Adam steps?

Continues a finished `mpnode train` run from its best weights with scipy's L-BFGS-B on the whole
training split at once (the run's own split, normalisation, loss and noise, from its checkpoint
beside the model), for a wall-time budget; validates every 10 iterations as training does and
keeps the best weights.  The model it writes is scored as any other (`mpnode eval`).

    python benchmarks/studies/quadrotor/lbfgs_polish.py RUN.h5 OUT.h5 TRAIN.h5... [--seconds S] [--memory M]
"""
import argparse
import json
import time

import numpy as np
import scipy.optimize

from mpnode.data import read_trajectories
from mpnode.training import losses
from mpnode.training.batches import TrainingData
from mpnode.training.loop import Validator, weighted_nmse
from mpnode.training.state import TrainState, state_path


class Budget(Exception):
    """The wall-time budget is spent."""


def full_batch(parts, spec, config, dtype):
    """The training loss over every training trajectory and its gradient, as a function of float64 weights."""
    batches = [p.batch(np.arange(p.n)) for p in parts]
    nodes = sum(b.x.shape[1] for b in batches)

    def value_and_grad(theta64):
        theta = theta64.astype(dtype)
        total, grad = 0.0, np.zeros(theta64.size)
        for b in batches:
            loss, g = losses.batch_value_and_grad(spec, theta, b, config.loss, 0)
            total += loss * b.x.shape[1]
            grad += g * b.x.shape[1]
        return total / nodes, grad / nodes

    return value_and_grad


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run"), ap.add_argument("out"), ap.add_argument("files", nargs="+")
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--memory", type=int, default=20, help="L-BFGS correction pairs")
    a = ap.parse_args()
    state = TrainState.load(state_path(a.run))
    model, config = state.best_model(), state.config
    data = TrainingData([read_trajectories(f) for f in a.files], config, a.files)
    train, val = data.parts(model, "keep")
    validate, objective = Validator(val, config.loss), full_batch(train, model.spec, config, model.dtype)
    start_loss, files = validate(model.spec, model.theta)
    best = {"val_loss": start_loss, "val_nmse": weighted_nmse(files), "iteration": 0, "theta": model.theta.copy()}
    trace, t0, count = [], time.perf_counter(), [0]

    def after_iteration(theta64):
        count[0] += 1
        if count[0] % 10:
            return
        theta = theta64.astype(model.dtype)
        loss, files = validate(model.spec, theta)
        seconds = time.perf_counter() - t0
        trace.append({"iteration": count[0], "seconds": round(seconds, 1), "val_nmse": weighted_nmse(files)})
        print(json.dumps(trace[-1]), flush=True)
        if loss < best["val_loss"]:
            best.update(val_loss=loss, val_nmse=weighted_nmse(files), iteration=count[0], theta=theta)
        if seconds > a.seconds:
            raise Budget

    try:
        scipy.optimize.minimize(objective, model.theta.astype(np.float64), jac=True, method="L-BFGS-B",
                                callback=after_iteration,
                                options={"maxiter": 10**6, "maxcor": a.memory, "ftol": 0.0, "gtol": 0.0})
    except Budget:
        pass
    model.theta[:] = best.pop("theta")
    model.save(a.out)
    print(json.dumps({"start_val_nmse": weighted_nmse(state.best_files), **best, "iterations": count[0]}))


if __name__ == "__main__":
    main()

"""Ensembles from files: K members trained as tasks on the local process pool or on Dask, then
their spread calibrated on the validation trajectories, into one model file (version 5).

Every member is one ordinary run (`run.train`, or `run.finetune` from the parent's member or
the parent itself) with seed SEED + k; all share the validation split of SEED (``split_seed``)
and hence one normalisation, so their predictions differ only by what the seed and, with
``bootstrap``, the resample of the training trajectories decide.  ``time_limit`` is the
ensemble's: the members run in as few waves as the workers allow (all at once in the pool:
a process of one thread each, so K members share the cores for the whole budget), and each
wave gets its share of the budget.
"""
import math
import os
import tempfile

import numpy as np

from mpnode.base.errors import InputError
from mpnode.model import Model
from mpnode.model.ensemble import Ensemble, fitted_scale
from mpnode.training.batches import TrainingData

from . import run as runs
from .executors import open_executor

#: of the budget, what the members' training gets (the rest: starting the workers, calibrating)
TRAINING_SHARE = 0.93


def train_ensemble(paths, output, options, *, recipe_name="auto", scheduler=None, notify=None, datasets=None,
                   names=None, parent=None, refit_norm=False):
    """Train ``options["ensemble"]`` = K >= 2 members on ``paths`` into the ensemble file ``output``
    (fine-tune them from the model file ``parent`` when given: an ensemble's members each from
    its own, one model's from it); returns (Ensemble, [member's TrainResult summary])."""
    options = runs.canonical(options)
    config = runs.split_options(options)[1]  # K, the seed and the budget are the run's options, checked
    k, seed = config.ensemble, config.seed
    if k < 2:
        raise InputError("options", "ensemble", f"is {k}", "K >= 2 members (1: one model, mpnode.runs.train)")
    datasets = datasets or runs.read_all(paths)
    names = list(map(str, names or paths))
    parents = _parents(parent, k)
    if parent is None:
        options, chosen = runs.with_recipe(options, recipe_name, datasets)
        runs._announce(notify, chosen, f"recipe {recipe_name} for {datasets[0].system}")
    with open_executor(scheduler, workers=k, one_thread=True) as farm:
        waves = math.ceil(k / max(1, farm.workers))
        share = {}
        if config.time_limit is not None:
            share["time_limit"] = config.time_limit * TRAINING_SHARE / waves
        if notify:
            notify(f"ensemble: {k} members in {waves} wave(s) on {farm.workers} worker(s)"
                   + (f", {share['time_limit']:.0f} s each" if share else ""))
        futures = [farm.submit(train_member, list(map(str, paths)), names, datasets,
                               {**options, **share, "ensemble": 1, "seed": seed + i, "split_seed": seed},
                               recipe_name, parents[i], refit_norm) for i in range(k)]
        results = [f.result() for f in futures]
    members = [r.pop("model") for r in results]
    ensemble = Ensemble(members, member_info={
        "member_seed": np.arange(seed, seed + k), "member_epoch": np.array([r["best_epoch"] for r in results]),
        "member_val_loss": np.array([r["best_val_loss"] for r in results])}, attrs=members[0].attrs)
    for own in ("seed", "epoch", "val_loss"):  # member 0's: each member's are under ensemble/
        ensemble.attrs.pop(own, None)
    ensemble.spread_scale = calibration(ensemble, datasets, names, {**options, "seed": seed}, notify)
    ensemble.save(output, seed=seed)
    return ensemble, results


def ensemble_size(path):
    """K of the model file ``path``: its members, 1 for one model."""
    model = Model.load(path)
    return model.size if isinstance(model, Ensemble) else 1


def _parents(parent, k):
    """Each member's starting model: None (train afresh), or the parent's member i / the parent itself."""
    if parent is None:
        return [None] * k
    model = Model.load(parent)
    if isinstance(model, Ensemble):
        if model.size != k:
            raise InputError(parent, "ensemble_size", f"is {model.size} members, not the {k} of --ensemble",
                             f"--ensemble {model.size} (each member continues its own)")
        return list(model.members)
    return [model] * k


def train_member(paths, names, datasets, options, recipe_name, parent, refit_norm):
    """One member's run (a task of the farm): trains in a temporary folder and returns its model
    and figures (nothing of it stays on the worker)."""
    with tempfile.TemporaryDirectory(prefix="mpnode-member-") as tmp:
        out = os.path.join(tmp, "member.h5")
        if parent is None:
            result = runs.train(paths, out, options, recipe_name=recipe_name, datasets=datasets, names=names)
        else:
            parent_path = os.path.join(tmp, "parent.h5")
            parent.save(parent_path)
            fine = {k: v for k, v in options.items() if k in runs.TRAIN_OPTIONS or k == "substeps"}
            result = runs.finetune(parent_path, paths, out, fine, refit_norm=refit_norm, recipe_name=recipe_name,
                                   datasets=datasets, names=names, parent_name="ensemble member")
    return {"model": result.model, "status": result.status, "best_epoch": result.best_epoch,
            "epoch": result.epoch, "best_val_loss": float(result.best_val_loss), "seconds": result.seconds,
            "val_nmse": result.val_nmse}


def calibration(ensemble, datasets, names, options, notify=None):
    """(dx,) the spread's scale that makes the 90% band cover 90% of the validation trajectories'
    true values (their rollouts from the first observation, steps 1..T); 1 without validation data."""
    from mpnode.evaluation.evaluate import evaluate, subset

    config = runs.split_options(options)[1]
    split = TrainingData(datasets, config, names).split
    truth, mean, std = [], [], []
    for traj, (_, val), name in zip(datasets, split, names):  # the files as read: evaluate hears them as the model
        if len(val):
            r = evaluate(ensemble, subset(traj, val), source=name, check_stability=False,
                         ignore_attrs=config.ignore_attrs)
            truth.append(r.scored[:, 1:].reshape(-1, traj.state_dim))
            mean.append(r.predictions[:, 1:].reshape(-1, traj.state_dim))
            std.append(r.member_std[:, 1:].reshape(-1, traj.state_dim))
    if not truth:
        if notify:
            notify("warning: no validation trajectories: the ensemble's spread is not calibrated (scale 1)")
        return np.ones(ensemble.spec.state_dim)
    scale = fitted_scale(np.concatenate(truth), np.concatenate(mean), np.concatenate(std))
    if notify:
        notify("ensemble spread calibrated on the validation trajectories: scale "
               + ", ".join(f"{s:.3g}" for s in scale))
    return scale

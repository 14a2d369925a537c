"""Data that cannot be learned as given, named before training starts, with the fix.

* A state dimension with zero variance (one value in every training trajectory, step and
  node): there is nothing to learn in it, and every error measured against its variance is
  infinite.  A dimension never observed (NaN throughout) is not of zero variance: it has
  no variance at all, and is not refused here.
* No validation trajectory while a validation split is asked for (one trajectory per file):
  the best model could not be chosen on held-out data.
* Values so large that the normalisation overflows (the variance of x * 1e300 is inf).
"""
import warnings

import numpy as np

from mpnode.base.errors import InputError


def check_learnable(data, config):
    """InputError naming the files, the field and the fix when ``data`` (a TrainingData split
    under ``config``) cannot be learned as given (module docstring)."""
    source = data.sources[0] if len(data.sources) == 1 else "training data (" + ", ".join(data.sources) + ")"
    for field in ("x", "u"):
        if field == "x" or data.datasets[0].control_dim:
            _check_overflow(data, field, source)
    _check_constant(data, source)
    _check_validation(data, config)


def _check_overflow(data, field, source):
    with np.errstate(over="ignore", invalid="ignore"):
        mean, std = data.normalization()[:2] if field == "x" else data.normalization()[2:]
    if not (np.any(np.isinf(mean)) or np.any(np.isinf(std))):  # NaN (never observed) is not overflow
        return
    biggest = max(float(np.nanmax(np.abs(a))) for a in data.training(field))
    raise InputError(source, field, f"has values up to {biggest:.3g}, whose variance overflows (float64 holds "
                     "up to 1.8e308), so the data cannot be normalised", f"the data rescaled before they are "
                     f"converted (e.g. {field} / {10 ** np.floor(np.log10(biggest)):.0e}: the model learns in "
                     "normalised units either way)")


def _check_constant(data, source):
    arrays = [a.reshape(-1, a.shape[-1]) for a in data.training("x") if a.size]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice": a dimension never observed
        low = np.nanmin([np.nanmin(a, axis=0) for a in arrays], axis=0)
        high = np.nanmax([np.nanmax(a, axis=0) for a in arrays], axis=0)
    constant = np.flatnonzero(low == high)  # a dimension of NaN only has NaN bounds: not constant
    if constant.size:
        d = int(constant[0])
        names = data.datasets[0].attrs.get("state_names")
        field = f"x[..., {d}]" + (f" ({names[d]})" if names is not None and len(names) > d else "")
        others = [i for i in range(len(low)) if i not in set(constant.tolist())]
        raise InputError(source, field, f"is {low[d]:g} in every training trajectory, step and node: a state "
                         "dimension without variation gives the model nothing to learn there, and makes every "
                         "error measured against its variance infinite",
                         f"the data without it (x[..., {others}]), or trajectories in which it varies")


def _check_validation(data, config):
    if sum(len(va) for _, va in data.split) or not (config.val_split or config.val_graphs):
        return
    few = [f"{src} ({t.n_trajectories})" for src, t in zip(data.sources, data.datasets)]
    raise InputError(", ".join(data.sources), "x", "leaves no trajectory for validation: "
                     f"{', '.join(few)} trajectories, and --val-split {config.val_split:g} of that rounds to 0, so the "
                     "best model could not be chosen on data it was not trained on",
                     "more trajectories (a long recording can be cut into several shorter ones), or --val-split 0 "
                     "to train without validation (the best model is then the one with the lowest training loss)")

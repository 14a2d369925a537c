"""An ensemble: K models of one kind and size trained apart (other seeds, maybe other resamples
of the data), one file (docs/model-format.md, version 5).

Where the members agree a prediction is trustworthy; where they disagree it is not.  An
`Ensemble` behaves as a `Model` for every reader (its `rollout` is the members' mean, so
eval, simulate and the step-size checks use it unchanged) and adds the spread: the members'
standard deviation times ``spread_scale``, a per-dimension factor fitted on validation data
when the ensemble was trained, so that the bands mean +- z * spread cover what they claim.
"""
import numpy as np

from mpnode.base.errors import InputError, NumericalError

from . import file as model_file

#: z of the central 50% and 90% bands of a normal distribution: mean +- z * spread
BAND_Z = {50: 0.6744897501960817, 90: 1.6448536269514722}


class Ensemble:
    """K members (Models of one spec, normalisation and dtype) and the calibration of their spread.

    spread_scale : (dx,) the factor of the members' standard deviation (1: not calibrated)
    attrs : the file's extra attributes;  member_info : {member_seed, member_epoch, member_val_loss} (K,)
    """

    def __init__(self, members, spread_scale=None, attrs=None, member_info=None):
        members = list(members)
        if len(members) < 2:
            raise ValueError("an ensemble needs at least 2 members")
        first = members[0]
        for m in members[1:]:
            if m.spec != first.spec or m.dtype != first.dtype:
                raise ValueError("the members of an ensemble share one spec and dtype")
            if not (np.array_equal(m.x_mean, first.x_mean) and np.array_equal(m.x_std, first.x_std)
                    and np.array_equal(m.u_mean, first.u_mean) and np.array_equal(m.u_std, first.u_std)):
                raise ValueError("the members of an ensemble share one normalisation (one training split)")
        self.members = members
        dx = first.spec.state_dim
        self.spread_scale = np.ones(dx) if spread_scale is None else np.asarray(spread_scale, dtype=np.float64)
        if self.spread_scale.shape != (dx,) or not np.all(self.spread_scale > 0):
            raise ValueError(f"spread_scale must be {dx} numbers > 0")
        self.attrs = dict(attrs or {})
        self.member_info = dict(member_info or {})

    @classmethod
    def from_file(cls, held, path, model_class):
        """The ensemble of what `model_file.read_model` returned for an ensemble file, its members
        of ``model_class`` (mpnode.model.Model, which reads the files: this module never imports it)."""
        common = {k: held[k] for k in ("spec", "x_mean", "x_std", "u_mean", "u_std")}
        info = {k: v for k, v in held["ensemble"].items() if k != "spread_scale"}
        seeds = info.get("member_seed")
        seen = {k: v for k, v in held["attrs"].items()  # the training ranges, and the node attributes they hear
                if k in (model_file.SEEN_ATTR, "attr_names")}
        members = [model_class(theta, attrs={**seen, **({} if seeds is None else {"seed": int(seeds[i])})}, **common)
                   for i, theta in enumerate(held["theta"])]
        try:
            return cls(members, held["ensemble"]["spread_scale"], held["attrs"], info)
        except ValueError as e:
            raise InputError(path, "ensemble_size", str(e), "an ensemble of at least 2 members") from None

    def save(self, path, **attrs):
        """Write the ensemble file atomically (version 5)."""
        self.check_finite()
        first = self.members[0]
        params = {name: np.stack([m.params[name] for m in self.members]) for name in first.params}
        norm = {"x_mean": first.x_mean, "x_std": first.x_std, "u_mean": first.u_mean, "u_std": first.u_std}
        arrays = {"spread_scale": self.spread_scale, **{k: np.asarray(v) for k, v in self.member_info.items()}}
        model_file.write_model(path, first.spec, params, norm, {**self.attrs, **attrs}, ensemble=arrays)

    # ---- what a Model has --------------------------------------------------
    @property
    def size(self):
        return len(self.members)

    def __getattr__(self, name):
        # spec, kind, dtype, latent_dims, node attributes, normalisation and their helpers: the members share them
        if name in ("spec", "kind", "dtype", "latent_dims", "x_mean", "x_std", "u_mean", "u_std", "fitted",
                    "normalize_x", "denormalize_x", "normalize_u", "check_nodes", "attr_names",
                    "controls_of") and "members" in self.__dict__:
            return getattr(self.__dict__["members"][0], name)
        raise AttributeError(name)

    def _each(self, how):
        return Ensemble([how(m) for m in self.members], self.spread_scale, self.attrs, self.member_info)

    def copy(self, dtype=None):
        return self._each(lambda m: m.copy(dtype))

    def with_spec(self, **changes):
        return self._each(lambda m: m.with_spec(**changes))

    def check_finite(self):
        for m in self.members:
            m.check_finite()
        if not np.all(np.isfinite(self.spread_scale)):
            raise NumericalError("the ensemble's spread_scale contains non-finite values")

    def rollout(self, x0, graph, u=None, steps=None, backend="auto", times=None, node_attrs=None):
        """The members' mean rollout (Model.rollout's arguments and shape)."""
        return self.rollout_members(x0, graph, u, steps, backend, times, node_attrs).mean(axis=0).astype(self.dtype)

    def rollout_members(self, x0, graph, u=None, steps=None, backend="auto", times=None, node_attrs=None):
        """(K, ...) every member's rollout from the same start (Model.rollout's shape after K)."""
        return np.stack([m.rollout(x0, graph, u, steps, backend, times, node_attrs) for m in self.members])

    def predict(self, x0, graph, u=None, steps=None, backend="auto", times=None, node_attrs=None):
        """(mean, spread): the members' mean rollout and its calibrated spread, both in data units."""
        xs = self.rollout_members(x0, graph, u, steps, backend, times, node_attrs)
        return xs.mean(axis=0), self.spread(xs)

    def spread(self, member_predictions):
        """The calibrated spread of predictions (K, ..., dx): members' std (ddof 1) times spread_scale."""
        return np.std(np.asarray(member_predictions, dtype=np.float64), axis=0, ddof=1) * self.spread_scale

    def initial_state(self, observations, times=None):
        """Where the members' rollouts start: the mean of their estimates (Model.initial_state)."""
        return np.mean([m.initial_state(observations, times) for m in self.members], axis=0).astype(self.dtype)

    def summary(self):
        """A member's summary with the ensemble's size, spread scale and members' seeds, epochs, losses."""
        out = self.members[0].summary()
        out["parameters"] *= self.size
        out["attrs"] = {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in self.attrs.items()}
        out["ensemble"] = {"members": self.size, "spread_scale": self.spread_scale.tolist(),
                           **{k: np.asarray(v).tolist() for k, v in self.member_info.items()}}
        return out


def models_of(model):
    """The models whose rollouts a prediction of ``model`` runs: an Ensemble's members (it
    averages them), or the one Model itself."""
    return list(model.members) if isinstance(model, Ensemble) else [model]


def coverage(truth, mean, spread, band):
    """The fraction of the finite ``truth`` values inside the central ``band`` (50 or 90) percent
    band mean +- z * spread (NaN when none is finite)."""
    inside = np.abs(truth - mean) <= BAND_Z[band] * spread
    scored = np.isfinite(truth) & np.isfinite(mean)
    return float(inside[scored].mean()) if scored.any() else float("nan")


def fitted_scale(truth, mean, std, band=90):
    """(dx,) the factor of the members' std ``std`` that makes the central ``band`` band cover
    ``band`` percent of the finite ``truth`` values of each dimension (1 where nothing is scored
    or the members agree exactly)."""
    dx = truth.shape[-1]
    out = np.ones(dx)
    for d in range(dx):
        t, m, s = truth[..., d], mean[..., d], std[..., d]
        ok = np.isfinite(t) & np.isfinite(m) & (s > 0)
        if ok.sum() >= 10:
            out[d] = float(np.quantile(np.abs(t[ok] - m[ok]) / s[ok], band / 100)) / BAND_Z[band]
    return np.where(out > 0, out, 1.0)

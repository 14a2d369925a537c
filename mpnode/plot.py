"""Figures of a run: evaluation, simulation and training (the optional ``plot`` extra).

Three figures a person would put in a report, each from what the library already returns:
`plot_eval` (truth against prediction per state dimension for a few trajectories and nodes,
and the error over time with the predictable horizon marked: the MP-NODE paper's Fig. 2 in
spirit; for a network, also the network coloured by each node's error and its worst and median
node over time) from `mpnode.evaluation.evaluate.evaluate`'s EvalResult; `plot_simulation` (a few nodes per
state dimension) from any rollout; `plot_training` (losses, validation normalised MSE and
learning rate per epoch) from the training log.  They know no particular system: state dimensions are named by
the file's ``state_names`` attribute when it has one, x[0], x[1], ... otherwise, and time
is in the file's units (t = step * dt).

matplotlib is imported inside the functions only (``import mpnode.plot`` works without it),
and only through `matplotlib.figure.Figure`: no pyplot, no global backend switched under a
notebook's feet.  Each function returns the Figure and, given ``out``, writes it atomically.
`check_output` lets a command fail before any work when matplotlib is missing.
"""
import functools
import os
import warnings

import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.evaluation.metrics import normalised_sq_error

#: z of the central 90% band of a normal distribution (mpnode.model.ensemble.BAND_Z)
BAND_90 = 1.6448536269514722
INSTALL_HINT = "matplotlib installed: pip install 'mpnode[plot]' (from a checkout: pip install '.[plot]')"
#: 1200 x 800 pixels: legible at 100 % on a screen and in a report
FIGSIZE, DPI = (12, 8), 100
#: the evaluation of a network of at least NETWORK_NODES nodes gets a row more (1200 x 1200 pixels):
#: the network coloured by each node's error, the worst and the median node over time
NETWORK_NODES, NETWORK_FIGSIZE = 3, (12, 12)
#: networks up to this many nodes are laid out by Kamada-Kawai (seconds for 300), larger ones by springs
KAMADA_KAWAI_NODES = 300
STYLE = {"font.size": 11, "axes.titlesize": 12, "axes.labelsize": 11, "legend.fontsize": 10,
         "xtick.labelsize": 10, "ytick.labelsize": 10, "figure.titlesize": 13, "axes.grid": True,
         "grid.alpha": 0.3}


def check_output(path, flag="--plot"):
    """InputError unless a figure can be written to ``path``: matplotlib is installed and the
    extension names a format it writes.  Returns the format (e.g. "png").  Cheap: call it
    before any work, so a missing extra costs nothing."""
    try:
        import matplotlib  # noqa: F401
        from matplotlib.figure import Figure
    except ImportError:
        raise InputError(flag, path, "needs matplotlib (the plot extra), which is not installed",
                         INSTALL_HINT) from None
    fmt = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    supported = Figure().canvas.get_supported_filetypes()
    if fmt not in supported:
        common = [f".{k}" for k in ("pdf", "svg", "jpg") if k in supported]
        raise InputError(flag, path, f"has extension {'.' + fmt if fmt else '(none)'}, not a figure format",
                         f"a file name ending in .png (or another format matplotlib writes: {', '.join(common)}, "
                         "...)")
    return fmt


def save_figure(fig, out):
    """Write ``fig`` to ``out`` atomically, in the format its extension names; returns ``out``."""
    fmt = check_output(out, "out")
    with atomic_path(out) as tmp:
        if fmt == "png":
            _save_png(fig, tmp)
        else:
            fig.savefig(tmp, format=fmt, dpi=fig.dpi)
    return out


def _save_png(fig, path):
    """A 256-colour PNG: line plots use a handful of colours, so it looks the same at a third
    of the size (figures end up in reports and repositories).  Pillow comes with matplotlib."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi)
    buf.seek(0)
    with Image.open(buf) as image:
        image.convert("RGB").quantize(colors=256).save(path, format="PNG", optimize=True)


def _styled(draw):
    """Run a figure function under STYLE (matplotlib reads font sizes when artists are made)."""
    @functools.wraps(draw)
    def wrapper(*args, **kwargs):
        import matplotlib

        with matplotlib.rc_context(STYLE):
            return draw(*args, **kwargs)
    return wrapper


def _figure(figsize=FIGSIZE):
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=DPI, layout="constrained")


def _finish(fig, out):
    if out is not None:
        save_figure(fig, out)
    return fig


def time_label(dt):
    """The time axis' label: the file's own units, which it does not name."""
    return f"t (dt = {float(dt):g})"


def dimension_names(attrs, dx):
    """The ``state_names`` attribute when it names all dx dimensions, else x[0], x[1], ..."""
    names = (attrs or {}).get("state_names")
    names = [names] if isinstance(names, str) else names
    if isinstance(names, (list, tuple, np.ndarray)) and len(names) == dx and all(isinstance(n, str) for n in names):
        return [str(n) for n in names]
    return [f"x[{k}]" for k in range(dx)]


def _limits(truth, pred):
    """y-limits showing the truth whole and a prediction as far as twice the truth's range:
    a prediction that blows up leaves the panel instead of flattening the truth."""
    lo, hi = float(np.nanmin(truth)), float(np.nanmax(truth))
    r = max(hi - lo, 1e-12 * max(abs(lo), abs(hi), 1.0))
    finite = pred[np.isfinite(pred)]
    plo = max(float(finite.min()), lo - r) if finite.size else lo
    phi = min(float(finite.max()), hi + r) if finite.size else hi
    lo, hi = min(lo, plo), max(hi, phi)
    pad = 0.05 * (hi - lo) if hi > lo else 0.5
    return lo - pad, hi + pad


def _state_grid(fig, spec, x, dt, names, bs, ns, ds, truth=None, times=None, dots=None, spread=None):
    """Panels (state dimension x trajectory) of nodes ``ns``: x dashed over the truth when
    given, solid otherwise, and the observations ``dots`` (NaN: not observed) as dots; one colour
    per node; an ensemble's central 90% band x +- 1.645 ``spread`` shaded; time from ``times``
    (B, T+1) or every dt.  Returns the axes (rows, columns)."""
    axes = np.empty((len(ds), len(bs)), dtype=object)
    with np.errstate(invalid="ignore"):
        for c, b in enumerate(bs):
            t = np.arange(x.shape[1]) * float(dt) if times is None else times[b]
            for r, d in enumerate(ds):
                ax = fig.add_subplot(spec[r, c], sharex=axes[0, 0] if r or c else None)
                axes[r, c] = ax
                for i in ns:
                    if truth is not None:
                        ax.plot(t, truth[b, :, i, d], color=f"C{i % 10}", lw=1.8)
                    if dots is not None:
                        ax.plot(t, dots[b, :, i, d], ls="none", marker="o", ms=3.5, color=f"C{i % 10}", alpha=0.7)
                    ax.plot(t, np.where(np.isfinite(x[b, :, i, d]), x[b, :, i, d], np.nan), color=f"C{i % 10}",
                            lw=1.8, ls="--" if truth is not None else "-")
                    if spread is not None:
                        half = BAND_90 * spread[b, :, i, d]
                        ax.fill_between(t, x[b, :, i, d] - half, x[b, :, i, d] + half, color=f"C{i % 10}",
                                        alpha=0.18, lw=0)
                reference = truth if truth is not None else dots
                if reference is not None and np.isfinite(reference[b][:, list(ns), d]).any():
                    ax.set_ylim(*_limits(reference[b][:, list(ns), d], x[b][:, list(ns), d]))
                if r == 0:
                    ax.set_title(f"trajectory {b}")
                if c == 0:
                    ax.set_ylabel(names[d])
                if r == len(ds) - 1:
                    ax.set_xlabel(time_label(dt))
                else:
                    ax.tick_params(labelbottom=False)
    return axes


def _node_legend(ax, ns, with_truth, with_dots=False, with_band=False):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color=f"C{i % 10}", lw=2, label=f"node {i}") for i in ns]
    if with_band:
        handles.append(Patch(color="0.5", alpha=0.3, label="ensemble's 90% band"))
    if with_truth:
        handles += [Line2D([], [], color="0.25", lw=1.8, label="truth"),
                    Line2D([], [], color="0.25", lw=1.8, ls="--", label="prediction")]
    if with_dots:
        handles += [Line2D([], [], color="0.25", ls="none", marker="o", ms=4, label="observations")]
    ax.legend(handles=handles, loc="best", ncol=2 if len(handles) > 4 else 1, framealpha=0.85)


def _selection(shape, trajectories, nodes, dims):
    """The first few trajectories, nodes and state dimensions (ranges)."""
    b, _, n, dx = shape
    return range(min(b, trajectories)), range(min(n, nodes)), range(min(dx, dims))


def _shown(names, ds, dx):
    """' (x[0], x[1] of 13 dimensions shown)' when not every dimension fits."""
    return "" if len(ds) == dx else f" ({', '.join(names[d] for d in ds)} of {dx} state dimensions shown)"


@_styled
def plot_eval(truth, result, out=None, *, trajectories=2, nodes=3, dims=4, title=None):
    """Truth against prediction, and the error over time with the predictable horizon.

    truth : the Trajectories evaluated;  result : its `evaluate` EvalResult.  Left: one panel
    per state dimension (rows, the first ``dims``) and trajectory (columns, the first
    ``trajectories``), the first ``nodes`` nodes, truth solid and prediction dashed.  Right:
    the normalised MSE per step (mean over trajectories, as `mpnode eval` reports it; the
    median and 10-90 % of the trajectories' own), the horizon thresholds and where the median
    trajectory first exceeds each, the first blow-up, and the drift of a conserved quantity when
    the evaluation measured one.  Of a network of NETWORK_NODES nodes or more, a row below
    (mpnode.evaluation.nodes: the graph most trajectories run on): the network laid out
    (`network_layout`), each node coloured by its error on the watched dimensions, and the worst
    and the median node's watched dimension over its first three trajectories, truth beside
    prediction.  Returns the Figure; writes ``out``.
    """
    x = np.asarray(truth.x, dtype=np.float64)
    pred = np.asarray(result.predictions, dtype=np.float64)[..., :x.shape[3]]  # a model's latent dimensions: no truth
    bs, ns, ds = _selection(x.shape, trajectories, nodes, dims)
    names = dimension_names(truth.attrs, x.shape[3])
    as_lines = truth.complete and truth.truth is None  # else: the observations as dots, the truth (if any) as lines
    clean = x if as_lines else (None if truth.truth is None else np.asarray(truth.truth, dtype=np.float64))
    times = None if truth.regular else truth.times()
    nodes = getattr(result, "nodes", None)
    network = nodes is not None and x.shape[2] >= NETWORK_NODES
    fig = _figure(NETWORK_FIGSIZE if network else FIGSIZE)
    outer = fig.add_gridspec(2 if network else 1, 1, height_ratios=[1.8, 1.2] if network else [1])
    spec = outer[0].subgridspec(len(ds), len(bs) + 1, width_ratios=[1] * len(bs) + [1.3])
    spread = getattr(result, "spread", None)
    axes = _state_grid(fig, spec, pred, truth.dt, names, bs, ns, ds, truth=clean, times=times,
                       dots=None if as_lines else x, spread=spread)
    _node_legend(axes[0, 0], ns, with_truth=clean is not None, with_dots=not as_lines, with_band=spread is not None)
    scored = np.array(x if clean is None else clean)
    scored[..., list(result.hidden_dims or [])] = np.nan  # a state never measured in training has no units to compare
    for d in result.hidden_dims or []:
        if d in ds:
            axes[list(ds).index(d), 0].set_ylabel(f"{names[d]}\n(never measured: the model's hidden state)")
    _error_panel(fig.add_subplot(spec[:, -1]), scored, pred, truth.dt, result, times)
    if network:
        _network_row(fig, outer[1], truth, x, clean, pred, nodes, names, times)
    head = title or f"{truth.system}: prediction against {'truth' if clean is not None else 'observations'}"
    first = max(1, result.warmup)
    fig.suptitle(f"{head}: normalised MSE {result.nmse:.3g} (mean over steps {first}..{x.shape[1] - 1})"
                 f"{_shown(names, ds, x.shape[3])}")
    return _finish(fig, out)


def _network_row(fig, spec, truth, observed, clean, pred, nodes, names, times):
    """The network coloured by each node's error (mpnode.evaluation.nodes.NodeErrors), beside the worst
    and the median node's watched dimension over the first trajectories on that network (``observed``:
    the file's x as float64)."""
    row = spec.subgridspec(1, 3, width_ratios=[1.5, 1, 1])
    graph = truth.graphs[nodes.graph]
    dims = [d for d in nodes.dims if d < len(names)]  # a model's latent dimensions have no truth to draw
    what = "the whole state" if len(dims) == len(names) else ", ".join(names[d] for d in dims)
    _network_panel(fig, fig.add_subplot(row[0, 0]), graph, nodes, what)
    rows = nodes.trajectories[:3]
    first = None
    for k, (label, i) in enumerate((("worst", (nodes.worst(1) or [None])[0]), ("median", nodes.median()))):
        ax = fig.add_subplot(row[0, k + 1], sharex=first)
        first = first or ax
        if i is None:
            ax.set_axis_off()
            continue
        d = max(dims, key=lambda d: np.nan_to_num(nodes.nmse[i, d], nan=-1.0))  # its worst watched one
        for c, b in enumerate(rows):
            t = np.arange(observed.shape[1]) * float(truth.dt) if times is None else times[b]
            reference = observed[b, :, i, d] if clean is None else clean[b, :, i, d]
            ax.plot(t, reference, color=f"C{c}", lw=1.8, ls="-" if clean is not None else "none",
                    marker=None if clean is not None else "o", ms=3)
            with np.errstate(invalid="ignore"):
                ax.plot(t, np.where(np.isfinite(pred[b, :, i, d]), pred[b, :, i, d], np.nan), color=f"C{c}",
                        lw=1.8, ls="--")
        shown = (observed if clean is None else clean)[rows][:, :, i, d]
        if np.isfinite(shown).any():
            ax.set_ylim(*_limits(shown, pred[rows][:, :, i, d]))
        ax.set_title(f"{label}: {nodes.name(i)}, nMSE {nodes.error[i]:.3g}")
        ax.set_ylabel(names[d])
        ax.set_xlabel(time_label(truth.dt))
    _trajectory_legend(first, rows, clean is not None)


def _trajectory_legend(ax, rows, with_truth):
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=f"C{c}", lw=2, label=f"trajectory {b}") for c, b in enumerate(rows)]
    handles += [Line2D([], [], color="0.25", lw=1.8, label="truth" if with_truth else "observations",
                       ls="-" if with_truth else "none", marker=None if with_truth else "o"),
                Line2D([], [], color="0.25", lw=1.8, ls="--", label="prediction")]
    ax.legend(handles=handles, loc="best", fontsize=9, framealpha=0.85)


def network_layout(graph, seed=0):
    """(N, 2) node positions of ``graph`` (its edges undirected): Kamada-Kawai up to KAMADA_KAWAI_NODES
    nodes, springs (seeded) beyond; the same graph always gets the same drawing."""
    import networkx as nx

    g = nx.Graph()
    g.add_nodes_from(range(graph.n_nodes))
    g.add_edges_from((int(i), int(j)) for i, j in graph.edges() if i != j)
    pos = (nx.kamada_kawai_layout(g) if graph.n_nodes <= KAMADA_KAWAI_NODES and nx.is_connected(g)
           else nx.spring_layout(g, seed=seed))
    return np.array([pos[i] for i in range(graph.n_nodes)])


def _network_panel(fig, ax, graph, nodes, what):
    """The graph's nodes coloured by their error (a log scale when it spans more than a decade), the
    worst three and the median named; a node whose prediction became non-finite black, one never
    scored grey."""
    from matplotlib import colormaps, colors, ticker
    from matplotlib.collections import LineCollection

    pos = network_layout(graph)
    pairs = graph.edges()
    ax.add_collection(LineCollection(pos[pairs[pairs[:, 0] < pairs[:, 1]]], colors="0.6", linewidths=0.8, zorder=1))
    error = nodes.error
    finite = error[np.isfinite(error) & (error > 0)]
    lo, hi = (finite.min(), finite.max()) if finite.size else (1e-3, 1.0)
    norm = colors.LogNorm(lo, max(hi, lo * 1.01)) if hi > 10 * lo else colors.Normalize(0, max(hi, 1e-12))
    shown = np.where(error > 0, error, lo)  # an exact node on a log scale: its lowest colour
    shown[np.isnan(error)] = np.nan
    size = float(np.clip(4000 / graph.n_nodes, 12, 160))
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=shown, s=size, norm=norm, edgecolors="0.2", linewidths=0.5, zorder=2,
                    cmap=colormaps["YlOrRd"].with_extremes(over="k", bad="0.85"), plotnonfinite=True)
    bar = fig.colorbar(sc, ax=ax, location="bottom", shrink=0.8, extend="max" if np.isinf(error).any() else "neither",
                       label=f"nMSE of {what}")
    if isinstance(norm, colors.LogNorm):  # plain numbers at 1, 2, 5 of each decade
        plain = ticker.FuncFormatter(lambda v, _: f"{v:g}")
        bar.ax.xaxis.set_major_formatter(plain)
        bar.ax.xaxis.set_minor_locator(ticker.LogLocator(subs=(2, 5)))
        bar.ax.xaxis.set_minor_formatter(plain)
    median = nodes.median()
    for i in nodes.worst(3) + ([median] if median is not None and median not in nodes.worst(3) else []):
        ax.annotate(nodes.name(i) + (" (median)" if i == median else ""), pos[i], xytext=(4, 4),
                    textcoords="offset points", fontsize=9, zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_axis_off()
    k = len(nodes.trajectories)
    ax.set_title(f"graph {nodes.graph}, {k} trajector{'y' if k == 1 else 'ies'}: error per node")


def _error_panel(ax, x, pred, dt, result, times=None):
    """Normalised MSE over time (log scale), horizon thresholds and crossings, first blow-up.
    With each trajectory's own times, a step is drawn at its mean time."""
    t = np.arange(x.shape[1]) * float(dt) if times is None else np.nanmean(times, axis=0)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a step with nothing observed is a gap
        own = np.nanmean(normalised_sq_error(pred, x), axis=(2, 3))[:, 1:]  # (B, T): each trajectory's
        mean = np.asarray(result.nmse_per_step, dtype=np.float64)[1:]
        if own.shape[0] >= 3:
            lo, med, hi = np.nanpercentile(own, [10, 50, 90], axis=0)
            ax.fill_between(t[1:], _loggable(lo), _loggable(hi), color="0.5", alpha=0.25,
                            label="10-90 % of trajectories")
            ax.plot(t[1:], _loggable(med), color="0.3", lw=1.2, ls=":", label="median trajectory")
    ax.plot(t[1:], _loggable(mean), color="k", lw=2.2, label="mean (as mpnode eval reports)")
    for k, (thr, h) in enumerate((result.horizons or {}).items()):
        color = ("C4", "C3", "C5", "C6")[k % 4]
        ax.axhline(float(thr), color=color, lw=1, ls="--")
        when = f"beyond t = {t[-1]:.3g}" if h["median_time"] is None else f"t = {h['median_time']:.3g}"
        if h["median_time"] is not None:
            ax.axvline(h["median_time"], color=color, lw=1.5)
        ax.plot([], [], color=color, lw=1.5, label=f"horizon, nMSE > {thr}: {when} (median)")
    if result.first_bad_step is not None:
        ax.axvline(result.first_bad_step * float(dt), color="k", lw=2, ls="-.",
                   label=f"first blow-up: t = {result.first_bad_step * float(dt):.3g}")
    drift = [] if result.invariant_drift is None else np.asarray(result.invariant_drift[0])[1:]
    if len(drift):  # a conserved quantity's relative drift along the predictions, on the same log axis
        ax.plot(t[1:], _loggable(drift), color="C2", lw=1.5, label="drift of the conserved quantity, |I(t) - I(0)| / |I(0)|")
    _log_axis(ax, np.concatenate([mean, own.ravel(), drift]))
    ax.set_xlim(0, t[-1])
    ax.set_xlabel(time_label(dt))
    ax.set_ylabel("normalised MSE (1 = predicting the mean)")
    ax.set_title("error over time")
    ax.legend(loc="lower right", fontsize=9, framealpha=0.85)


def _loggable(v):
    """Values for a log axis: non-finite (blown up) and non-positive entries are gaps."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(np.isfinite(v) & (v > 0), v, np.nan)


@_styled
def plot_simulation(x, dt, out=None, *, state_names=None, trajectories=2, nodes=5, dims=4, title=None, spread=None):
    """Simulated trajectories: one panel per state dimension (rows) and trajectory (columns),
    one line per node (the first ``nodes``).  x : (B, T+1, N, dx), e.g. a SimulationResult's
    predictions;  state_names : one per dimension (default x[0], x[1], ...);  spread : an
    ensemble's (like x), drawn as the central 90% band.  Returns the Figure; writes ``out``."""
    x = np.asarray(x, dtype=np.float64)
    bs, ns, ds = _selection(x.shape, trajectories, nodes, dims)
    names = dimension_names({"state_names": state_names}, x.shape[3])
    fig = _figure()
    axes = _state_grid(fig, fig.add_gridspec(len(ds), len(bs)), x, dt, names, bs, ns, ds, spread=spread)
    _node_legend(axes[0, 0], ns, with_truth=False, with_band=spread is not None)
    more = f", the first {len(ns)} of {x.shape[2]} nodes" if len(ns) < x.shape[2] else ""
    fig.suptitle(f"{title or 'simulated trajectories'}{more}{_shown(names, ds, x.shape[3])}")
    return _finish(fig, out)


@_styled
def plot_training(log, out=None, *, loss=None, title=None):
    """Training and validation loss per epoch (log scale), the validation normalised MSE when
    the log has it, and the learning rate.

    log : the records of a training log (`mpnode.training.log.read_log`) or its path;
    loss : the loss' name for the axis label ("huber", "mse").  Marks the best validation
    epoch and, with a horizon curriculum, where each window length starts.  Returns the
    Figure; writes ``out``.
    """
    from mpnode.training.log import read_log

    records = read_log(log) if isinstance(log, (str, os.PathLike)) else list(log)
    if not records:
        raise InputError(str(log), "log", "has no epochs", "the log of a training run that started")
    nmse = _series(records, "val_nmse")
    fig = _figure()
    axes = fig.subplots(3 if np.isfinite(nmse).any() else 2, 1, sharex=True,
                        height_ratios=[3, 1.5, 1] if np.isfinite(nmse).any() else [3, 1])
    epochs = np.array([r["epoch"] for r in records])
    _loss_panel(axes[0], records, epochs, loss)
    if len(axes) == 3:
        axes[1].plot(epochs, _loggable(nmse), color="C4", lw=1.6)
        _log_axis(axes[1], nmse)
        axes[1].set_ylabel("validation\nnormalised MSE")
    lr = _series(records, "lr")
    axes[-1].step(epochs, lr, where="post", color="C2", lw=1.6)
    if np.nanmax(lr) > np.nanmin(lr):
        _log_axis(axes[-1], lr)
    else:  # a constant rate: a log axis would only show its tick labels crowding
        axes[-1].set_ylim(0, 1.5 * lr[0] if lr[0] > 0 else 1)
    axes[-1].set_ylabel("learning rate")
    axes[-1].set_xlabel("epoch")
    fig.suptitle(f"{title or 'training'}: {epochs[-1]} epochs in {_duration(records[-1].get('elapsed') or 0.0)}")
    return _finish(fig, out)


def _series(records, key):
    """records[k][key] as float64, NaN where missing (an old log, epoch 0's training loss)."""
    return np.array([np.nan if r.get(key) is None else r[key] for r in records], dtype=np.float64)


def _loss_panel(ax, records, epochs, loss):
    """Training and validation loss, the best validation epoch, the curriculum stages."""
    for key, label, color in (("train_loss", "training", "C0"), ("val_loss", "validation", "C1")):
        ax.plot(epochs, _loggable(_series(records, key)), color=color, lw=1.6, label=f"{label} loss")
    val = _loggable(_series(records, "val_loss"))
    if np.isfinite(val).any():
        best = int(np.nanargmin(val))
        ax.plot(epochs[best], val[best], "*", color="C3", ms=14,
                label=f"best validation: {val[best]:.4g} at epoch {epochs[best]}")
    _windows(ax, records)
    _log_axis(ax, np.concatenate([_series(records, "train_loss"), _series(records, "val_loss")]))
    ax.set_ylabel(f"{loss + ' ' if loss else ''}loss per node\n(normalised states)")
    ax.legend(loc="upper right", framealpha=0.85)


def _windows(ax, records):
    """Dashed lines where a horizon curriculum starts a stage (none without a curriculum)."""
    stages = [r.get("stage") for r in records]
    last_stage = max((st for st in stages if st is not None), default=0)
    if last_stage == 0:
        return
    previous = None
    for r, stage in zip(records, stages):
        if stage is not None and stage != previous:
            w = r.get("window")
            label = f"full horizon ({w} steps)" if stage == last_stage else f"window {w} steps"
            ax.axvline(r["epoch"], color="0.4", lw=1, ls="--")
            ax.text(r["epoch"], 0.98, " " + label, rotation=90, va="top", ha="left", fontsize=9, color="0.3",
                    transform=ax.get_xaxis_transform())
        previous = stage


def _log_axis(ax, values):
    """A log y-axis labelled in plain numbers (0.5, 2, 50) when the data span under two decades."""
    from matplotlib import ticker

    v = _loggable(values)
    if not np.isfinite(v).any():
        return
    ax.set_yscale("log")
    ratio = np.nanmax(v) / np.nanmin(v)
    if ratio < 100:  # few decades: label more than the powers of ten, as plain numbers
        plain = ticker.FuncFormatter(lambda y, _: f"{y:g}")
        subs = np.arange(2, 10) if ratio < 3 else (2, 3, 5) if ratio < 10 else (2, 5)
        ax.yaxis.set_major_formatter(plain)
        ax.yaxis.set_minor_locator(ticker.LogLocator(subs=subs))
        ax.yaxis.set_minor_formatter(plain)


def _duration(seconds):
    return f"{seconds:.3g} s" if seconds < 120 else f"{seconds / 60:.3g} min" if seconds < 7200 \
        else f"{seconds / 3600:.3g} h"

"""Paper Fig. 6: gene expression of every node drawn as a square image, truth against prediction.

The gene graphs (BA, ER, WS) have no geometry of their own; the paper shows the 16 or 64 nodes
as a 4 x 4 or 8 x 8 grid, node i at row i // side, column i % side.  A node count that is not
a square is padded with blank cells, so quick runs on other sizes still draw.
"""
import math

import numpy as np
from common import figure_block, pyplot

from mpnode.evaluation.metrics import nmse

FIG6 = ("Figure 6: Performance of the MP-NODE on the gene dynamics model: finetuning to larger grids, as "
        "well as zero-shot generalization to unseen graph structures.")
FIG6A = FIG6 + " (a) MP-NODE predictions on a 8 × 8 grid of gene regulatory dynamics finetuned over a model " \
               "trained on 4× 4 grid data."
FIG6B = FIG6 + " (b) MP-NODE predictions on a 4 × 4 grid of gene regulatory dynamics using the ER network, a " \
               "topology unseen during training."
#: columns of the figure: evenly spaced saved steps, the first and last included
TIMES = 5


def grid_image(values):
    """Node values (N,) as a (side, side) image, side = ceil(sqrt(N)); cells past N are NaN (blank)."""
    values = np.asarray(values, dtype=float)
    side = math.isqrt(len(values) - 1) + 1 if len(values) else 0
    img = np.full(side * side, np.nan)
    img[:len(values)] = values
    return img.reshape(side, side)


def shown_steps(horizon, count=TIMES):
    """``count`` distinct saved steps from 0 to ``horizon``, evenly spaced."""
    return sorted({int(round(k)) for k in np.linspace(0, horizon, count)})


def gene_grid(ctx, model, traj, name, caption, what, index=0):
    """Draw trajectory ``index`` of ``traj`` (truth) and ``model``'s rollout from its initial state
    (prediction) as node grids at a few times; return (markdown block, numbers).

    what: the setting, for the sentence under the figure (e.g. "gene64 fine-tuned from gene16").
    """
    plt = pyplot()
    graph = traj.graphs[int(traj.graph_index[index])]
    truth = np.asarray(traj.x[index], dtype=np.float64)  # (T+1, N, dx)
    pred = np.asarray(model.copy(np.float64).rollout(truth[0], graph, steps=traj.horizon), dtype=np.float64)
    steps = shown_steps(traj.horizon)
    lo, hi = float(truth[..., 0].min()), float(truth[..., 0].max())  # the truth's scale: predictions beyond it clip
    hi = max(hi, lo + 1e-12)
    fig, axes = plt.subplots(2, len(steps), figsize=(1.9 * len(steps) + 0.8, 3.6), squeeze=False)
    for col, t in enumerate(steps):
        for row, (label, x) in enumerate((("truth", truth), ("prediction", pred))):
            ax = axes[row, col]
            im = ax.imshow(grid_image(x[t, :, 0]), vmin=lo, vmax=hi, cmap="viridis")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"t = {t * traj.dt:.2g}", fontsize=9)
            if col == 0:
                ax.set_ylabel(label)
    side = grid_image(truth[0, :, 0]).shape[0]
    fig.suptitle(f"{what}: the {traj.n_nodes} nodes on a {side} x {side} grid (trajectory {index})", fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="expression level")
    link = ctx.figure(fig, name)
    spread = np.asarray(traj.x, dtype=np.float64)
    per_step = [nmse(pred[t:t + 1], truth[t:t + 1], spread) for t in steps]
    numbers = {"trajectory": index, "steps": steps, "nmse": nmse(pred[1:], truth[1:], spread),
               "nmse_at_steps": per_step, "truth_range": [float(truth[..., 0].min()), float(truth[..., 0].max())]}
    worst = int(np.argmax(per_step))
    ours = (f"{what}, trajectory {index}: nMSE {numbers['nmse']:.3g} over steps 1..{traj.horizon} (the test file's "
            f"variance as the unit); of the times shown, the worst is t = {steps[worst] * traj.dt:.2g} "
            f"(nMSE {per_step[worst]:.3g}), while the true expression spans {numbers['truth_range'][0]:.3g}.."
            f"{numbers['truth_range'][1]:.3g}.")
    return figure_block(link, caption, ours), numbers

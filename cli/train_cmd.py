"""`mpnode train DATA... -o MODEL` and `mpnode finetune MODEL DATA... -o NEW`: learn an MP-NODE."""
import os
import sys
import tempfile

import click

from mpnode.errors import InputError, NumericalError

from .main import main

#: `mpnode train SCENE` (a scene instead of files): trajectories generated and the default time budget
SCENE_TRAJECTORIES = 300
SCENE_EVAL_TRAJECTORIES = 100
SCENE_TIME_LIMIT = 3.0  # minutes


def training_options(f):
    """The optimisation flags shared by train and finetune (defaults: the seed code's MP-NODE run)."""
    options = [
        click.option("--epochs", type=click.IntRange(min=0), default=4000, show_default=True,
                     help="Passes over the training trajectories."),
        click.option("--time-limit", type=click.FloatRange(min=0, min_open=True),
                     help="Stop cleanly after this many minutes (best model and checkpoint saved)."),
        click.option("--batch-size", type=click.IntRange(min=1), default=128, show_default=True,
                     help="Trajectories per batch (each batch from one file: one block-diagonal graph)."),
        click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True,
                     help="Adam learning rate."),
        click.option("--beta1", type=click.FloatRange(0, 1, max_open=True), default=0.9, show_default=True),
        click.option("--beta2", type=click.FloatRange(0, 1, max_open=True), default=0.999, show_default=True),
        click.option("--eps", type=click.FloatRange(min=0), default=1e-8, show_default=True, help="Adam epsilon."),
        click.option("--clip", type=click.FloatRange(min=0), default=500.0, show_default=True,
                     help="Gradient clip norm, applied to each parameter array separately (0: no clipping)."),
        click.option("--clip-global", is_flag=True, help="Clip by one norm over all parameters instead."),
        click.option("--val-split", type=click.FloatRange(0, 1, max_open=True), default=0.3, show_default=True,
                     help="Fraction of every file's trajectories held out for validation (random, seeded)."),
        click.option("--noise", type=click.FloatRange(min=0), default=1e-4, show_default=True,
                     help="Std of the Gaussian noise added once to the normalised training states."),
        click.option("--loss", type=click.Choice(["huber", "mse"]), default="huber", show_default=True),
        click.option("--patience", type=click.IntRange(min=1), default=500, show_default=True,
                     help="Epochs without a new best validation loss before the learning rate is cut."),
        click.option("--lr-decay", type=click.FloatRange(0, 1, min_open=True), default=0.5, show_default=True,
                     help="Factor applied to the learning rate at each cut."),
        click.option("--min-lr", type=click.FloatRange(min=0), default=1e-6, show_default=True,
                     help="No cut once the learning rate is at or below this."),
        click.option("--max-bad-steps", type=click.IntRange(min=1), default=5, show_default=True,
                     help="Stop after this many non-finite steps in a row."),
        click.option("--seed", type=int, default=0, show_default=True,
                     help="Seed of the initial weights, the split, the noise and the shuffles."),
        click.option("--substeps", type=click.IntRange(min=1), help="RK4 steps per dt (train default 1; "
                     "finetune default: the model's)."),
        click.option("--horizon-curriculum", "curriculum", callback=_parse_curriculum, metavar="W1,W2,...,full",
                     help="Train first on windows of W1 steps, then W2, ..., then the full horizon (e.g. 5,10,full; "
                          "'full' is implied at the end).  Each trajectory is cut into consecutive windows, each "
                          "starting from its true state; validation stays on the full horizon."),
        click.option("--curriculum-epochs", type=click.IntRange(min=1), default=100, show_default=True,
                     help="Epochs per window length of --horizon-curriculum (the full horizon gets the rest)."),
        click.option("--resume", is_flag=True,
                     help="Continue the run whose checkpoint (OUTPUT.state) is beside -o; its settings are kept "
                          "except --epochs and --time-limit."),
        click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
                     help="Model file to write (the best model so far, saved atomically on every improvement)."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def _parse_curriculum(ctx, param, value):
    """'5,10,full' -> (5, 10): increasing window lengths in steps; 'full' only last (and implied)."""
    if value is None:
        return ()
    items = [v.strip().lower() for v in value.split(",") if v.strip()]
    if items and items[-1] == "full":
        items = items[:-1]
    windows = []
    for v in items:
        try:
            w = int(v)
        except ValueError:
            raise click.BadParameter(f"{v!r} is not a window length (an integer >= 1, or 'full' at the end)")
        if w < 1 or (windows and w <= windows[-1]):
            raise click.BadParameter(f"window lengths must be increasing integers >= 1, got {value!r}")
        windows.append(w)
    return tuple(windows)


def _config(o, norm):
    from mpnode.train import TrainConfig

    return TrainConfig(epochs=o["epochs"], batch_size=o["batch_size"], lr=o["lr"], beta1=o["beta1"],
                       beta2=o["beta2"], eps=o["eps"], clip=o["clip"],
                       clip_mode="global" if o["clip_global"] else "per-array", val_split=o["val_split"],
                       noise=o["noise"], loss=o["loss"], patience=o["patience"], lr_decay=o["lr_decay"],
                       min_lr=o["min_lr"], seed=o["seed"], norm=norm, max_bad_steps=o["max_bad_steps"],
                       curriculum=o["curriculum"], curriculum_epochs=o["curriculum_epochs"],
                       time_limit=None if o["time_limit"] is None else o["time_limit"] * 60.0).check()


def _check_output(output):
    folder = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(folder):
        raise InputError("--output", output, f"folder {folder} does not exist", "a path in an existing folder")


def _read_all(paths):
    from mpnode.data import read_trajectories

    return [read_trajectories(p) for p in paths]


def _fmt(v):
    return "-" if v is None else f"{v:.4g}"


def run_training(model, datasets, sources, config, output, resume, attrs):
    """Train with a progress bar on stderr; print the outcome; exit 3/130 on divergence/interrupt."""
    from mpnode.train import fit, log_path

    state = {"bar": None}

    def show(record):
        if record is None:
            return ""
        window = f"  window {record['window']}" if record.get("window") is not None else ""
        return (f"epoch {record['epoch']}  train {_fmt(record['train_loss'])}  val {_fmt(record['val_loss'])}  "
                f"best {_fmt(record['best_val_loss'])}  lr {record['lr']:.2g}{window}")

    def progress(record):
        bar = state["bar"]
        bar.update(max(0, record["epoch"] - bar.pos), record)

    def notify(msg):
        click.echo(("\n" if state["bar"] is not None else "") + msg, err=True)

    with click.progressbar(length=max(config.epochs, 1), label="training", file=sys.stderr, item_show_func=show,
                           show_eta=True) as bar:
        state["bar"] = bar
        result = fit(model, datasets, config, output, sources=sources, resume=resume, progress=progress,
                     notify=notify, model_attrs=attrs)
    click.echo(f"{result.status}: {result.message}")
    click.echo(f"best validation loss {result.best_val_loss:.6g} at epoch {result.best_epoch} of {result.epoch}; "
               f"{result.seconds:.1f} s; learning rate now {result.lr:g}")
    click.echo(f"wrote {output} (best model), {log_path(output)} (log), {output}.state (checkpoint for --resume)")
    if result.status == "diverged":
        raise NumericalError(result.message)
    if result.status == "interrupted":
        click.echo("interrupted: continue with the same command plus --resume", err=True)
        sys.exit(130)
    return result


def validation_report(result, datasets, sources):
    """Normalised MSE of the best model on each file's validation split (one line per file)."""
    from mpnode.evaluate import evaluate, subset

    lines = []
    for traj, src, (_, val) in zip(datasets, sources, result.split):
        if len(val):
            r = evaluate(result.model, subset(traj, val), source=src)
            lines.append(f"validation normalised MSE on {src} ({len(val)} trajectories): mean over steps "
                         f"{r.nmse:.4g}, last step {r.nmse_last:.4g}")
    return "\n".join(lines)


@main.command("train")
@click.argument("data", nargs=-1, required=True)
@click.option("--message-dim", type=click.IntRange(min=0), default=3, show_default=True, help="Message size dm.")
@click.option("--hidden", type=click.IntRange(min=1), default=32, show_default=True, help="Hidden width H.")
@click.option("--zero-messages", is_flag=True, help="Clamp messages to 0 (the paper's ablation).")
@click.option("--self-messages", is_flag=True,
              help="Every node also hears its own message (the seed code's 'full' graph for Lorenz).")
@click.option("--dtype", type=click.Choice(["float32", "float64"]), default="float32", show_default=True)
@click.option("--trajectories", type=click.IntRange(min=2), default=SCENE_TRAJECTORIES, show_default=True,
              help="Only when DATA is a scene: trajectories to generate.")
@training_options
def train_cmd(data, message_dim, hidden, zero_messages, self_messages, dtype, trajectories, **o):
    """Learn an MP-NODE from trajectory files DATA... (same dx, du and dt; graphs and N may differ).

    DATA may instead be one scene (a built-in name such as coupled_pendulum, or a
    .toml file): its data are generated beside the model (OUTPUT.data.h5, --trajectories
    of them), the model is trained (default time limit 3 minutes) and evaluated at the
    end on fresh trajectories of the scene (another seed).

    Normalisation (z-score per state dimension) is fitted on the training split only
    and stored in the model.  Beside OUTPUT: OUTPUT.log.jsonl (one JSON line per epoch:
    losses, mean and max gradient norm, learning rate, window length and curriculum
    stage; each line written whole by one write, so a killed run leaves a readable log)
    and OUTPUT.state (checkpoint for --resume; also after a kill -9, from the last
    checkpoint).

    Chaotic systems: --horizon-curriculum 5,10,full trains on short windows first.

    Exit status: 0 trained; 2 bad input; 3 training diverged (the best finite model is
    kept); 130 interrupted (continue with --resume).
    """
    import numpy as np

    from mpnode.model import Model

    output = o["output"]
    _check_output(output)
    scene = None
    if len(data) == 1 and not os.path.exists(data[0]):
        from mpnode.data_gen import BUILTIN

        if data[0] in BUILTIN or data[0].endswith(".toml"):
            scene = data[0]
        else:
            raise InputError(data[0], "file", "does not exist and is not a built-in scene",
                             "trajectory files, or one scene name (see `mpnode scenes`)")
    if scene is not None:
        path = output + ".data.h5"
        if not (o["resume"] and os.path.exists(path)):
            _generate(scene, path, trajectories, seed=o["seed"])
        data = (path,)
        if o["time_limit"] is None:
            o["time_limit"] = SCENE_TIME_LIMIT
    datasets = _read_all(data)
    config = _config(o, "fit")
    model = None
    if not o["resume"]:
        t0 = datasets[0]
        model = Model.create(t0.state_dim, t0.control_dim, message_dim, hidden, t0.dt, o["substeps"] or 1,
                             zero_messages, self_messages, seed=o["seed"], dtype=np.dtype(dtype))
    attrs = {"trained_on": ";".join(os.path.abspath(p) for p in data), "system": datasets[0].system}
    result = run_training(model, datasets, list(data), config, output, o["resume"], attrs)
    click.echo(validation_report(result, datasets, list(data)))
    if scene is not None:
        from .eval_cmd import format_report, run_eval

        with tempfile.TemporaryDirectory() as tmp:
            test = os.path.join(tmp, "test.h5")
            _generate(scene, test, SCENE_EVAL_TRAJECTORIES, seed=o["seed"] + 1)
            traj = _read_all([test])[0]
            _, report = run_eval(result.model, traj, f"{SCENE_EVAL_TRAJECTORIES} fresh {scene} trajectories "
                                 f"(seed {o['seed'] + 1})")
        click.echo(format_report(report, output))


def _generate(scene, path, trajectories, seed):
    from dataclasses import replace

    from mpnode.data import write_trajectories
    from mpnode.data_gen import generate, load_scene

    s = replace(load_scene(scene), trajectories=trajectories, seed=seed)
    with click.progressbar(length=s.trajectories, label=f"generating {s.name}", file=sys.stderr) as bar:
        traj = generate(s, workers=2, progress=bar.update)
    write_trajectories(path, traj)
    click.echo(f"generated {path}: {s.name}, B={s.trajectories}, T={s.horizon}, seed {seed}")


@main.command("finetune")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("data", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--refit-norm", is_flag=True,
              help="Fit the normalisation on the new training split instead of keeping the model's.")
@training_options
def finetune_cmd(model_file, data, refit_norm, **o):
    """Continue training MODEL on DATA... and write the result to OUTPUT.

    Starts from exactly MODEL's weights (its dimensions, dt, message settings and, by
    default, its normalisation), e.g. a Lorenz3 model becomes a Lorenz10 model with a
    few dozen Lorenz10 trajectories.  Same flags and files as `mpnode train`.
    """
    from mpnode.model import Model

    output = o["output"]
    _check_output(output)
    datasets = _read_all(data)
    config = _config(o, "fit" if refit_norm else "keep")
    model = None
    if not o["resume"]:
        model = Model.load(model_file)
        if o["substeps"]:
            model = model.with_spec(substeps=o["substeps"])
    attrs = {"trained_on": ";".join(os.path.abspath(p) for p in data), "finetuned_from": os.path.abspath(model_file),
             "system": datasets[0].system}
    result = run_training(model, datasets, list(data), config, output, o["resume"], attrs)
    click.echo(validation_report(result, datasets, list(data)))

"""`mpnode train DATA... -o MODEL` and `mpnode finetune MODEL DATA... -o NEW`: learn a model."""
import contextlib
import os
import sys
import tempfile

import click

from mpnode.base.errors import InputError, NumericalError
from mpnode.base.options import aliases, switches
from mpnode.engine.spec import AGGREGATIONS, KINDS, LINEAR_TARGETS
from mpnode.model.config import DTYPES, ModelConfig
from mpnode.training import TrainConfig
from mpnode.training.config import DEFAULT_EPOCHS, SCHEDULES, epoch_cap, parse_curriculum
from mpnode.training.losses import LOSSES
from mpnode.training.recipes import AUTO_ALL, FINETUNE_AUTO

from .eval_cmd import check_plot, plot_option
from .main import claim_outputs, main, scheduler_option

#: `mpnode train SCENE` (a scene instead of files): trajectories generated and the default time budget
#: (a scene set: its members' own counts, and the budget its evidence was measured at)
SCENE_TRAJECTORIES = 300
SCENE_EVAL_TRAJECTORIES = 100
SCENE_TIME_LIMIT = "3m"
SCENE_SET_TIME_LIMIT = "10m"
DEFAULT = TrainConfig()
MODEL_DEFAULT = ModelConfig()


def flags(cls, name):
    """The flags of option ``name`` of the configuration class ``cls``: its own name first, then
    its older names, and the parameter name (the library's)."""
    return [f"--{n.replace('_', '-')}" for n in (name, *aliases(cls, name))] + [name]


def switch_flags(cls, name):
    """The flag of the switch of option ``name`` (e.g. --clip-global for clip_mode), and its key."""
    key = next(k for k, (option, _) in switches(cls).items() if option == name)
    return [f"--{key.replace('_', '-')}", key]


class Duration(click.ParamType):
    """--time-limit: minutes, or a number with s, m or h."""

    name = "DURATION"

    def convert(self, value, param, ctx):
        from mpnode.runs import parse_duration

        try:
            return parse_duration(value)
        except InputError as e:
            self.fail(f"{value!r}: {e.expected}", param, ctx)


def training_options(f):
    """The optimisation flags shared by train and finetune; defaults are TrainConfig's, and so are
    the checks of their values (`checked`): a flag here only parses."""
    d = DEFAULT
    options = [
        click.option("--epochs", type=int, default=d.epochs,
                     help=f"Passes over the training trajectories.  Default: {DEFAULT_EPOCHS}, or with --time-limit as "
                          "many as the time limit allows (it is the budget)."),
        click.option("--time-limit", type=Duration(),
                     help="Stop cleanly after this long (best model and checkpoint saved): minutes, or 90s, 1.5h."),
        click.option("--batch-size", type=int, default=d.batch_size,
                     help="Trajectories per batch (each batch from one file: one block-diagonal graph).  Default: "
                          f"the recipe's (auto: {AUTO_ALL['batch_size']} to train an MP-NODE or L2S model, "
                          f"{FINETUNE_AUTO['batch_size']} to fine-tune an MP-NODE model; otherwise and with "
                          f"--recipe paper: {d.batch_size})."),
        click.option("--lr", type=float, default=d.lr, show_default=True, help="Adam learning rate (> 0)."),
        click.option("--beta1", type=float, default=d.beta1, show_default=True, help="Adam beta1, in [0, 1)."),
        click.option("--beta2", type=float, default=d.beta2, show_default=True, help="Adam beta2, in [0, 1)."),
        click.option("--eps", type=float, default=d.eps, show_default=True, help="Adam epsilon."),
        click.option("--clip", type=float, default=d.clip, show_default=True,
                     help="Gradient clip norm, applied to each parameter array separately (0: no clipping)."),
        click.option(*switch_flags(TrainConfig, "clip_mode"), is_flag=True,
                     help="Clip by one norm over all parameters instead."),
        click.option("--val-split", type=float, default=d.val_split, show_default=True,
                     help="Fraction in [0, 1) of every file's trajectories held out for validation (random, seeded)."),
        click.option("--split-seed", type=int, help="Seed of the train/validation split.  Default: --seed."),
        click.option("--noise", type=float, default=d.noise, show_default=True,
                     help="Std of the Gaussian noise added once to the normalised training states."),
        click.option("--loss", type=click.Choice(list(LOSSES)), default=d.loss, show_default=True),
        click.option("--patience", type=int, default=d.patience, show_default=True,
                     help="Epochs without a new best validation loss before the learning rate is cut."),
        click.option("--lr-decay", type=float, default=d.lr_decay, show_default=True,
                     help="Factor in (0, 1] applied to the learning rate at each cut."),
        click.option("--min-lr", type=float, default=d.min_lr, show_default=True,
                     help="No cut once the learning rate is at or below this."),
        click.option("--schedule", type=click.Choice(SCHEDULES), default=d.schedule, show_default=True,
                     help="Learning rate: plateau (cut by --lr-decay after --patience epochs without a new best) or "
                          "cosine (from --lr down to --min-lr over --epochs, or over --time-limit when that comes "
                          "first)."),
        click.option("--val-graphs", type=int, default=d.val_graphs, show_default=True,
                     help="Hold out this many whole graphs of every file that has more, for validation: the best "
                          "model is then the one that does best on graphs it was not trained on."),
        click.option("--seed", type=int, default=d.seed, show_default=True,
                     help="Seed of the initial weights, the split, the noise and the shuffles."),
        click.option("--substeps", type=int, help="RK4 steps per dt (train default 1; "
                     "finetune default: the model's)."),
        click.option(*flags(TrainConfig, "curriculum"), callback=parsed_by(parse_curriculum), metavar="W1,W2,...,full",
                     help="Train first on windows of W1 steps, then W2, ..., then the full horizon (e.g. 5,10,full; "
                          "'full' is implied at the end).  Each trajectory is cut into consecutive windows, each "
                          "starting from its true state; validation stays on the full horizon."),
        click.option("--curriculum-epochs", type=int, default=d.curriculum_epochs,
                     show_default=True, help="Epochs per window length of --curriculum (the full horizon "
                     "gets the rest)."),
        click.option("--input-noise", type=float, default=d.input_noise, metavar="STD",
                     help="Std of Gaussian noise, drawn afresh every epoch, added to the initial state of every "
                     "training rollout (normalised units; the targets stay clean): the model learns to come back "
                     "towards the data from states a little off them, as its own long rollouts are.  "
                     f"Default: the recipe's ({d.input_noise:g} unless the README's recipe table says otherwise)."),
        click.option("--train-window", type=int, default=d.train_window, metavar="W",
                     help="Train on windows of W steps (after any --curriculum) while the model is still chosen "
                     "by its validation error over the files' full horizon (0: train on the full horizon).  "
                     "Default: the recipe's (0 unless the README's recipe table says otherwise)."),
        click.option("--ignore-attrs", is_flag=True, default=False,
                     help="Learn as if the data had neither node attributes nor edge weights (by default a model "
                          "hears both whenever the files have them; finetune: only a MODEL trained without them)."),
        click.option("--resume", is_flag=True,
                     help="Continue the run whose checkpoint (OUTPUT.state) is beside -o; its settings are kept "
                          "except --epochs and --time-limit."),
        click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
                     help="Model file to write: the best model so far (saved atomically at most every 10 s and at the end)."),
        plot_option("the training and validation loss per epoch, the validation normalised MSE and the learning "
                    "rate (from the training log, at the end of the run, whatever its outcome)"),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def safeguard_options(f):
    """--max-bad-steps, --blowup and --checkpoint-seconds (train and finetune): what a run does
    about steps that blow up and how much of it a kill can lose; defaults and checks TrainConfig's."""
    d = DEFAULT
    options = [
        click.option("--max-bad-steps", type=int, default=d.max_bad_steps, show_default=True,
                     help="Stop after this many bad steps (non-finite or blown-up) without a new best."),
        click.option("--blowup", type=float, default=d.blowup, show_default=True, metavar="FACTOR",
                     help="A step whose batch loss exceeds FACTOR times the initial validation loss is bad: skipped, "
                          "the weights back to the best epoch's and the learning rate halved (0: only non-finite "
                          "steps are bad)."),
        click.option("--checkpoint-seconds", type=float, default=d.checkpoint_seconds, show_default=True,
                     help="Save the best model and the checkpoint at most this often (and at the end)."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def ensemble_options(f):
    """--ensemble and --bootstrap (train and finetune); --time-limit is then the ensemble's."""
    d = DEFAULT
    options = [
        click.option("--ensemble", type=int, default=d.ensemble, show_default=True, metavar="K",
                     help="Train K models (members: seeds SEED, SEED+1, ...; one validation split) into one file, "
                          "in parallel (a process each on this machine, or on Dask with --scheduler).  Their "
                          "spread says how far to trust a prediction: `mpnode eval` reports it, calibrated on "
                          "the validation trajectories, and how often the truth falls inside its bands.  "
                          "--time-limit is the whole ensemble's budget."),
        click.option("--bootstrap/--no-bootstrap", default=None,
                     help="With --ensemble: each member trains on a resample (with replacement) of the training "
                          "trajectories (the validation split stays one): members that saw different data disagree "
                          "where data are thin.  Default: off (members differ by seed only)."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def recipe_option(paper):
    """--recipe of train and finetune; ``paper`` says what the paper's recipe sets."""
    return click.option("--recipe", type=click.Choice(["auto", "paper"]), default="auto", show_default=True,
                        help="Settings for what you leave unset: auto (the best we measured for the data's system: "
                             f"see the README's recipe table) or paper ({paper}).")


def parsed_by(parse):
    """A click callback that parses a flag's text with the library's ``parse`` (its InputError,
    click's usage error naming the flag as the user typed it)."""
    def callback(ctx, param, value):
        try:
            return parse(value)
        except InputError as e:
            raise click.BadParameter(f"{e.problem} (expected {e.expected})") from None

    return callback


def given_options(o, skip=("output", "resume", "trajectories", "recipe", "plot", "scheduler")):
    """The library's options (runs.split_options' names; a switch such as clip_global under its
    own) the user set, checked by the library: flags left at their defaults are not passed, so
    the recipe and the library's defaults fill them."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    return checked({k: v for k, v in o.items() if k not in skip and v is not None
                    and ctx.get_parameter_source(k) not in (None, ParameterSource.DEFAULT)})


def checked(options):
    """``options`` if the library takes them (runs.split_options, before any work); its InputError
    names the option's flag."""
    from mpnode.runs.run import OPTION_NAMES, split_options

    try:
        split_options(options)
    except InputError as e:
        source = "--" + e.field.replace("_", "-") if e.field in OPTION_NAMES else e.source
        raise InputError(source, e.field, e.problem, e.expected) from None
    return options


def check_outputs(output, inputs, data_files=(), plot=None):
    """-o, the files beside it and --plot must not be one of the inputs, nor one another
    (nothing is written if one is); a --plot needs matplotlib (checked first)."""
    from mpnode.base.atomic import check_outputs as check
    from mpnode.training import state_path
    from mpnode.training.log import log_path

    check_plot(plot)
    outputs = {"--output": output, "--output (log)": log_path(output), "--output (checkpoint)": state_path(output)}
    for path in data_files:
        outputs[f"--output (data {os.path.basename(path)})"] = path
    if plot:
        outputs["--plot"] = plot
    check(outputs, [p for p in inputs if os.path.exists(p)])


def _fmt(v):
    return "-" if v is None else f"{v:.4g}"


def run_with_progress(epochs, time_limit, output, call, plot=None):
    """Run ``call(progress=, notify=)`` (a runs.train/finetune) with a progress bar on stderr that
    follows whichever of ``epochs`` and ``time_limit`` (seconds or None) ends the run first; print
    the outcome; draw the training curves to ``plot``; exit 3 on divergence, 130 on Ctrl-C."""
    from mpnode.training import state_path
    from mpnode.training.log import log_path

    state = {"bar": None}
    epochs = epoch_cap(epochs, time_limit)

    with contextlib.ExitStack() as stack:
        def progress(record):  # the bar starts with the first epoch: a run refused before it prints nothing
            if state["bar"] is None:
                state["bar"] = stack.enter_context(click.progressbar(
                    length=BAR, label="training", file=sys.stderr, item_show_func=progress_line, show_eta=True))
            bar = state["bar"]
            bar.update(max(0, round(done_fraction(record, epochs, time_limit) * BAR) - bar.pos), record)

        def notify(msg):
            click.echo(("\n" if state["bar"] is not None else "") + msg, err=True)

        result = call(progress=progress, notify=notify)
    click.echo(f"{result.status}: {result.message}")
    best = (f"validation normalised MSE {_fmt(result.val_nmse)}" if result.validation
            else f"loss {result.best_val_loss:.4g} (no validation trajectories: on the training data)")
    click.echo(f"best {best} at epoch {result.best_epoch} of {result.epoch}; {result.seconds:.1f} s; "
               f"learning rate now {result.lr:g}")
    click.echo(f"wrote {output} (best model), {log_path(output)} (log), {state_path(output)} (checkpoint for --resume)")
    if plot:
        plot_training(output, plot, result.config.loss)
    if result.status == "diverged":
        raise NumericalError(result.message)
    if result.status == "interrupted":
        click.echo("interrupted: continue with the same command plus --resume", err=True)
        sys.exit(130)
    return result


#: steps of the training progress bar (a fraction of the epochs or of the time limit)
BAR = 1000


def done_fraction(record, epochs, time_limit):
    """How much of the run an epoch's log record has done, in [0, 1]: of the epochs (None: no cap),
    or of the time limit (seconds) when that ends the run first."""
    done = 0.0
    if epochs is not None:
        done = record["epoch"] / epochs if epochs else 1.0
    if time_limit:
        done = max(done, record["elapsed"] / time_limit)
    return min(done, 1.0)


def progress_line(record):
    """What the progress bar shows of an epoch's log record: the validation normalised MSE (1 is no
    better than predicting the mean, 0 perfect), the best so far, the learning rate."""
    if record is None:
        return ""
    window = f"  window {record['window']} steps" if record.get("window") is not None else ""
    return (f"epoch {record['epoch']}  validation nMSE {_fmt(record.get('val_nmse'))}  "
            f"best {_fmt(record.get('best_val_nmse'))}  lr {record['lr']:.2g}{window}")


def plot_training(output, plot, loss):
    """The training curves of the run beside ``output`` (its whole log, resumed parts included)."""
    from mpnode.plot import plot_training as draw
    from mpnode.training.log import log_path

    draw(log_path(output), plot, loss=loss, title=os.path.basename(output))
    click.echo(f"wrote {plot} (training curves)")


def print_validation(result):
    for f in result.validation:
        click.echo(f"validation normalised MSE on {f['file']} ({f['trajectories']} trajectories): mean over steps "
                   f"{f['nmse']:.4g}, last step {f['nmse_last']:.4g}")


@main.command("train")
@click.argument("data", nargs=-1, required=True)
@click.option(*flags(ModelConfig, "kind"), type=click.Choice(KINDS), default=MODEL_DEFAULT.kind, show_default=True,
              help="mpnode: one module per node with learned messages (runs on any graph); l2s: the paper's "
                   "graph-network ODE baseline (any graph); node: one neural ODE for the whole system (its N only).")
@click.option("--message-dim", type=int, default=MODEL_DEFAULT.message_dim, show_default=True,
              help="Message size: the number of learned message variables each node carries (mpnode only).")
@click.option("--hidden", type=int, default=MODEL_DEFAULT.hidden, show_default=True,
              help="Hidden width: units in each of the network's two tanh layers.")
@click.option(*flags(ModelConfig, "aggregation"), type=click.Choice(AGGREGATIONS),
              help="How a node combines what its neighbours send: mean (the paper's), sum, or scaled (the sum over "
                   "the training graphs' mean in-degree).  Default: mean (mpnode), sum (l2s).")
@click.option("--linear-aggregate", is_flag=True,
              help="Also feed the aggregate straight to the field, around the MLP (k = MLP([x, u, m']) + m' W_agg, "
                   "W_agg starting at 0): the field can then follow the larger aggregates of denser graphs than "
                   "its training graphs (mpnode with messages; docs/model-format.md).")
@click.option("--linear-aggregation", type=click.Choice(AGGREGATIONS),
              help="The aggregate the linear path reads, when not the MLP's own (implies --linear-aggregate).  "
                   "E.g. --aggregation mean --linear-aggregation scaled: the MLP sees the degree-free mean, which "
                   "stays in range on denser graphs, and the degree reaches the field only through the linear "
                   "path (scaled sum, as PNA's degree scalers).")
@click.option("--linear-target", type=click.Choice(LINEAR_TARGETS),
              help="What the linear path adds to: all (dx/dt and the messages' dm/dt; the default) or state "
                   "(dx/dt alone, so the messages' own dynamics never hear the degree; implies "
                   "--linear-aggregate).")
@click.option("--zero-messages", is_flag=True, help="Clamp messages to 0 (the paper's ablation).")
@click.option("--self-messages", is_flag=True,
              help="Every node also hears its own message (the Julia code's 'full' graph for Lorenz).")
@click.option("--dtype", type=click.Choice(DTYPES), default=MODEL_DEFAULT.dtype, show_default=True)
@click.option("--encoder-window", type=int, metavar="W",
              help="Learn, with the model, an initial-state encoder that estimates each trajectory's whole "
                   "starting state from its first W observations: values nobody measured (a dimension that is "
                   "NaN throughout the data is such a hidden state) and noise on the measured ones; 0: start "
                   "from the first observation as it is.  Default: the recipe's.")
@click.option("--latent-dims", type=int, metavar="K",
              help="Give each node K more state dimensions than the data have, never observed: room for what "
                   "the data do not show (the initial-state encoder estimates where they start).")
@click.option("--kinematics", metavar="TERMS",
              help="State derivatives the physics fixes, computed exactly instead of learned, so the network "
                   "learns only the rest: terms D:S (x_D' = x_S: a position and its velocity) or qD:S (the unit "
                   "quaternion x_D..x_D+3, [w, x, y, z], turned by the body rates x_S..x_S+2), separated by "
                   "commas, e.g. 0:7,1:8,2:9,q3:10 (the quadrotor); none: every derivative learned (mpnode and "
                   "node models).  Default: none.")
@recipe_option("the MP-NODE paper's: mean aggregation, plateau schedule, batch 128")
@click.option("--trajectories", type=click.IntRange(min=2),
              help=f"Only when DATA is a scene: trajectories to generate (default {SCENE_TRAJECTORIES}; a scene set: "
                   "each member's own count, or this many for each).")
@training_options
@safeguard_options
@ensemble_options
@scheduler_option
def train_cmd(data, trajectories, recipe, **o):
    """Learn a model from trajectory files DATA... (same dx, du and dt; graphs and N may differ).

    DATA may instead be one scene (a built-in name such as coupled_pendulum, or a
    .toml file): its data are generated beside the model (OUTPUT.data.h5, --trajectories
    of them), the model is trained (default time limit 3 minutes) and evaluated at the
    end on fresh trajectories of the scene (another seed).  Or a scene set (quad3-5:
    3, 4 and 5 quadrotors): one file per member scene (OUTPUT.quad3.data.h5, ...;
    member i with seed --seed + i), trained on together (default time limit 10
    minutes), then evaluated on fresh trajectories of a size none of them has (quad6).

    Normalisation (z-score per state dimension) is fitted on the training split only
    and stored in the model.  Beside OUTPUT: OUTPUT.log.jsonl (one JSON line per epoch:
    losses, the validation normalised MSE, mean and max gradient norm, learning rate,
    window length and curriculum stage; each line written whole by one write, so a
    killed run leaves a readable log)
    and OUTPUT.state (checkpoint for --resume; also after a kill -9, from the last
    checkpoint).

    Chaotic systems: --curriculum 5,10,full trains on short windows first.

    Exit status: 0 trained; 2 bad input (also: OUTPUT is being written by another run,
    or --resume with a flag that contradicts the run); 3 training diverged (the best finite
    model is kept); 4 the system refused (a file could not be written, e.g. a full disk:
    OUTPUT and its checkpoint stay a consistent pair to --resume from; memory; numba
    missing, checked before anything is written); 130 interrupted (continue with --resume).
    """
    from mpnode import runs

    from data_gen import SETS

    runs.require_numba()
    output, plot = o["output"], o["plot"]
    options = given_options(o)  # checked before any data are generated
    scene = _scene_of(data)
    if scene is None:
        check_outputs(output, data, plot=plot)
        claim_outputs({"--output": output})
    else:
        scenes = _training_scenes(scene, trajectories, o["seed"])
        data = tuple(output + (f".{s.name}" if scene in SETS else "") + ".data.h5" for s in scenes)
        check_outputs(output, [scene], data, plot=plot)
        claim_outputs({"--output": output})
        if not (o["resume"] and all(map(os.path.exists, data))):
            for s, path in zip(scenes, data):
                _generate(s, path)
    if scene is not None and o["time_limit"] is None:
        options["time_limit"] = runs.parse_duration(SCENE_SET_TIME_LIMIT if scene in SETS else SCENE_TIME_LIMIT)
    datasets = runs.read_all(data)
    resume = o["resume"]
    if o["ensemble"] > 1:
        model = train_ensemble(o, data, output, options, recipe, datasets)
    else:
        result = run_with_progress(o["epochs"], options.get("time_limit"), output, lambda **kw: runs.train(
            data, output, options, recipe_name=recipe, resume=resume, datasets=datasets, **kw), plot)
        print_validation(result)
        model = result.model
    if scene is not None:
        _evaluate_on_fresh(scene, model, output, o["seed"])


def check_ensemble(o):
    """--ensemble K > 1 trains K runs into one file: no log or checkpoint of its own to plot or resume."""
    for flag in ("resume", "plot"):
        if o[flag]:
            raise InputError(f"--{flag}", flag, "is given with --ensemble",
                             "an ensemble without it (its members train afresh and leave no log or checkpoint)")


def train_ensemble(o, data, output, options, recipe, datasets, parent=None, refit_norm=False):
    """`--ensemble K`: the members on the pool or --scheduler, then their figures; returns the Ensemble."""
    from mpnode.runs.ensemble import train_ensemble as train

    check_ensemble(o)

    def notify(msg):
        click.echo(msg, err=True)

    ensemble, results = train(data, output, options, recipe_name=recipe, scheduler=o["scheduler"], notify=notify,
                              datasets=datasets, parent=parent, refit_norm=refit_norm)
    for i, r in enumerate(results):
        click.echo(f"member {i} (seed {ensemble.member_info['member_seed'][i]}): {r['status']}, best validation "
                   f"normalised MSE {_fmt(r['val_nmse'])} at epoch {r['best_epoch']} of {r['epoch']}; "
                   f"{r['seconds']:.1f} s")
    if any(r["status"] == "diverged" for r in results):
        raise NumericalError("a member diverged (its best finite model is kept in the ensemble)")
    click.echo(f"wrote {output} (ensemble of {ensemble.size}; spread scale "
               + ", ".join(f"{v:.3g}" for v in ensemble.spread_scale) + ")")
    return ensemble


def _scene_of(data):
    """The scene or scene set DATA names (one argument, not a file), or None for trajectory files."""
    if len(data) != 1 or os.path.exists(data[0]):
        return None
    from data_gen import BUILTIN, SETS

    if data[0] in BUILTIN or data[0] in SETS or data[0].endswith(".toml"):
        return data[0]
    raise InputError(data[0], "file", "does not exist and is not a built-in scene",
                     "trajectory files, or one scene name (see `mpnode scenes`)")


def _training_scenes(scene, trajectories, seed):
    """The Scenes whose data `mpnode train SCENE` generates: the scene's, or a scene set's members."""
    from dataclasses import replace

    from data_gen import SETS, load_scene

    if scene in SETS:
        return SETS[scene].scenes(trajectories, seed)
    return [replace(load_scene(scene), trajectories=trajectories or SCENE_TRAJECTORIES, seed=seed)]


def _generate(s, path):
    from data_gen import generate
    from mpnode.data import write_trajectories

    with click.progressbar(length=s.trajectories, label=f"generating {s.name}", file=sys.stderr) as bar:
        traj = generate(s, workers=2, progress=bar.update)
    write_trajectories(path, traj)
    click.echo(f"generated {path}: {s.name}, B={s.trajectories}, T={s.horizon}, seed {s.seed}")


def _evaluate_on_fresh(scene, model, output, seed):
    """Evaluate on fresh trajectories: of the scene (seed + 1), or of a scene set's test scene (the
    seed after its members')."""
    from dataclasses import replace

    from data_gen import SETS, load_scene
    from mpnode.data import read_trajectories

    from .eval_cmd import evaluate_and_report, format_report

    name, seed = (SETS[scene].test, seed + len(SETS[scene].members)) if scene in SETS else (scene, seed + 1)
    with tempfile.TemporaryDirectory() as tmp:
        test = os.path.join(tmp, "test.h5")
        _generate(replace(load_scene(name), trajectories=SCENE_EVAL_TRAJECTORIES, seed=seed), test)
        # a model without the scene's node attributes or edge weights was trained with --ignore-attrs
        _, report = evaluate_and_report(model, read_trajectories(test),
                                        f"{SCENE_EVAL_TRAJECTORIES} fresh {name} trajectories (seed {seed})",
                                        ignore_attrs=True)
    click.echo(format_report(report, output))


@main.command("finetune")
@click.argument("model_file", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("data", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--refit-norm/--keep-norm", default=None,
              help="Fit the normalisation on the new training split, or keep the model's.  Refitting changes the "
                   "weights with it so that the model starts from the same predictions, and the loss weighs each "
                   "state dimension by the new data's spread (as `mpnode eval` does).  Default: the recipe's "
                   "(auto: refit for the quadrotor swarm, keep otherwise; paper: keep).")
@recipe_option("the paper's training settings: plateau schedule, batch 128")
@training_options
@safeguard_options
@ensemble_options
@scheduler_option
def finetune_cmd(model_file, data, refit_norm, recipe, **o):
    """Continue training MODEL on DATA... and write the result to OUTPUT.

    Starts from exactly MODEL's weights (its kind, dimensions, dt, message settings and,
    by default, its normalisation), e.g. a Lorenz3 model becomes a Lorenz10 model with a
    few dozen Lorenz10 trajectories.  Same flags, files and exit statuses as `mpnode train`;
    a MODEL trained on another system than DATA's is used, with a warning.  DATA must have the
    node attributes (the same names, in order) and the edge weights MODEL hears, as for
    `mpnode eval`; --ignore-attrs leaves out those of DATA for a MODEL trained without them.
    """
    from mpnode import runs

    runs.require_numba()
    output = o["output"]
    check_outputs(output, [model_file, *data], plot=o["plot"])
    claim_outputs({"--output": output})
    datasets = runs.read_all(data)
    resume, options = o["resume"], given_options(o)
    from mpnode.runs.ensemble import ensemble_size

    if o["ensemble"] == 1 and not resume:  # an ensemble's members each continue by default
        o["ensemble"] = options["ensemble"] = ensemble_size(model_file)
    if o["ensemble"] > 1:
        train_ensemble(o, data, output, options, recipe, datasets, parent=model_file, refit_norm=refit_norm)
        return
    result = run_with_progress(o["epochs"], o["time_limit"], output, lambda **kw: runs.finetune(
        model_file, data, output, options, refit_norm=refit_norm, recipe_name=recipe, resume=resume,
        datasets=datasets, **kw), o["plot"])
    print_validation(result)

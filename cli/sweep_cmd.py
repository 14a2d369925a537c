"""`mpnode sweep SWEEP.toml -o DIR`: many trainings from one file, on a process pool or Dask."""
import sys

import click

from .main import claim_outputs, main, scheduler_option


@main.command("sweep")
@click.argument("sweep_file", metavar="SWEEP.toml", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for the runs (DIR/runs/NAME/: model.h5, its log, result.json) and the summary "
                   "(DIR/summary.csv, DIR/summary.md); created if absent.")
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True,
              help="Trainings at once on the local pool or --scheduler local (each one numba thread).")
@scheduler_option
def sweep_cmd(sweep_file, output, workers, scheduler):
    """Train every run of SWEEP.toml (a grid or a list of runs; docs/sweep-format.md).

    Each run is one task: its data files go to the worker, the model file, log and
    evaluation come back and are written under DIR; the summary table (validation and
    test nMSE, epochs, minutes, errors) is rewritten as each run finishes.  Runs already
    finished with the same settings and data are not redone, so rerunning the command
    continues an interrupted sweep.  A run that fails is reported in the summary and the
    others go on.

    Every check a run can make before training is made before the first run starts:
    every data and test file is read, the test files must fit the models (dx, du, dt),
    the data must be learnable and the trainings fit in memory, and no input may lie
    where the sweep writes (DIR/runs/, DIR/summary.*).

    Exit status: 0 every run finished; 1 some failed (see the summary); 2 bad sweep file
    or option (also: DIR being written by another sweep); 4 the system refused (DIR
    cannot be written: permission, full disk, read-only folder); 130 interrupted (rerun
    to continue).
    """
    import os

    from mpnode.base.atomic import check_writable
    from mpnode.base.oserrors import file_error
    from mpnode.runs.executors import open_executor
    from mpnode.runs.preflight import check_out_folder
    from mpnode.runs.sweep import FINISHED, load_finished, read_sweep, run_sweep

    sweep = read_sweep(sweep_file)
    for warning in sweep.warnings:
        click.echo(f"warning: {warning}", err=True)
    check_out_folder(sweep, output)
    try:
        os.makedirs(output, exist_ok=True)
    except OSError as e:
        raise file_error(e, output, "create the folder") from None
    check_writable(os.path.join(output, "summary.csv"))
    claim_outputs({"--output": output})
    with open_executor(scheduler, workers, one_thread=True) as farm:
        where = f"{farm.workers} Dask worker thread(s)" if farm.is_dask else f"{workers} local process(es)"
        click.echo(f"{len(sweep.runs)} run(s) of {sweep_file} on {where}", err=True)
        with click.progressbar(length=len(sweep.runs), label="runs", file=sys.stderr, show_eta=True,
                               item_show_func=lambda r: r and f"{r['name']}: {r['status']}") as bar:
            bar.update(sum(load_finished(output, p) is not None for p in sweep.runs))  # not redone

            def progress(record):
                bar.update(1, record)
                click.echo(f"\n{_line(record)}", err=True)

            try:
                records = run_sweep(sweep, output, farm, progress=progress)
            except KeyboardInterrupt:
                click.echo(f"\ninterrupted: finished runs are in {output}; rerun the same command to continue",
                           err=True)
                sys.exit(130)
    failed = [r for r in records.values() if r["status"] not in FINISHED]
    click.echo(f"wrote {os.path.join(output, 'summary.csv')} and summary.md: "
               f"{len(records) - len(failed)} of {len(records)} runs finished")
    if failed:
        click.echo("failed: " + ", ".join(f"{r['name']} ({r.get('error')})" for r in failed), err=True)
        sys.exit(1)


def _line(r):
    if r["status"] in ("failed", "skipped"):
        return f"{r['name']}: {r['status'].upper()}: {r.get('error')}"
    val = "-" if r.get("val_nmse") is None else f"{r['val_nmse']:.4g}"
    test = "" if r.get("test_nmse") is None else f", test nMSE {r['test_nmse']:.4g}"
    return (f"{r['name']}: {r['status']}, {r['epochs']} epochs, validation nMSE {val}{test}, "
            f"{r['seconds'] / 60:.1f} min")

"""Entry point of the `mpnode` command: a click group whose commands live in sibling modules.

This group is the one place where failures become messages: each is a one-paragraph message
on stderr, never a traceback, with its exit status (EXIT_STATUS): bad input anywhere below
(`mpnode.base.errors.InputError`) 2; a computation that blew up (NumericalError) 3; the
system refusing (an OSError: a full disk, a read-only folder, a missing permission, a file in
use; memory running out; a library that cannot be imported) 4.
"""
import sys

import click

from mpnode.base.errors import InputError, NumericalError

#: the exit statuses of the failures every command shares (each command's --help lists its own)
EXIT_STATUS = {"input": 2, "numerical": 3, "system": 4}


class _Group(click.Group):
    def invoke(self, ctx):
        from mpnode.base.oserrors import explain

        try:
            return super().invoke(ctx)
        except InputError as e:
            _fail(e, "input")
        except NumericalError as e:
            _fail(e, "numerical")
        except BrokenPipeError:  # the reader of our output went away (`mpnode eval ... | head`): not a failure
            _quiet_exit()
        except OSError as e:
            _fail(explain(e), "system")
        except MemoryError:
            _fail("the system ran out of memory (ask for less: fewer trajectories, a shorter horizon, a smaller "
                  "--hidden or --batch-size; or close other programs)", "system")
        except ImportError as e:
            missing = getattr(e, "name", None)
            _fail(f"{e} (mpnode needs it: pip install {missing.split('.')[0]})" if missing else e, "system")


def _quiet_exit():
    """Stop without a word: nobody reads standard output any more (its pipe closed)."""
    import os

    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's own flush at exit must not fail
    sys.exit(0)


def _fail(message, kind):
    click.echo(f"Error: {message}", err=True)
    sys.exit(EXIT_STATUS[kind])


def claim_outputs(outputs):
    """Claim the files this command writes ({flag: path}) until it ends (a lock beside each:
    mpnode.base.locks), so that a second command writing one stops with exit status 2 naming this one."""
    from mpnode.base.locks import claim

    ctx = click.get_current_context()
    command = " ".join(["mpnode", *sys.argv[1:]]) if sys.argv and "mpnode" in sys.argv[0] else ctx.command_path
    for flag, path in outputs.items():
        if path:
            ctx.with_resource(claim(path, command, flag))


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mpnode")
def main():
    """mpnode: learn modular simulations of networked dynamical systems.

    One small neural ODE learns a single subsystem; every node of a graph runs it
    and nodes coordinate through learned messages (MP-NODE).
    """
    from mpnode.engine.codegen import ask_for_wide_vectors
    from mpnode.engine.compiling import set_announcer

    ask_for_wide_vectors()  # the command's process is mpnode's own (mpnode.engine.codegen)
    set_announcer(lambda message: click.echo(message, err=True))


def scheduler_option(f):
    """--scheduler (default: $MPNODE_SCHEDULER): where independent tasks run (mpnode.runs.executors)."""
    return click.option(
        "--scheduler", envvar="MPNODE_SCHEDULER", show_envvar=True, metavar="none|local|ADDRESS|FILE",
        help="Run the tasks on Dask (pip install 'mpnode[dist]'): local (a cluster of --workers processes on this "
             "machine), the address of a running scheduler (tcp://host:8786) or its scheduler file.  "
             "Default: a local process pool.")(f)


# Each command module adds its commands to `main` on import.
from . import (
    convert_cmd,  # noqa: E402,F401
    eval_cmd,  # noqa: E402,F401
    export_cmd,  # noqa: E402,F401
    fit_cmd,  # noqa: E402,F401
    generate_cmd,  # noqa: E402,F401
    inspect_cmd,  # noqa: E402,F401
    sweep_cmd,  # noqa: E402,F401
    train_cmd,  # noqa: E402,F401
)

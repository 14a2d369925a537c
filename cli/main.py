"""Entry point of the `mpnode` command: a click group whose commands live in sibling modules.

Bad input anywhere below surfaces as `mpnode.base.errors.InputError`; this group turns it
into a one-paragraph message on stderr and exit status 2, never a traceback.
"""
import sys

import click

from mpnode.base.errors import InputError, NumericalError


class _Group(click.Group):
    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except InputError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(2)
        except NumericalError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(3)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mpnode")
def main():
    """mpnode: learn modular simulations of networked dynamical systems.

    One small neural ODE learns a single subsystem; every node of a graph runs it
    and nodes coordinate through learned messages (MP-NODE).
    """


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
    generate_cmd,  # noqa: E402,F401
    inspect_cmd,  # noqa: E402,F401
    sweep_cmd,  # noqa: E402,F401
    train_cmd,  # noqa: E402,F401
)

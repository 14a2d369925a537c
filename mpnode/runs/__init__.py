"""Running trainings from files: one run (`train`, `finetune`: the functions behind the
commands), sweeps of many runs from a TOML file, and the executors they run on (a local
process pool or Dask).

Owns: `run`, `ensemble` (K members trained as tasks into one file), `sweep`, `preflight` (a sweep's checks before its first run), `executors`.  May import: mpnode.training and everything below it.
"""
from .run import finetune, parse_duration, read_all, require_numba, train  # noqa: F401

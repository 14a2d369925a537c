"""Run the whole paper suite: every experiment's trainings, analyses and figures -> RESULTS.md.

    python benchmarks/paper/run_all.py            # full run (about 6 hours on 2 cores from nothing; minutes when cached)
    python benchmarks/paper/run_all.py --short    # a quarter of the epochs and budgets (about 85 minutes from nothing) into benchmarks/paper/short/
    python benchmarks/paper/run_all.py --quick    # CI-sized smoke run (a few minutes) into benchmarks/paper/quick/

Each experiment also runs alone (python benchmarks/paper/exp_NAME.py [--short | --quick]); trained
models and data are cached under OUT/work, so reruns only redo what changed, and an invocation
that was killed continues its trainings from their checkpoints (mpnode.runs.sweep).
"""
from common import EXPERIMENTS, main

if __name__ == "__main__":
    main(list(EXPERIMENTS), description=__doc__)

"""Models trained apart, averaged: the normalised MSE of the mean of their predictions.

Separately trained models (other seeds, other splits, so other normalisations: not one ensemble
file) each predict the test file from its first states; their predictions are averaged and scored
as `mpnode eval` scores one model (squared error over the test file's per-dimension variance, mean
over steps 1..T), for each model alone, each pair and all of them.

    python benchmarks/studies/quadrotor/averaged_models.py TEST.h5 MODEL.h5 MODEL.h5 [...]
"""
import itertools
import json
import sys

import numpy as np

from mpnode.data import read_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.evaluation.metrics import variance
from mpnode.model import Model


def main(test_path, model_paths):
    data = read_trajectories(test_path)
    runs = [evaluate(Model.load(p), data) for p in model_paths]
    truth = runs[0].scored
    var = variance(truth)

    def nmse(members):
        mean = np.mean([runs[i].predictions for i in members], axis=0)
        return float(np.nanmean((mean[:, 1:] - truth[:, 1:]) ** 2 / var))

    sets = [c for k in range(1, len(runs) + 1) for c in itertools.combinations(range(len(runs)), k)]
    print(json.dumps({" + ".join(model_paths[i] for i in c): nmse(c) for c in sets}, indent=1))


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__.rsplit("\n\n", 1)[-1])
    main(sys.argv[1], sys.argv[2:])

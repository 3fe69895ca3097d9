"""The paper's baselines (Table 1): M4 draws each mass uniformly in [1, 351] g with the Mersenne Twister,
M5 predicts the mean training container mass for every recording."""
from __future__ import annotations

import random
from collections.abc import Iterable

import pandas as pd

from massviz.io.ccm_annotations import ANN_MASS

#: M4's interval in grams.
RANDOM_RANGE_G = (1.0, 351.0)


def random_baseline(ids: Iterable[int], seed: int) -> dict[int, float]:
    """M4: ``{id: random.Random(seed).uniform(1, 351)}``, drawn in the order of ``ids`` (Python's Mersenne Twister)."""
    rng = random.Random(seed)
    return {int(i): rng.uniform(*RANDOM_RANGE_G) for i in ids}


def average_mass(train_ann: pd.DataFrame) -> float:
    """M5's prediction for every recording: the mean ``container mass`` over the training recordings (one label per
    recording, so containers with more recordings weigh more)."""
    return float(train_ann[ANN_MASS].mean())


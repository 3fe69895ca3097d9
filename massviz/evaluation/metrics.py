"""Scoring of container-mass predictions: the CORSMAL challenge score (the paper's Eq. 2) with per-class analysis.

Per annotated recording j with true empty mass m > 0 and prediction m̂:

* ε = |m̂ − m| / m (relative absolute error);
* the recording is *estimated* when it has a prediction m̂ ≥ 0. A recording missing from the predictions, or
  predicted negative (the challenge writes -1 for "not estimated"), is not estimated: it scores 0 and has no ε;
* s = (1/J) Σ_j 1[estimated] · exp(−ε) over **all** J annotated recordings;
* mean ε is over the *estimated* recordings only (as in the paper's Fig. 4); it is NaN when none is estimated.

Predicted recordings that are not in the annotations are ignored and listed in ``ScoreReport.ignored_ids``.
A prediction file that predicts the same recording twice is an error (there is no sound rule for which to keep).

Notebook use::

    from massviz.io.ccm_annotations import read_annotations

    report = score(read_predictions("F1.csv"), read_annotations("test_annotations_fold0.csv"))
    report.score_pct, report.per_class, report.per_container
    score_from_estimates({23: 6.0, 38: 36.0}, read_annotations("Val_annotations.csv"))
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from massviz.errors import DataError
from massviz.io.ccm_annotations import (
    ANN_CONTAINER,
    ANN_ID,
    ANN_MASS,
    MAX_ID,
    check_unique,
    column_values,
    parse_id,
    parse_number,
    read_table,
)

#: Key and value columns of the challenge prediction CSV.
PRED_ID, PRED_MASS = "Configuration ID", "Container mass"
#: The paper's classes, in the order of its tables and figure.
CLASS_ORDER = ("cup", "glass", "box")

ClassOf = Callable[[int], str] | Mapping[int, str]


# ----------------------------------------------------------------------------------------------------------- reading
def read_predictions(path: str | Path) -> pd.DataFrame:
    """Read a CORSMAL challenge prediction CSV: a frame with int ``'Configuration ID'`` and float ``'Container mass'``.

    Only those two columns are read and checked (the file's other task columns are not this project's); a negative
    mass (the challenge's -1) means "not estimated". A header-only file is valid (nothing estimated).
    Raises ``DataError`` (naming file, row and column) for an unreadable or non-CSV file, a missing column, a
    ragged row, a non-numeric or non-finite value, or a recording id that appears twice.
    """
    path = Path(path)
    header, rows = read_table(path, (PRED_ID, PRED_MASS))
    ids = column_values(path, header, rows, PRED_ID, parse_id)
    check_unique(path, rows, PRED_ID, ids)
    masses = column_values(path, header, rows, PRED_MASS, parse_number)
    return pd.DataFrame({PRED_ID: pd.Series(ids, dtype="int64"), PRED_MASS: pd.Series(masses, dtype="float64")})


# ----------------------------------------------------------------------------------------------------------- classes
def default_class_of(container_id: int) -> str:
    """The paper's classes of the CCM training containers: cup 1–3, glass 4–6, box 7–9."""
    if 1 <= container_id <= 9:
        return CLASS_ORDER[(container_id - 1) // 3]
    raise DataError(f"container {container_id} has no class (cup 1–3, glass 4–6, box 7–9); "
                    "give an explicit container→class mapping")


def parse_class_map(spec: str) -> dict[int, str]:
    """Container→class mapping from ``"1=cup,2=cup,..."`` or from a JSON file ``{"1": "cup", ...}``."""
    if spec.strip().endswith(".json") or Path(spec).is_file():
        from massviz.io.untrusted import load_json

        raw = load_json(spec, "class mapping", DataError)
        if not isinstance(raw, dict):
            raise DataError('class mapping must be a JSON object {"1": "cup", ...}', spec)
        pairs = [(str(k), str(v)) for k, v in raw.items()]
    else:
        pairs = [part.partition("=")[::2] for part in spec.split(",") if part.strip()]
    mapping = {}
    for key, name in pairs:
        try:
            container = int(key)
        except ValueError:
            raise DataError(f"class mapping: {key.strip()!r} is not a container id (expected e.g. 1=cup,2=cup)") from None
        if not name.strip():
            raise DataError(f"class mapping: container {container} has no class name (expected e.g. {container}=cup)")
        if not 0 <= container <= MAX_ID:
            raise DataError(f"class mapping: container id {container} must be >= 0 and <= {MAX_ID}")
        from massviz.io.untrusted import text_id

        mapping[container] = text_id(name.strip(), f"class mapping: the class name of container {container}", None)
    if not mapping:
        raise DataError("class mapping is empty (expected e.g. 1=cup,2=cup,4=glass)")
    return mapping


def _class_function(class_of: ClassOf) -> Callable[[int], str]:
    if not isinstance(class_of, Mapping):
        return class_of

    def lookup(container_id: int) -> str:
        if container_id not in class_of:
            raise DataError(f"container {container_id} is not in the class mapping "
                            f"(which maps {', '.join(str(c) for c in sorted(class_of))})")
        return class_of[container_id]

    return lookup


def _class_rank(name: str) -> tuple[int, str]:
    return (CLASS_ORDER.index(name), "") if name in CLASS_ORDER else (len(CLASS_ORDER), name)


# ----------------------------------------------------------------------------------------------------------- scoring
def _summary(frame: pd.DataFrame, by: str) -> pd.DataFrame:
    # one cythonised reduction per column: the same table as ``.agg(recordings=("s", "size"), ...)``, whose named
    # aggregation costs ~10x more (a slider move in the notebook panels re-scores every recording)
    groups = frame.groupby(by)
    return pd.DataFrame({"recordings": groups["s"].size(), "estimated": groups["estimated"].sum(),
                         "score_pct": groups["s"].mean() * 100, "mean_eps": groups["eps"].mean()})


def _records(table: pd.DataFrame) -> list[dict]:
    return json.loads(table.reset_index().to_json(orient="records", double_precision=15))


@dataclass(frozen=True)
class ScoreReport:
    """The result of :func:`score`.

    ``per_recording`` (index ``id``): ``container``, ``class``, ``true_g``, ``pred_g`` (NaN when missing),
    ``estimated``, ``eps`` (NaN when not estimated), ``s`` (the recording's term: exp(−ε), or 0).
    ``per_class`` (index ``class``: cup, glass, box, then others) and ``per_container`` (index ``container``, with
    its ``class``): ``recordings``, ``estimated``, ``score_pct``, ``mean_eps``. Values are kept at full precision;
    :meth:`format` rounds the score to 2 and ε to 3 decimals.
    """

    score: float  # s in [0, 1]
    mean_eps: float  # over estimated recordings; NaN if none
    per_class: pd.DataFrame
    per_container: pd.DataFrame
    per_recording: pd.DataFrame
    ignored_ids: tuple[int, ...]  # predicted but not annotated

    @property
    def score_pct(self) -> float:
        return 100 * self.score

    @property
    def n_recordings(self) -> int:
        return len(self.per_recording)

    @property
    def n_estimated(self) -> int:
        return int(self.per_recording["estimated"].sum())

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN becomes ``None``)."""
        return {
            "score_pct": self.score_pct,
            "mean_eps": None if math.isnan(self.mean_eps) else self.mean_eps,
            "recordings": self.n_recordings,
            "estimated": self.n_estimated,
            "ignored_ids": list(self.ignored_ids),
            "per_class": _records(self.per_class),
            "per_container": _records(self.per_container),
            "per_recording": _records(self.per_recording),
        }

    def format(self) -> str:
        """Terminal text: the overall score in % (2 decimals), then the per-class and per-container tables."""
        eps = "-" if math.isnan(self.mean_eps) else f"{self.mean_eps:.3f}"
        lines = [f"score {self.score_pct:.2f} % over {self.n_recordings} recordings "
                 f"({self.n_estimated} estimated), mean ε {eps}"]
        if self.ignored_ids:
            shown = ", ".join(str(i) for i in self.ignored_ids[:10])
            more = f" … ({len(self.ignored_ids) - 10} more)" if len(self.ignored_ids) > 10 else ""
            lines.append(f"ignored {len(self.ignored_ids)} predicted recordings not in the annotations: {shown}{more}")
        names = {"score_pct": "score %", "mean_eps": "mean ε"}
        formatters = {"score %": "{:.2f}".format, "mean ε": lambda v: "-" if math.isnan(v) else f"{v:.3f}"}
        for title, table in (("per class", self.per_class), ("per container", self.per_container)):
            text = table.reset_index().rename(columns=names).to_string(index=False, formatters=formatters, col_space=8,
                                                                       na_rep="-")  # pandas skips formatters on NaN
            lines += ["", f"{title}:", text]
        return "\n".join(lines)


def relative_error(estimate, true_mass):
    """ε = |m̂ − m| / m per recording (NaN where not estimated, m̂ < 0 or NaN)."""
    est = np.asarray(estimate, dtype=np.float64)
    true_mass = np.asarray(true_mass, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(est >= 0, np.abs(est - true_mass) / true_mass, np.nan)


def recording_scores(estimate, true_mass) -> np.ndarray:
    """The CORSMAL score's per-recording term: 1[estimated]·exp(−ε), i.e. exp(−ε), or 0 when not estimated.
    The one formula of the score: ``score`` and the sweeps both use it."""
    eps = relative_error(estimate, true_mass)
    return np.where(np.isfinite(eps), np.exp(-np.nan_to_num(eps, nan=0.0)), 0.0)


def score(pred: pd.DataFrame, ann: pd.DataFrame, class_of: ClassOf = default_class_of) -> ScoreReport:
    """Score predictions (a :func:`read_predictions` frame) against annotations (a :func:`read_annotations` frame).

    ``class_of`` maps a container id to its class: a function, or an explicit ``{container: class}`` mapping.
    See the module docstring for the rules (missing / negative predictions, mean ε, ignored ids).
    """
    if not pred[PRED_ID].is_unique:
        raise DataError(f"predictions: recording {pred[PRED_ID][pred[PRED_ID].duplicated()].iloc[0]} is predicted "
                        "more than once")
    if not ann[ANN_ID].is_unique:
        raise DataError(f"annotations: recording {ann[ANN_ID][ann[ANN_ID].duplicated()].iloc[0]} appears twice")
    if not (ann[ANN_MASS] > 0).all():
        raise DataError("annotations: every true container mass must be > 0 g")
    lookup = _class_function(class_of)
    frame = pd.DataFrame(
        {
            "container": ann[ANN_CONTAINER].astype("int64").to_numpy(),
            "class": [lookup(int(c)) for c in ann[ANN_CONTAINER]],
            "true_g": ann[ANN_MASS].astype("float64").to_numpy(),
        },
        index=pd.Index(ann[ANN_ID].astype("int64"), name="id"),
    )
    frame["pred_g"] = pred.set_index(PRED_ID)[PRED_MASS].astype("float64").reindex(frame.index)
    frame["estimated"] = frame["pred_g"] >= 0  # NaN (missing) compares False
    frame["eps"] = relative_error(frame["pred_g"].to_numpy(), frame["true_g"].to_numpy())
    frame["s"] = recording_scores(frame["pred_g"].to_numpy(), frame["true_g"].to_numpy())

    per_class = _summary(frame, "class")
    per_class = per_class.loc[sorted(per_class.index, key=_class_rank)]
    per_container = _summary(frame, "container")
    per_container.insert(0, "class", frame.groupby("container")["class"].first())
    ignored = tuple(sorted(set(pred[PRED_ID].astype(int)) - set(frame.index)))
    return ScoreReport(score=float(frame["s"].mean()), mean_eps=float(frame["eps"].mean()), per_class=per_class,
                       per_container=per_container, per_recording=frame, ignored_ids=ignored)


def score_from_estimates(estimates: Mapping[int, float | None], ann: pd.DataFrame,
                         class_of: ClassOf = default_class_of) -> ScoreReport:
    """Score an in-memory ``{recording id: grams}`` dict (``None`` or a negative value: not estimated)."""
    pred = pd.DataFrame({PRED_ID: pd.Series(list(estimates), dtype="int64"),
                         PRED_MASS: pd.Series([np.nan if v is None else v for v in estimates.values()],
                                              dtype="float64")})
    return score(pred, ann, class_of)

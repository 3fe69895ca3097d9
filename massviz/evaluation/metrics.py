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

    report = score(read_predictions("F1.csv"), read_annotations("test_annotations_fold0.csv"))
    report.score_pct, report.per_class, report.per_container
    score_from_estimates({23: 6.0, 38: 36.0}, read_annotations("Val_annotations.csv"))
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from massviz.errors import DataError
from massviz.io.challenge_csv import ANN_CONTAINER, ANN_ID, ANN_MASS, ANN_SIZES  # noqa: F401 - re-exported

#: Key and value columns of the challenge prediction CSV.
PRED_ID, PRED_MASS = "Configuration ID", "Container mass"
#: The paper's classes, in the order of its tables and figure.
CLASS_ORDER = ("cup", "glass", "box")

ClassOf = Callable[[int], str] | Mapping[int, str]


# ----------------------------------------------------------------------------------------------------------- reading
class _Row(NamedTuple):
    number: int  # 1-based data row (the header is not counted)
    line: int  # line in the file
    fields: list[str]


_RAGGED = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


def _read_table(path: Path, required: Sequence[str]) -> tuple[list[str], list[_Row]]:
    """Header and data rows of a CSV file (``pandas.read_csv``, every field as text), checking it is UTF-8 text,
    has the ``required`` columns and a rectangular shape. Blank lines are skipped; rows keep their line numbers."""
    try:
        # header=None: the header is read as row 0, so its length is what every row must have (pandas then names
        # the line of a longer row); shorter rows come back padded with NaN
        frame = pd.read_csv(path, dtype=str, keep_default_na=False, skip_blank_lines=False, encoding="utf-8-sig",
                            header=None, engine="python", on_bad_lines="error")
    except UnicodeDecodeError:
        raise DataError("not a CSV file (not UTF-8 text)", path) from None
    except pd.errors.EmptyDataError:
        raise DataError("empty file: no header row", path) from None
    except pd.errors.ParserError as err:
        m = _RAGGED.search(str(err))
        if m is None:
            raise DataError(f"not a valid CSV file ({str(err).splitlines()[0]})", path) from None
        n_header, line, n_fields = (int(g) for g in m.groups())
        number = _data_row_number(path, line)
        raise DataError(f"row {number} (line {line}): {n_fields} fields, but the header has only {n_header}",
                        path) from None
    except OSError as err:
        raise DataError(f"cannot read the file ({err.strerror})", path) from None
    header = [str(name).strip() for name in frame.iloc[0].fillna("")]
    frame = frame.iloc[1:]
    if not any(header):
        raise DataError("empty file: no header row", path)
    seen = set()
    for name in header:
        if name in seen and name:
            raise DataError(f"header: column '{name[:60]}' appears twice (which one holds the values?)", path)
        seen.add(name)
    for name in required:
        if name not in header:
            raise DataError(f"header: missing column '{name}' (expected a CSV with columns "
                            f"{', '.join(repr(n) for n in required)})", path)
    rows: list[_Row] = []
    missing = frame.isna().to_numpy()
    values = frame.to_numpy()
    for i in range(len(frame)):
        if missing[i].all():
            continue  # a blank line
        row = _Row(len(rows) + 1, i + 2, [str(v) for v, m in zip(values[i], missing[i]) if not m])
        if missing[i].any():
            first = int(missing[i].argmax())
            raise DataError(f"row {row.number} (line {row.line}), column '{header[first]}': missing "
                            f"(the row has {len(row.fields)} fields, the header {len(header)})", path)
        rows.append(row)
    return header, rows


def _data_row_number(path: Path, line: int) -> int:
    """The data-row number (blank lines not counted) of file line ``line``."""
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        lines = f.read().splitlines()[1:line]
    return sum(1 for text in lines if text.strip())


#: largest recording / container id read from a CSV (ids are indices, never near this).
MAX_ID = 2**31 - 1


def _integer(text: str) -> int:
    """A recording or container id: an integer in [0, MAX_ID] (``1e30`` would overflow the int64 columns)."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not an integer" if text else "empty value") from None
    if not value.is_integer():
        raise ValueError(f"{text!r} is not an integer")
    if not 0 <= value <= MAX_ID:
        raise ValueError(f"{text!r} must be >= 0 and <= {MAX_ID}")
    return int(value)


#: largest magnitude of a mass (g) or size (mm, mL) read from a CSV (a container is far below: 1e9 g is 1000 t).
MAX_QUANTITY = 1e9
#: smallest true mass (g): ε divides by it (a 1e-300 g container would make ε overflow).
MIN_TRUE_MASS_G = 1e-3


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number" if text else "empty value") from None
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a finite number")
    if abs(value) > MAX_QUANTITY:
        raise ValueError(f"{text[:40]!r} is beyond +-{MAX_QUANTITY:g}")
    return value


def _positive_mass(text: str) -> float:
    value = _number(text)
    if value <= 0:
        raise ValueError(f"the true mass must be > 0 g (ε divides by it), got {text[:40]}")
    if value < MIN_TRUE_MASS_G:
        raise ValueError(f"the true mass must be >= {MIN_TRUE_MASS_G:g} g (ε divides by it), got {text[:40]}")
    return value


def _column(path: Path, header: list[str], rows: list[_Row], name: str, parse: Callable[[str], Any]) -> list:
    """The values of column ``name`` parsed with ``parse``; a failure names the file, row and column."""
    index = header.index(name)
    values = []
    for row in rows:
        try:
            values.append(parse(row.fields[index].strip()))
        except ValueError as err:
            raise DataError(f"row {row.number} (line {row.line}), column '{name}': {err}", path) from None
    return values


def _check_unique(path: Path, rows: list[_Row], name: str, ids: list[int]) -> None:
    first: dict[int, int] = {}
    for row, value in zip(rows, ids):
        if value in first:
            raise DataError(f"row {row.number} (line {row.line}), column '{name}': recording {value} already "
                            f"appears in row {first[value]} (one row per recording)", path)
        first[value] = row.number


def read_predictions(path: str | Path) -> pd.DataFrame:
    """Read a CORSMAL challenge prediction CSV: a frame with int ``'Configuration ID'`` and float ``'Container mass'``.

    Only those two columns are read and checked (the file's other task columns are not this project's); a negative
    mass (the challenge's -1) means "not estimated". A header-only file is valid (nothing estimated).
    Raises ``DataError`` (naming file, row and column) for an unreadable or non-CSV file, a missing column, a
    ragged row, a non-numeric or non-finite value, or a recording id that appears twice.
    """
    path = Path(path)
    header, rows = _read_table(path, (PRED_ID, PRED_MASS))
    ids = _column(path, header, rows, PRED_ID, _integer)
    _check_unique(path, rows, PRED_ID, ids)
    masses = _column(path, header, rows, PRED_MASS, _number)
    return pd.DataFrame({PRED_ID: pd.Series(ids, dtype="int64"), PRED_MASS: pd.Series(masses, dtype="float64")})


def read_annotations(path: str | Path) -> pd.DataFrame:
    """Read a CCM annotation CSV (``id``, ``container id``, ..., ``container mass``, ...) into a frame.

    ``id`` and ``container id`` are ints in [0, 2^31), ``container mass`` (g) a finite float > 0, the size columns
    (:data:`ANN_SIZES`, mm / mL; -1 = not given) finite floats; every other column is kept, numeric where all its
    values parse as numbers. Raises ``DataError`` (naming file, row and column) for an unreadable or
    non-CSV file, a missing column, a ragged row, a non-numeric value, a mass ≤ 0, a repeated id or no data rows.
    """
    path = Path(path)
    header, rows = _read_table(path, (ANN_ID, ANN_CONTAINER, ANN_MASS))
    if not rows:
        raise DataError("no annotated recordings (only a header)", path)
    parsers = {ANN_ID: _integer, ANN_CONTAINER: _integer, ANN_MASS: _positive_mass,
               **{name: _number for name in ANN_SIZES}}
    data = {}
    for name in header:
        if name in parsers:
            data[name] = _column(path, header, rows, name, parsers[name])
        else:
            text = pd.Series([row.fields[header.index(name)] for row in rows])
            try:
                data[name] = pd.to_numeric(text)
            except ValueError:
                data[name] = text
    _check_unique(path, rows, ANN_ID, data[ANN_ID])
    return pd.DataFrame(data)


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

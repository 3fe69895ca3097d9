"""Reading untrusted data files: every dataset may come from someone else.

The checks every reader makes on what it reads from a file (see docs/untrusted.md), one module per topic:

* :func:`load_calibration_pickle` — CCM calibration pickles through a restricted unpickler that admits only what
  CCM's files hold (numpy arrays, dicts, lists, numbers, strings); anything else is refused before it runs.
* :func:`confined` — a path named *inside* a data file (a mask PNG in a replay JSON, a patch image in an index.csv,
  a ground-truth pattern in meta.json) must stay inside the folder that file lives in.
* :func:`text_id` / :func:`safe_filename` — ids from data files are text: no control characters, bounded length;
  turned into file names only through ``safe_filename``.
* :func:`number` — a numeric field is finite, in range and integral where it must be, checked where it is read.
* :func:`decode_image` — the one reader of an image from a user's folder: its format told by its first bytes, the
  size and channels its header declares bounded (:func:`check_image_size`), before it is decoded.
* :func:`read_bounded` — the one bounded file read: the size checked before reading (a sparse 2 TiB file is
  refused at once), a file growing past the bound while read refused; every reader of an untrusted file uses it.
* :func:`load_json` / :func:`parse_json` — every JSON file from a dataset or a user: size bounded, nesting depth
  bounded before parsing, integers of more than a few hundred digits refused; any failure one error naming the file.
* :func:`load_npz_checked` — .npz arrays: declared sizes and the inflated size bounded before anything is inflated.
* :func:`printable` — text from data files made safe for the terminal (control characters escaped).
"""
from __future__ import annotations

from massviz.io.untrusted.bounded import read_bounded
from massviz.io.untrusted.images import (
                                         MAX_IMAGE_PIXELS,
                                         MAX_IMAGE_SIDE,
                                         check_image_size,
                                         decode_image,
                                         image_format,
                                         image_header_size,
                                         png_header_size,
)
from massviz.io.untrusted.jsonfile import MAX_JSON_BYTES, MAX_JSON_DEPTH, MAX_JSON_INT_DIGITS, load_json, parse_json
from massviz.io.untrusted.npz import MAX_NPZ_BYTES, MAX_NPZ_RATIO, load_npz_checked
from massviz.io.untrusted.paths import confined, frame_path
from massviz.io.untrusted.pickles import MAX_CALIB_BYTES, RestrictedUnpickler, load_calibration_pickle
from massviz.io.untrusted.tables import csv_cell, csv_safe, csv_writer, write_csv
from massviz.io.untrusted.text import MAX_ID_CHARS, printable, safe_filename, text_id
from massviz.io.untrusted.values import MAX_INDEX, json_safe, number

__all__ = ["read_bounded", "MAX_NPZ_RATIO", "MAX_JSON_BYTES", "MAX_JSON_DEPTH", "MAX_JSON_INT_DIGITS", "parse_json",
           "load_json", "MAX_NPZ_BYTES", "load_npz_checked", "MAX_CALIB_BYTES", "MAX_ID_CHARS", "MAX_IMAGE_SIDE",
           "MAX_IMAGE_PIXELS", "MAX_INDEX", "RestrictedUnpickler", "load_calibration_pickle", "confined", "text_id",
           "safe_filename", "number", "check_image_size", "decode_image", "image_format", "image_header_size", "png_header_size", "frame_path",
           "printable", "csv_cell", "csv_safe", "csv_writer", "write_csv", "json_safe"]

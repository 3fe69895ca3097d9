"""Reading untrusted data files: every dataset may come from someone else.

One place for the checks every reader makes on what it reads from a file (see docs/untrusted.md):

* :func:`load_calibration_pickle` — CCM calibration pickles through a restricted unpickler that admits only what
  CCM's files hold (numpy arrays, dicts, lists, numbers, strings); anything else is refused before it runs.
* :func:`confined` — a path named *inside* a data file (a mask PNG in a replay JSON, a patch image in an index.csv,
  a ground-truth pattern in meta.json) must stay inside the folder that file lives in.
* :func:`text_id` / :func:`safe_filename` — ids from data files are text: no control characters, bounded length;
  turned into file names only through ``safe_filename``.
* :func:`number` — a numeric field is finite, in range and integral where it must be, checked where it is read.
* :func:`check_image_size` — the size an image *declares* in its header is bounded before it is decoded.
* :func:`read_bounded` — the one bounded file read: the size checked before reading (a sparse 2 TiB file is
  refused at once), a file growing past the bound while read refused; every reader of an untrusted file uses it.
* :func:`load_json` / :func:`parse_json` — every JSON file from a dataset or a user: size bounded, nesting depth
  bounded before parsing, integers of more than a few hundred digits refused; any failure one error naming the file.
* :func:`load_npz_checked` — .npz arrays: declared sizes and the inflated size bounded before anything is inflated.
* :func:`printable` — text from data files made safe for the terminal (control characters escaped).
"""
from __future__ import annotations

import io
import math
import numbers
import os
import pickle
import re
import unicodedata
from pathlib import Path

import numpy as np

from massviz.errors import DataError, MassvizError

#: largest calibration pickle read (CCM's are ~4 KB).
MAX_CALIB_BYTES = 1 << 20
#: largest id (recording id, config id) taken from a data file, in characters.
MAX_ID_CHARS = 200
#: largest image side and pixel count massviz decodes (any RGB-D camera frame is far below).
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 26  # 67 Mpixel
#: largest integer a file may give for a frame index or a pixel coordinate.
MAX_INDEX = 2**31 - 1


# ------------------------------------------------------------------------------------------------- bounded reads
def read_bounded(path: str | Path, limit: int, what: str, error=DataError, *, hint: str = "",
                 with_stats: bool = False):
    """The bytes of the untrusted file ``path``, at most ``limit``: the size is checked from the open file before
    anything is read (a sparse 2 TiB file is refused at once) and at most ``limit + 1`` bytes are read (a file that
    grows past the bound while read is refused too). ``error`` naming ``path`` for any failure, in one line: missing
    or unreadable (``cannot read WHAT (reason)``), a directory, too big (``hint``: added to the bound, e.g. what such
    files usually weigh). The one bounded read of massviz: frame files, JSON, calibration pickles.

    ``with_stats``: (bytes, ``os.stat_result`` of the open file before and after it was read): the caller can
    tell a file that changed while it was read (the bytes may be a mix of two versions)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            before = os.fstat(fh.fileno())
            if before.st_size > limit:
                raise error(f"{what} is {before.st_size} bytes (at most {limit}{'; ' + hint if hint else ''}); not "
                            "read", path)
            data = fh.read(limit + 1)
            after = os.fstat(fh.fileno()) if with_stats else None
    except IsADirectoryError:
        raise error(f"{what} is a directory, not a file", path) from None
    except OSError as err:
        raise error(f"cannot read {what} ({err.strerror or err})", path) from None
    if len(data) > limit:
        raise error(f"{what} is larger than {limit} bytes; not read", path)
    return (data, before, after) if with_stats else data


# ------------------------------------------------------------------------------------------------------- pickles
class _NdarrayRef:
    """What ``numpy.ndarray`` resolves to: accepted only as ``_reconstruct``'s first argument, never called."""

    def __repr__(self) -> str:
        return "numpy.ndarray"


_NDARRAY = _NdarrayRef()


def _check_dtype(dt) -> np.dtype:
    if not isinstance(dt, np.dtype) or dt.hasobject or dt.kind not in "biufc":
        raise pickle.UnpicklingError(f"array of dtype {dt} (only numeric arrays are admitted)")
    return dt


def _reconstruct(cls, shape, dtype_code):
    from numpy._core.multiarray import _reconstruct as real

    if cls is not _NDARRAY:
        raise pickle.UnpicklingError("_reconstruct of something other than numpy.ndarray")
    if not (isinstance(shape, tuple) and all(isinstance(s, int) and 0 <= s <= MAX_CALIB_BYTES for s in shape)
            and math.prod(shape) <= MAX_CALIB_BYTES):
        raise pickle.UnpicklingError(f"array shape {shape!r}")
    return real(np.ndarray, shape, dtype_code)


def _dtype(spec, align=False, copy=True):
    if not isinstance(spec, str):
        raise pickle.UnpicklingError(f"dtype {spec!r}")
    return _check_dtype(np.dtype(spec, bool(align), bool(copy)))


def _encode(text, encoding="latin1"):
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("_codecs.encode other than of latin1 text")
    return text.encode("latin1")


def _frombuffer(buf, dtype, shape, order):
    dt = _check_dtype(dtype)
    data = bytes(buf)
    if not isinstance(shape, tuple) or math.prod(shape) * dt.itemsize != len(data) or order not in ("C", "F"):
        raise pickle.UnpicklingError("array buffer does not match its shape")
    return np.frombuffer(data, dtype=dt).reshape(shape, order=order).copy()


def _scalar(dtype, data=None):
    from numpy._core.multiarray import scalar as real

    dt = _check_dtype(dtype)
    if not isinstance(data, bytes) or len(data) != dt.itemsize:
        raise pickle.UnpicklingError("numpy scalar of the wrong size")
    return real(dt, data)


#: (module, name) -> what it resolves to. Exactly the globals CCM calibration pickles use (protocol 0, written by
#: Python 2 numpy: _reconstruct, ndarray, dtype), the names numpy 2 and Python 3 use when such a file is re-saved
#: (numpy._core..., _codecs.encode for protocol 2/3 bytes, _frombuffer for protocol 5) and numpy scalars.
_ALLOWED = {
    **{(m, "_reconstruct"): _reconstruct for m in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(m, "scalar"): _scalar for m in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(m, "_frombuffer"): _frombuffer for m in ("numpy.core.numeric", "numpy._core.numeric")},
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _dtype,
    ("_codecs", "encode"): _encode,
}


class RestrictedUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` that resolves only the globals of :data:`_ALLOWED` (numpy arrays of numbers); every
    other global (``os.system``, ``builtins.eval``, any class) raises ``UnpicklingError`` before anything is
    called. Plain containers and numbers (dict, list, tuple, str, bytes, int, float, bool, None) need no global."""

    def find_class(self, module: str, name: str):
        try:
            return _ALLOWED[module, name]
        except KeyError:
            raise pickle.UnpicklingError(f"refused to load {module}.{name} (a calibration file holds only numpy "
                                         "arrays, dicts, lists and numbers)") from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("refused a persistent id (not a plain calibration file)")


def load_calibration_pickle(path: str | Path, error=MassvizError):
    """Unpickle a CCM calibration file with :class:`RestrictedUnpickler` (latin1 strings, as CCM's Python 2
    files need). Any refusal or malformation raises ``error`` naming ``path``; nothing in the file is executed."""
    path = Path(path)
    data = read_bounded(path, MAX_CALIB_BYTES, "calibration pickle", error, hint="CCM's are a few KB")
    try:
        return RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()
    except pickle.UnpicklingError as err:
        raise error(f"not a CCM calibration pickle: {err}", path) from None
    except Exception as err:  # noqa: BLE001 - any other failure is a malformed file; nothing ran
        raise error(f"not a CCM calibration pickle ({type(err).__name__}: {_first_line(err)})", path) from None


# -------------------------------------------------------------------------------------------------------- paths
def confined(base: str | Path, name, source: str | Path, what: str, error=DataError) -> Path:
    """``base / name`` for a relative path ``name`` read from the data file ``source``; ``error`` (naming
    ``source``) when it is not a non-empty relative path or leads outside ``base`` (``..``). The check is on the
    path as written: symlinks inside ``base`` are the file system's arrangement (frames linked to another disk) and
    are followed."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise error(f"{what} must be a relative file path, got {_short(name)}", source)
    if _control(name):
        raise error(f"{what} {name!r} contains control characters", source)
    rel = Path(name)
    if rel.is_absolute() or rel.drive or name.startswith(("/", "\\")):
        raise error(f"{what} {name!r} is an absolute path; paths in a data file must be relative to its folder "
                    f"({base})", source)
    norm = Path(os.path.normpath(rel))
    if norm.parts[:1] == ("..",) or str(norm) == ".":
        raise error(f"{what} {name!r} leads outside {base}; paths in a data file must stay inside its folder",
                    source)
    return Path(base) / norm


def frame_path(pattern, base: str | Path, frame: int, source, what: str, error=DataError) -> Path:
    """The file of ``frame`` for a per-frame path pattern read from a data file (e.g. meta.json's
    ``"gt/{frame:06d}.png"``): the only field allowed is ``{frame}`` or ``{frame:0Nd}`` (no attribute or index
    access, no huge widths), and the path must stay inside ``base`` (:func:`confined`)."""
    import string

    if not isinstance(pattern, str) or not pattern:
        raise error(f"{what} must be a path pattern such as \"gt/{{frame:06d}}.png\", got {_short(pattern)}", source)
    try:
        fields = [(f, spec, conv) for _, f, spec, conv in string.Formatter().parse(pattern) if f is not None]
    except ValueError as e:
        raise error(f"{what} {_short(pattern)} is not a format pattern ({e})", source) from None
    for name, spec, conv in fields:
        if name != "frame" or conv or not re.fullmatch(r"(0?[1-9]?d)?", spec or ""):
            raise error(f"{what} {_short(pattern)}: the only field allowed is {{frame}} or {{frame:0Nd}} "
                        "(N one digit)", source)
    return confined(base, pattern.format(frame=int(frame)), source, what, error)


# ---------------------------------------------------------------------------------------------------------- ids
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def _control(text: str) -> bool:
    return bool(_CONTROL.search(text))


def text_id(value, what: str, source, error=DataError) -> str:
    """An id read from a data file as text: a string (or an integer), 1..MAX_ID_CHARS characters, no control or
    bidirectional-override characters (they would rewrite the terminal line or the CSV row it is printed in)."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise error(f"{what} must be a string, got {type(value).__name__} {_short(value)}", source)
    text = str(value)
    if not text.strip():
        raise error(f"{what} is empty", source)
    if len(text) > MAX_ID_CHARS:
        raise error(f"{what} is {len(text)} characters long (at most {MAX_ID_CHARS})", source)
    if _control(text):
        raise error(f"{what} {text!r} contains control characters", source)
    return text


def printable(text, keep: str = "") -> str:
    """``text`` safe to print on a terminal: every control, C1 or bidirectional-override character except those in
    ``keep`` (e.g. ``"\\n\\r\\t"`` for whole progress output) is written as its escape (``\\x1b``, ``\\u202e``), so
    a name from a data file cannot move the cursor, retitle the window or clear the screen."""
    text = str(text)

    def escape(m: re.Match) -> str:
        c = m.group()
        if c in keep:
            return c
        return f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}"

    return _CONTROL.sub(escape, text)


#: first characters that make a spreadsheet read a CSV cell as a formula (OWASP "CSV injection").
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value):
    """``value`` as a CSV cell a spreadsheet will not run: text starting with ``= + - @`` (or tab/CR), that is not a
    number, gets a leading ``'``. Numbers and other text are returned unchanged (matching uses the raw id; only
    what is written is neutralised)."""
    if not isinstance(value, str) or not value.startswith(_FORMULA_START):
        return value
    try:
        float(value)
        return value  # "-1", "+2.5": a number, not a formula
    except ValueError:
        return "'" + value


def csv_safe(frame):
    """A copy of the pandas ``frame`` with :func:`csv_cell` applied to every text cell (and header): the one
    guard every CSV massviz writes goes through (``frame.to_csv``) or, for ``csv.writer`` rows, ``csv_cell``."""
    out = frame.copy()
    for col in out.columns:
        if out[col].dtype == object or str(out[col].dtype).startswith("string"):
            out[col] = out[col].map(csv_cell)
    out.columns = [csv_cell(c) for c in out.columns]
    return out


def json_safe(value):
    """``value`` (dicts, lists, numbers) with every non-finite float replaced by None: JSON has no NaN/Infinity
    and massviz writes none (``json.dumps(..., allow_nan=False)`` then cannot fail)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.floating):
        return json_safe(float(value))
    return value


def safe_filename(text: str, max_chars: int = 100) -> str:
    """``text`` as one file-name component: letters, digits and ``_.-`` kept, any run of anything else (``/``,
    ``\\``, ``..``, spaces, ``:``) replaced by one ``_``, leading/trailing ``._`` stripped; never empty, never
    ``.``/``..`` or hidden (``../../x/y`` -> ``x_y``)."""
    text = unicodedata.normalize("NFKC", str(text))
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", text)
    safe = re.sub(r"_{2,}", "_", re.sub(r"\.{2,}", "_", safe)).strip("._")[:max_chars]
    return safe or "_"


# ------------------------------------------------------------------------------------------------------ numbers
def number(value, what: str, source=None, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, integral: bool = False, error=DataError):
    """``value`` (from a file or an option) as a float — an int when ``integral`` — checked: a real number (not a
    bool, not text), finite, integral when asked, within [lo, hi] (``lo_open``: > lo). ``error`` names ``source``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{what} must be a number, got {_short(value)}", source)
    try:
        f = float(value)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise error(f"{what} must be a finite number, got {_short(value)}", source)
    if integral:
        if isinstance(value, numbers.Integral):
            out = int(value)
        elif f.is_integer():
            out = int(f)
        else:
            raise error(f"{what} must be an integer, got {_short(value)}", source)
    else:
        out = f
    if lo is not None and (out <= lo if lo_open else out < lo):
        raise error(f"{what} must be {'>' if lo_open else '>='} {lo:g}, got {_short(value)}", source)
    if hi is not None and out > hi:
        raise error(f"{what} must be <= {hi:g}, got {_short(value)}", source)
    return out


def _short(value, n: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= n else text[:n] + "..."


def _first_line(err: BaseException) -> str:
    lines = str(err).splitlines()
    return lines[0][:200] if lines else type(err).__name__


# ------------------------------------------------------------------------------------------------------- images
def png_header_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) of the PNG whose first 24 bytes are ``head`` (its IHDR); None when it is not a PNG's start."""
    import struct

    if len(head) >= 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return struct.unpack(">II", head[16:24])
    return None


def image_header_size(path: str | Path, data: bytes | None = None) -> tuple[int, int] | None:
    """(width, height) an image file declares in its header, without decoding it; None when unknown. ``data``: the
    file's bytes when the caller has read them already (the file is then not opened again)."""
    import io
    import warnings

    if data is None:
        try:
            with open(path, "rb") as fh:
                head = fh.read(24)
        except OSError:
            return None
    else:
        head = data[:24]
    if (size := png_header_size(head)) is not None:
        return size
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path if data is None else io.BytesIO(data)) as img:
                return img.size
    except Image.DecompressionBombError:  # PIL's own bound (> 179 Mpixel) is above ours
        return (MAX_IMAGE_PIXELS, MAX_IMAGE_PIXELS)
    except Exception:  # noqa: BLE001 - not an image PIL knows: the decoder reports it
        return None


def check_image_size(path: str | Path, error=MassvizError, what: str = "image", data: bytes | None = None) -> None:
    """Refuse (``error`` naming ``path``) an image whose header declares more than MAX_IMAGE_SIDE per side or
    MAX_IMAGE_PIXELS pixels, before it is decoded (a small file may declare gigabytes of pixels). ``data``: the
    file's bytes when already read."""
    size = image_header_size(path, data)
    if size is None:
        return
    w, h = size
    if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise error(f"{what} declares {w}x{h} pixels (at most {MAX_IMAGE_SIDE} per side and {MAX_IMAGE_PIXELS} "
                    "pixels); not decoded", path)


# --------------------------------------------------------------------------------------------------------- JSON
#: largest JSON file read from a dataset or a user (meta.json, intrinsics.json, ranges, class maps, exclusions).
MAX_JSON_BYTES = 16 << 20
#: deepest nesting of arrays/objects a JSON file may have (massviz's own files nest at most 4 deep).
MAX_JSON_DEPTH = 64
#: most digits of an integer in a JSON file (Python refuses > 4300 with a ValueError; no field needs > 20).
MAX_JSON_INT_DIGITS = 100


def _json_depth(text: str) -> int:
    """The deepest nesting of ``[``/``{`` in ``text``, brackets inside strings ignored; stops early once it
    exceeds MAX_JSON_DEPTH (the parser is never handed a document that would exhaust its recursion)."""
    depth = deepest = 0
    # strings (with their escapes) are removed first, so their brackets do not count
    for m in re.finditer(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', text):
        tok = m.group()
        if tok in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > MAX_JSON_DEPTH:
                    break
        elif tok in "]}":
            depth -= 1
    return deepest


def _json_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_JSON_INT_DIGITS:
        raise ValueError(f"an integer of {digits} digits (at most {MAX_JSON_INT_DIGITS})")
    return int(text)


def parse_json(text: str | bytes, source, what: str = "JSON file", error=DataError):
    """``text`` (from ``source``) parsed as JSON, untrusted: at most MAX_JSON_BYTES, nesting at most
    MAX_JSON_DEPTH deep (checked before parsing), integers of at most MAX_JSON_INT_DIGITS digits. ``error`` naming
    ``source`` otherwise — never ``RecursionError`` or Python's int-digits ``ValueError``."""
    import json

    if len(text) > MAX_JSON_BYTES:
        raise error(f"{what} is {len(text)} bytes; at most {MAX_JSON_BYTES} are read", source)
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as err:
            raise error(f"cannot read {what}: not JSON (not UTF-8 text at byte {err.start})", source) from None
    if text.count("[") + text.count("{") > MAX_JSON_DEPTH and _json_depth(text) > MAX_JSON_DEPTH:
        raise error(f"cannot read {what}: it nests arrays/objects more than {MAX_JSON_DEPTH} deep", source)
    try:
        return json.loads(text, parse_int=_json_int)
    except json.JSONDecodeError as err:
        raise error(f"cannot read {what}: not valid JSON ({err.msg} at line {err.lineno} column {err.colno})",
                    source) from None
    except (ValueError, RecursionError, MemoryError) as err:
        raise error(f"cannot read {what}: not valid JSON ({_first_line(err)})", source) from None


def load_json(path: str | Path, what: str = "JSON file", error=DataError, max_bytes: int = MAX_JSON_BYTES):
    """The JSON document of the untrusted file ``path`` (see :func:`parse_json`); the size is checked before the
    file is read. ``error`` naming ``path`` for any failure (missing, unreadable, too big, malformed)."""
    path = Path(path)
    return parse_json(read_bounded(path, max_bytes, what, error), path, what, error)


# ---------------------------------------------------------------------------------------------------------- npz
#: most bytes of arrays an .npz (trace, replay, cache entry) may inflate to, all members together.
MAX_NPZ_BYTES = 1 << 29  # 512 MiB: a trace of an hour-long recording is far below
#: a member inflating to more than MAX_NPZ_SMALL bytes must compress at most this well (massviz's own traces: < 30:1;
#: a deflate bomb: ~1000:1).
MAX_NPZ_RATIO = 200
MAX_NPZ_SMALL = 1 << 20


def load_npz_checked(path: str | Path, max_bytes: int = MAX_NPZ_BYTES) -> dict[str, np.ndarray]:
    """The arrays of an .npz file, never unpickling and never allocating what the file only *declares*: the
    inflated sizes the zip directory declares must total at most ``max_bytes`` and each large member must compress
    at most MAX_NPZ_RATIO:1 (a deflate bomb is refused before anything is inflated); each member's .npy header
    (shape x item size) must fit in the member's size; members are read with bounded reads (never more than the
    declared size). ``ValueError`` (or ``zipfile.BadZipFile``/``OSError``) otherwise."""
    import zipfile

    total = 0
    with zipfile.ZipFile(path) as z:
        infos = z.infolist()
        names = [i.filename for i in infos]
        if len(set(names)) != len(names):
            raise ValueError("it holds two members of the same name")
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if not info.filename.endswith(".npy"):
                raise ValueError(f"member {name!r} is not a .npy array")
            total += info.file_size
            if total > max_bytes:
                raise ValueError(f"its arrays inflate to more than {max_bytes} bytes")
            if info.file_size > MAX_NPZ_SMALL and info.file_size > MAX_NPZ_RATIO * max(info.compress_size, 1):
                raise ValueError(f"array {name} inflates {info.compress_size} bytes to {info.file_size} (more than "
                                 f"{MAX_NPZ_RATIO}:1; a compression bomb?)")
            with z.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read(fh)
            if dtype.hasobject:
                raise ValueError(f"array {name} holds Python objects")
            declared = math.prod(shape) * dtype.itemsize
            if declared > info.file_size:
                raise ValueError(f"array {name} declares {declared} bytes but holds {info.file_size}")
        out = {}
        for info in infos:
            with z.open(info) as fh:  # ZipExtFile stops at the declared size and checks the CRC
                out[info.filename[:-4]] = np.lib.format.read_array(fh, allow_pickle=False)
        return out


__all__ = ["read_bounded", "MAX_NPZ_RATIO", "MAX_JSON_BYTES", "MAX_JSON_DEPTH", "MAX_JSON_INT_DIGITS", "parse_json", "load_json", "MAX_NPZ_BYTES", "load_npz_checked", "MAX_CALIB_BYTES", "MAX_ID_CHARS", "MAX_IMAGE_SIDE", "MAX_IMAGE_PIXELS", "MAX_INDEX",
           "RestrictedUnpickler", "load_calibration_pickle", "confined", "text_id", "safe_filename", "number",
           "check_image_size", "image_header_size", "png_header_size", "frame_path", "printable", "csv_cell",
           "csv_safe", "json_safe"]

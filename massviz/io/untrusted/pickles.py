"""CCM calibration pickles through a restricted unpickler: only numpy arrays of numbers, dicts, lists, numbers and
strings; any other global is refused before it runs."""
from __future__ import annotations

import io
import math
import pickle
from pathlib import Path

import numpy as np

from massviz.errors import MassvizError
from massviz.io.untrusted.bounded import read_bounded
from massviz.io.untrusted.text import _first_line

#: largest calibration pickle read (CCM's are ~4 KB).
MAX_CALIB_BYTES = 1 << 20


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

"""One bounded reader: ``massviz.io.untrusted.read_bounded`` is the only hand-written bounded file read;
frame files (``formats.common.read_bytes``), JSON (``untrusted.load_json``) and calibration pickles go through it,
with one wording for each failure, the size checked before anything is read."""
from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from massviz.errors import DataError, RecordingError
from massviz.io.formats.common import MAX_FRAME_FILE_BYTES, read_bytes
from massviz.io.untrusted import MAX_CALIB_BYTES, MAX_JSON_BYTES, load_calibration_pickle, load_json, read_bounded

ROOT = Path(__file__).resolve().parents[1]

READERS = {  # name: (read(path), error class, what, limit)
    "frame": (lambda p: read_bytes(p, "depth image"), RecordingError, "depth image", MAX_FRAME_FILE_BYTES),
    "json": (lambda p: load_json(p, "meta.json"), DataError, "meta.json", MAX_JSON_BYTES),
    "pickle": (lambda p: load_calibration_pickle(p, RecordingError), RecordingError, "calibration pickle",
               MAX_CALIB_BYTES),
}


@pytest.mark.parametrize("reader", READERS)
def test_every_reader_refuses_a_sparse_huge_file_from_its_size(reader, tmp_path):
    read, error, what, limit = READERS[reader]
    big = tmp_path / "big"
    with open(big, "wb") as fh:
        fh.truncate(2 << 40)  # 2 TiB, sparse: reading it would take hours
    t0 = time.perf_counter()
    with pytest.raises(error, match=rf"^{big}: {what} is {2 << 40} bytes \(at most {limit}(; [^)]*)?\); not read$"):
        read(big)
    assert time.perf_counter() - t0 < 2


@pytest.mark.parametrize("reader", READERS)
def test_every_reader_says_a_directory_or_a_missing_file_in_one_line(reader, tmp_path):
    read, error, what, _ = READERS[reader]
    with pytest.raises(error, match=rf"^{tmp_path}: {what} is a directory, not a file$"):
        read(tmp_path)
    with pytest.raises(error, match=rf"^{tmp_path / 'nope'}: cannot read {what} \(No such file or directory\)$"):
        read(tmp_path / "nope")


def test_a_file_growing_past_the_bound_while_read_is_refused(tmp_path, monkeypatch):
    path = tmp_path / "f"
    path.write_bytes(b"x" * 100)
    real = os.fstat
    monkeypatch.setattr(os, "fstat", lambda fd: os.stat_result((*real(fd)[:6], 0, 0, 0, 0)))  # st_size 0
    with pytest.raises(DataError, match=r"f: thing is larger than 10 bytes; not read$"):
        read_bounded(path, 10, "thing")


def test_a_frame_file_changed_while_read_gives_no_digest(tmp_path, monkeypatch):
    path = tmp_path / "000000.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    digests: dict = {}
    read_bytes(path, "depth image", digests=digests)
    assert digests[os.path.abspath(path)][1]  # unchanged: (identity, digest)
    real, calls = os.fstat, []

    def moving(fd):  # the second fstat (after the read) sees another modification time
        calls.append(fd)
        st = real(fd)
        return st if len(calls) % 2 else os.stat_result((*st[:8], st[8] + 1, st[9]))

    monkeypatch.setattr(os, "fstat", moving)
    read_bytes(path, "depth image", digests=digests)
    assert digests[os.path.abspath(path)] is None


def test_no_other_hand_written_bounded_read():
    """A size check on an open file (``os.fstat``) or a read of ``limit + 1`` bytes is ``read_bounded``'s alone."""
    pattern = re.compile(r"os\.fstat\(|\.read\([^)]*\+ ?1\)|\.st_size > ")
    offenders = []
    for p in (ROOT / "massviz").rglob("*.py"):
        for n, line in enumerate(p.read_text().splitlines(), 1):
            if pattern.search(line):
                offenders.append(f"{p.relative_to(ROOT)}:{n}")
    assert offenders and all(o.startswith("massviz/io/untrusted/bounded.py:") for o in offenders), offenders

"""``massviz.io.untrusted.printable``, the one escaping of text from data files and devices for the terminal and CSV
cells: every message that names such text (an error line, a RealSense device's name or serial) goes through it."""
from __future__ import annotations

import pytest

from massviz.io.untrusted import MAX_ID_CHARS, printable


@pytest.mark.parametrize("raw, shown", [
    ("cam\n\x1b]0owned\x07\x1b[2J", "cam\\n\\x1b]0owned\\x07\\x1b[2J"),  # newline, OSC title, bell, clear screen
    ("12\r34\x1b[1A", "12\\r34\\x1b[1A"),  # carriage return, cursor up
    ("a\tb\x00c\x7fd", "a\\tb\\x00c\\x7fd"),  # tab, NUL, DEL
    ("\x9b31m", "\\x9b31m"),  # C1 CSI
    ("cup\u202egnp.exe", "cup\\u202egnp.exe"),  # right-to-left override
    ("a\u061cb\u200bc\ufeffd", "a\\u061cb\\u200bc\\ufeffd"),  # Arabic letter mark, zero-width space, BOM
    ("line\u2028para\u2029", "line\\u2028para\\u2029"),  # line and paragraph separators
    ("tag\U000e0001", "tag\\U000e0001"),  # a format character beyond the BMP
    ("private\ue000", "private\\ue000"),
])
def test_printable_escapes_as_python_writes_a_string(raw, shown):
    assert printable(raw) == shown


def test_printable_keeps_ordinary_text_and_what_it_is_told_to_keep():
    text = "Tasse à café 漢字 █▏ 'quoted' \\x1b"  # accents, CJK, progress-bar blocks, a literal backslash
    assert printable(text) == text
    assert printable("line\nnext\r\tend\x1b", keep="\n\r\t") == "line\nnext\r\tend\\x1b"
    assert printable(12.5) == "12.5"


def test_printable_bounds_the_text_before_escaping():
    assert printable("x" * 300, max_chars=MAX_ID_CHARS) == "x" * MAX_ID_CHARS
    assert printable("\x1b" * 300, max_chars=2) == "\\x1b\\x1b"
    assert printable("x" * 300) == "x" * 300  # no bound unless asked


def test_an_error_line_shows_the_escapes():
    from massviz.cli import error_line

    assert error_line("estimate", "cam\n\x1b[2J: not found") == "massviz estimate: error: cam\\n\\x1b[2J: not found"


class _Device:
    def __init__(self, serial, name="Intel RealSense D435"):
        self.info = {"serial": serial, "name": name}

    def supports(self, info):
        return True

    def get_info(self, info):
        return self.info[info]


def _fake_realsense(monkeypatch, devices):
    from massviz.io.formats import realsense_live

    class FakeRS:
        class camera_info:
            serial_number, name = "serial", "name"

        class context:
            def query_devices(self):
                return devices

    monkeypatch.setattr(realsense_live, "import_rs", lambda: FakeRS)
    return realsense_live


def test_realsense_names_and_serials_are_escaped_and_bounded(monkeypatch):
    from massviz.errors import MassvizError

    long_serial = "9" * 300
    realsense = _fake_realsense(monkeypatch, [_Device("1\x1b[2J", name="cam\n\x07"), _Device(long_serial)])
    assert realsense.list_cameras() == [{"name": "cam\\n\\x07", "serial": "1\\x1b[2J"},
                                        {"name": "Intel RealSense D435", "serial": "9" * MAX_ID_CHARS}]
    with pytest.raises(MassvizError) as err:
        realsense.open_camera("3\r3")
    assert str(err.value) == f"no RealSense camera with serial 3\\r3 (connected: 1\\x1b[2J, {'9' * MAX_ID_CHARS})"

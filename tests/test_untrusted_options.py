"""Float options at the edge: ``nan``, ``inf``, ``-inf`` and ``-0`` for every float option of every command.

The cases are generated from the command line's own parsers (``massviz.cli.build_parser``): every option whose
value is a float. Each value is parsed and checked as the command line does before any work
(``massviz.commands._common.check_float_options``, through ``massviz.io.untrusted.number``): a non-finite value is
one ``MassvizError`` naming the option, ``-0`` is read as +0.0 or refused as out of range, never kept negative.
"""
from __future__ import annotations

import argparse
import math

import pytest

from massviz import cli
from massviz.commands._common import check_float_options
from massviz.errors import MassvizError

VALUES = ("nan", "inf", "-inf", "-0", "1e999", "NaN")


def float_options() -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(command, option, the command's parser) for every option of every command that takes a float."""
    parser = cli.build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    out = []
    for command, p in sub.choices.items():
        for a in p._actions:
            if a.option_strings and a.type is float:
                out.append((command, max(a.option_strings, key=len), p))
    return out


OPTIONS = float_options()


def test_the_commands_have_float_options():
    """The generated cases below are not empty (the parsers are walked as they are built)."""
    assert {(c, o) for c, o, _ in OPTIONS} >= {("live", "--duration"), ("train", "--lr"), ("compare", "--iou"),
                                                ("render", "--yaw"), ("estimate", "--threshold")}


def parse(p: argparse.ArgumentParser, option: str, value: str) -> argparse.Namespace:
    """The command's own parse of ``option=value`` (its positional arguments filled with placeholders)."""
    positional = [a for a in p._actions if not a.option_strings and a.nargs != 0]
    argv = [f"{option}={value}"]
    for a in p._actions:  # required options: a placeholder each
        if a.option_strings and a.required and max(a.option_strings, key=len) != option:
            argv += [max(a.option_strings, key=len), "x"]
    argv += ["x" for a in positional if a.nargs not in ("?", "*")]
    return p.parse_args(argv)


@pytest.mark.parametrize("value", VALUES)
@pytest.mark.parametrize("command,option", [(c, o) for c, o, _ in OPTIONS])
def test_every_float_option_is_finite_and_in_range_at_the_edge(command, option, value):
    (p,) = [p for c, o, p in OPTIONS if (c, o) == (command, option)]
    args = parse(p, option, value)
    dest = option.lstrip("-").replace("-", "_")
    assert isinstance(getattr(args, dest), float)
    try:
        check_float_options(args)
    except MassvizError as err:
        line = str(err)
        assert "\n" not in line and line.startswith(option + " "), line
        assert math.isfinite(float(value)) or "finite" in line, line
        return
    checked = getattr(args, dest)
    assert math.isfinite(checked), f"{command} {option}={value} was accepted as {checked}"
    assert math.copysign(1.0, checked) == 1.0, f"{command} {option}={value} was kept as {checked}"


@pytest.mark.parametrize("argv,line", [
    (["live", "--duration", "nan"], "--duration must be a finite number in (0, 1e+09], got nan"),
    (["live", "--duration=-inf"], "--duration must be a finite number in (0, 1e+09], got -inf"),
    (["compare", "x", "--iou", "0"], "--iou must be > 0, got 0.0"),
])
def test_the_command_line_says_it_in_one_line_before_any_work(argv, line, capsys):
    """Through ``massviz.cli.main``: exit 2 and one line, before a file is opened (``x`` does not exist)."""
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"massviz {argv[0]}: error: {line}"]

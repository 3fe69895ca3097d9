"""The package states the versions it supports as ranges; the tested pins live in constraints.txt, which set-up (and
so CI) installs with."""
from __future__ import annotations

import re
import tomllib

from packaging.requirements import Requirement
from packaging.version import Version

from support import ROOT


def requirements() -> dict[str, Requirement]:
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    return {r.name: r for r in map(Requirement, deps)}


def pins() -> dict[str, Version]:
    found = re.findall(r"^([A-Za-z0-9_.-]+)==(\S+)", (ROOT / "constraints.txt").read_text(), flags=re.M)
    return {name: Version(v) for name, v in found}


def test_torch_is_a_range_that_admits_the_tested_pin_and_older_releases():
    reqs, pinned = requirements(), pins()
    for name in ("torch", "torchvision"):
        spec = reqs[name].specifier
        assert not any(s.operator in ("==", "===") for s in spec), f"{name} is pinned in pyproject.toml: {spec}"
        tested = pinned[name]
        assert tested in spec, f"constraints.txt's {name}=={tested} is outside pyproject.toml's {spec}"
        older = Version(f"{tested.major}.{tested.minor - 1}.0")
        next_major = Version(f"{tested.major + 1}.0.0")
        assert older in spec and next_major not in spec, f"{name}: {spec} is not 'oldest supported up to the next major'"


def test_setup_installs_the_package_with_the_tested_pins():
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    install = next(ln for ln in setup.splitlines() if "pip install" in ln and '-e ".[test,notebooks]"' in ln)
    assert "-c constraints.txt" in install
    assert "bash scripts/setup.sh test" in (ROOT / ".ci" / "run").read_text().replace("exec ", "")

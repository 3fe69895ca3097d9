#!/usr/bin/env bash
# massviz set-up on a fresh machine, then one job:
#   bash scripts/setup.sh demo   install everything, run `massviz log` on a bundled sample -> out/cup_handover.rrd
#   bash scripts/setup.sh test   install everything, run the test suite (what CI runs)
# Installs Debian's libraries Open3D needs (libusb-1.0-0; offscreen rendering: libvulkan1 mesa-vulkan-drivers
# libegl1 libgl1; the test job also Chromium for the browser tests), creates .venv with Python >= 3.11 and installs
# massviz with the torch/torchvision versions it is tested with (constraints.txt).
# MASSVIZ_TORCH=cpu: torch/torchvision from PyTorch's CPU-only wheel index (no NVIDIA libraries, no triton: about
# 4.6 GB less: 3.7 GB instead of 8.3 GB, README); default (unset): the wheels pip resolves from PyPI, with CUDA, what CI uses.
set -euo pipefail
cd "$(dirname "$0")/.."
job="${1:-}"
case "$job" in demo|test) ;; *) echo "usage: [MASSVIZ_TORCH=cpu] bash scripts/setup.sh demo|test" >&2; exit 2 ;; esac
torch_wheels="${MASSVIZ_TORCH:-}"
case "$torch_wheels" in ""|cpu) ;;
  *) echo "setup: MASSVIZ_TORCH must be 'cpu' or unset (PyPI's CUDA wheels), got '$torch_wheels'" >&2; exit 2 ;;
esac
cpu_index="https://download.pytorch.org/whl/cpu"

apt_pkgs=(libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1)
# the browser tests (tests/test_browser.py) drive Debian's Chromium through playwright (no browser download)
if [ "$job" = test ]; then apt_pkgs+=(chromium); fi
missing=()
for p in "${apt_pkgs[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if ((${#missing[@]})); then
  sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  echo "setup: installing Debian packages: ${missing[*]}" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

py="${PYTHON:-python3}"
"$py" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "massviz needs Python >= 3.11")'
[ -x .venv/bin/python ] || "$py" -m venv .venv
# the tested torch/torchvision pins (constraints.txt; pyproject.toml states the supported ranges)
pins=($(grep -oE '^(torch|torchvision)==[^ #]+' constraints.txt))
if [ "$torch_wheels" = cpu ]; then
  echo "setup: installing ${pins[*]} CPU-only wheels from $cpu_index" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check --index-url "$cpu_index" "${pins[@]}"
  # pip may still have taken a CUDA wheel from another index of its configuration (e.g. a local mirror)
  cuda=$(.venv/bin/python -c 'import torch; print(torch.version.cuda or "")')
  if [ -n "$cuda" ]; then
    echo "setup: warning: MASSVIZ_TORCH=cpu, but the torch installed is built for CUDA $cuda ($cpu_index was not" \
      "reachable or pip's configuration preferred another index); massviz still works, on the CPU" >&2
  fi
fi
echo "setup: installing massviz into .venv with the tested versions of constraints.txt (${pins[*]})" >&2
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[test,notebooks]" 2>&1 \
  | { grep -v -e "^WARNING: Location" -e "is ignored: it is neither" || true; }

# setup: JupyterLab without the build check. dash (an Open3D dependency) ships a source extension that JupyterLab
# would announce as "Build Recommended" on every start; its Build button needs yarn and the network, and the notebooks
# need no build. The venv's own page config turns the check off for every `jupyter lab` of this venv.
.venv/bin/python -c 'import json, pathlib, sys
p = pathlib.Path(sys.prefix, "etc", "jupyter", "labconfig", "page_config.json")
p.parent.mkdir(parents=True, exist_ok=True)
c = json.loads(p.read_text()) if p.is_file() else {}
c.update(buildCheck=False, buildAvailable=False)
p.write_text(json.dumps(c, indent=2) + "\n")'

# Weights of the mass CNN: a reference copy beside the repo, when there is one, goes into the user cache
# (sha256-checked), where every later massviz command finds it offline; else massviz downloads the published
# checkpoint once into that cache on first use. $MASSVIZ_WEIGHTS or --weights still override it.
# setup: cache the reference weights
ref="../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch"
if [ -f "$ref" ]; then
  .venv/bin/python -c 'import sys; from massviz.io.weights import install_checkpoint as i; print("setup: mass CNN weights cached at", i(sys.argv[1]), file=sys.stderr)' "$ref"
fi

if [ "$job" = demo ]; then
  mkdir -p out
  .venv/bin/massviz log data_samples/cup_handover --detector depth --rrd out/cup_handover.rrd
  echo "setup: open it with: .venv/bin/massviz view out/cup_handover.rrd (a browser page; with a display: .venv/bin/rerun out/cup_handover.rrd)" >&2
else
  # lint first (pyproject.toml [tool.ruff]: pyflakes, import sorting, bugbear): a finding fails the job
  .venv/bin/ruff check .
  set +e
  # two workers (pytest-xdist; 2 cores in CI), a test file whole on one: its module fixtures (the Ray cluster, a
  # JupyterLab, the executed notebooks, dozens of CLI runs) are made once; files are handed out heaviest first
  # (tests/conftest.py: heaviest_files_first), not in xdist's most-tests-first order
  .venv/bin/python -m pytest -q -p no:cacheprovider -n 2 --dist loadfile --no-loadscope-reorder
  rc=$?
  set -e
  if [ "$rc" = 5 ]; then echo "setup: pytest collected no tests: the suite is missing" >&2; exit 1; fi
  exit "$rc"
fi

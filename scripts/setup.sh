#!/usr/bin/env bash
# massviz set-up on a fresh machine, then one job:
#   bash scripts/setup.sh demo   install everything, run `massviz log` on a bundled sample -> out/cup_handover.rrd
#   bash scripts/setup.sh test   install everything, run the test suite (what CI runs)
# Installs Debian's libraries Open3D needs (libusb-1.0-0; offscreen rendering: libvulkan1 mesa-vulkan-drivers
# libegl1 libgl1; the test job also Chromium for the browser tests), creates .venv with Python >= 3.11 and installs
# massviz with its pinned torch/torchvision.
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
# the torch/torchvision pins of pyproject.toml
pins=($(grep -oE '"(torch|torchvision)==[^"]+"' pyproject.toml | tr -d '"'))
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
echo "setup: installing massviz into .venv (${pins[*]} pinned in pyproject.toml)" >&2
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test,notebooks]" 2>&1 \
  | { grep -v -e "^WARNING: Location" -e "is ignored: it is neither" || true; }

# Weights of the mass CNN: $MASSVIZ_WEIGHTS, else the reference copy beside the repo when there is one,
# else massviz downloads the published checkpoint once (sha256-checked) into the user cache.
ref="../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch"
if [ -z "${MASSVIZ_WEIGHTS:-}" ] && [ -f "$ref" ]; then export MASSVIZ_WEIGHTS="$PWD/$ref"; fi

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

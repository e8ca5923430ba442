#!/usr/bin/env bash
# Sets up everything vkray needs on a fresh Debian/Ubuntu machine (idempotent): system packages
# (Vulkan loader, lavapipe, glslc, validation layers), a virtual environment in .venv with the
# Python packages of requirements-dev.txt, and vkray built into it (editable: Python changes are
# live, a Rust change needs this script again). Needs Rust's cargo on PATH. Prints a line a step.
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '[setup %s] %s\n' "$1" "$2"; }

step 1/4 "system packages (Vulkan loader, Mesa lavapipe >= 24.1, glslc, validation layers): scripts/setup-system.sh"
bash scripts/setup-system.sh
command -v cargo >/dev/null || { echo "cargo not found: install a Rust toolchain (https://rustup.rs)" >&2; exit 1; }

python=${PYTHON:-python3}
step 2/4 "Python environment .venv and requirements-dev.txt (first time: about 2 minutes)"
[ -x .venv/bin/python ] || "$python" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -m pip install -q -r requirements-dev.txt

if [ -f target/release/.vkray-built ]; then
  step 3/4 "building vkray's Rust core (cargo, release; only what changed)"
else
  step 3/4 "building vkray's Rust core (cargo, release; the first build takes 5-8 minutes on 2 cores)"
fi
# pip's editable install of this project alone (its dependencies came from requirements-dev.txt):
# the build runs maturin, as installed, into target/ as `maturin develop --release` would.
started=$(date +%s)
python -m pip install -q --no-build-isolation --no-deps -e .
mkdir -p target/release && touch target/release/.vkray-built

step 4/4 "vkray $(python -c 'import vkray.data; from importlib.metadata import version; print(version("vkray"))') ready in .venv ($(( $(date +%s) - started )) s to build)"

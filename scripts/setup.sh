#!/usr/bin/env bash
# Sets up everything vkray needs on a fresh Debian/Ubuntu machine (idempotent): system packages
# (Vulkan loader, lavapipe, glslc, validation layers), a virtual environment in .venv with the
# Python packages, and vkray built into it. Needs Rust's cargo on PATH.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup-system.sh
command -v cargo >/dev/null || { echo "cargo not found: install a Rust toolchain (https://rustup.rs)" >&2; exit 1; }

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -m pip install -q -r requirements-dev.txt
maturin develop --release -q

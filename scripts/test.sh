#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs every check and test: formatting and lints of the Rust core
# (cargo fmt, clippy) and of the Python layer (ruff, mypy, stubtest against the built module),
# the core's unit tests, then the Python suite under the Khronos validation layer (required: a
# missing layer fails the run).
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
. .venv/bin/activate
cargo fmt --check
cargo clippy --quiet --features python --all-targets -- -D warnings
ruff check python tests benchmarks examples
mypy
python -m mypy.stubtest vkray
cargo test --quiet
VKRAY_REQUIRE_VALIDATION=1 python -m pytest tests "$@"

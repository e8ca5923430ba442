#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs every test: the Rust core's unit tests, then the Python suite
# under the Khronos validation layer (required: a missing layer fails the run).
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
. .venv/bin/activate
cargo test --quiet
VKRAY_REQUIRE_VALIDATION=1 python -m pytest tests "$@"

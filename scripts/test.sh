#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs every check and test: formatting and lints of the Rust core
# (cargo fmt, clippy) and of the Python layer (ruff, mypy, stubtest against the built module),
# the core's unit tests, then the Python suite under the Khronos validation layer (required: a
# missing layer fails the run). Each stage ends with a line saying how it went and how long it
# took. pytest prints the reason of every skip (-rs) and its 15 slowest tests, and a test that
# skips for want of anything scripts/setup.sh installs fails instead (VKRAY_STRICT_SKIPS=1; only
# hardware this machine lacks, such as a CUDA GPU, may be skipped). Arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
. .venv/bin/activate

stage() {
  local name=$1 started=$SECONDS
  shift
  printf '[test] %s: %s\n' "$name" "$*"
  if "$@"; then
    printf '[test] %s: ok (%d s)\n' "$name" $((SECONDS - started))
  else
    local status=$?
    printf '[test] %s: FAILED with exit code %d (%d s)\n' "$name" "$status" $((SECONDS - started))
    exit "$status"
  fi
}

stage "rust format" cargo fmt --check
stage "rust lints" cargo clippy --quiet --features python --all-targets -- -D warnings
stage "python lints" ruff check python tests benchmarks examples
stage "python types" mypy
stage "stubs" python -m mypy.stubtest vkray
stage "rust unit tests" cargo test --quiet
export VKRAY_REQUIRE_VALIDATION=1 VKRAY_STRICT_SKIPS=${VKRAY_STRICT_SKIPS:-1}
stage "python tests" python -m pytest tests -rs --durations=15 "$@"

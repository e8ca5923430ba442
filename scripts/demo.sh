#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the demo: a depth image of a mesh rendered with vkray, timed
# against Embree on the same rays. Arguments go to examples/render_depth.py (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
. .venv/bin/activate
python examples/render_depth.py "$@"

#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the demo: a depth image of the Stanford bunny (shipped with
# vkray) rendered with vkray, timed against Embree on the same rays. The picture goes to the folder
# the command is run from (depth.png). Arguments go to examples/render_depth.py (try --help).
set -euo pipefail
caller=$PWD
root=$(cd "$(dirname "$0")/.." && pwd)

(cd "$root" && bash scripts/setup.sh)
. "$root/.venv/bin/activate"
echo "[demo] examples/render_depth.py $*"
cd "$caller"
python "$root/examples/render_depth.py" "$@"

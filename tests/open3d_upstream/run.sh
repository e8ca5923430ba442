#!/usr/bin/env bash
# Open3D's own tests of its RaycastingScene (python/test/t/geometry/test_raycasting_scene.py in
# Open3D's sources) with vkray.open3d.RaycastingScene in its place (swap_scene.py here, copied as
# their conftest.py), and open3d_test.py here in place of Open3D's test helper.
#
# Open3D's wheels (open3d, open3d-cpu on PyPI) do not ship its tests and Open3D publishes no
# source distribution on PyPI, so the file is given: SOURCE is the test file itself or a checkout
# of Open3D's sources, e.g. of the installed version's tag:
#   git clone --depth 1 -b v0.19.0 https://github.com/isl-org/Open3D /tmp/open3d-src
# The file these tests were first run with (Open3D's main at commit 00572f0aeb36, 17,597 bytes)
# has the SHA-256 printed below as "read"; another version prints another.
#
# Usage: tests/open3d_upstream/run.sh SOURCE [pytest arguments...]
# VKRAY_OPEN3D_SWAP=0 runs the same tests on Open3D's own class.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
source=${1:?"usage: run.sh SOURCE [pytest arguments...]: the test file, or a checkout of Open3D sources"}
shift
if [ -d "$source" ]; then
  source="$source/python/test/t/geometry/test_raycasting_scene.py"
fi
if [ ! -f "$source" ]; then
  echo "Open3D's test file is not at $source" >&2
  exit 66
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/t/geometry"
cp "$source" "$work/t/geometry/test_raycasting_scene.py"
cp "$here/open3d_test.py" "$work/"
cp "$here/swap_scene.py" "$work/t/geometry/conftest.py"
echo "read $(sha256sum "$source" | cut -d' ' -f1)  $source"
cd "$work/t/geometry"
python -m pytest -p no:cacheprovider -rs "$@" test_raycasting_scene.py

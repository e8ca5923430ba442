#!/usr/bin/env bash
# trimesh's own ray tests (tests/test_ray.py and tests/test_ray_upstream.py of the installed
# trimesh version's sdist, fetched from PyPI) with vkray.trimesh.RayMeshIntersector in place of
# both of trimesh's engines (swap_engines.py here, copied as its conftest.py), and generic.py here
# in place of trimesh's test helper.
# Usage: tests/trimesh_upstream/run.sh [work folder] [pytest arguments...]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
work=${1:-$(mktemp -d)}
shift || true
version=$(python -c "import trimesh; print(trimesh.__version__)")
if [ ! -f "$work/trimesh-$version.tar.gz" ]; then
  if ! python -m pip download -q --no-binary :all: --no-deps "trimesh==$version" -d "$work"; then
    echo "could not fetch trimesh's sdist from PyPI" >&2
    exit 75
  fi
fi
tar -xzf "$work/trimesh-$version.tar.gz" -C "$work" "trimesh-$version/tests/test_ray.py" "trimesh-$version/tests/test_ray_upstream.py"
tests="$work/trimesh-$version/tests"
cp "$here/swap_engines.py" "$tests/conftest.py"
cp "$here/generic.py" "$tests/"
cd "$tests"
python -m pytest -p no:cacheprovider -rs "$@" test_ray.py test_ray_upstream.py

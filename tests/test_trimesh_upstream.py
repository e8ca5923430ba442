"""trimesh's own ray tests (its tests/test_ray.py and tests/test_ray_upstream.py, from the sdist
of the installed trimesh on PyPI) run with vkray.trimesh.RayMeshIntersector in place of both of
trimesh's engines: tests/trimesh_upstream/run.sh. Tests needing model files that the sdist lacks
are skipped there, by name (4 of 30). Every other one must pass.
"""

import os
import pathlib
import re
import subprocess
import sys
import tempfile

import pytest

pytest.importorskip("trimesh")

RUN = pathlib.Path(__file__).parent / "trimesh_upstream" / "run.sh"


def test_trimeshs_ray_tests_pass_on_vkray():
    work = pathlib.Path(tempfile.gettempdir()) / "vkray-trimesh-sdist"
    work.mkdir(exist_ok=True)
    env = dict(os.environ, PATH=f"{pathlib.Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    result = subprocess.run(["bash", str(RUN), str(work), "-q", "-rfs"], capture_output=True, text=True, env=env,
                            timeout=600)
    out = result.stdout + result.stderr
    if result.returncode == 75:  # run.sh: the sdist could not be fetched (no network)
        if os.environ.get("VKRAY_REQUIRE_TRIMESH_TESTS") == "1":
            pytest.fail(f"could not fetch trimesh's tests:\n{out[-3000:]}")
        pytest.skip("trimesh's sdist could not be fetched from PyPI")
    passed = re.search(r"(\d+) passed", out)
    assert result.returncode == 0, out[-5000:]
    assert passed and int(passed.group(1)) >= 26, out[-3000:]

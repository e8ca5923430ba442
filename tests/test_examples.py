"""Every example runs with its defaults (sizes made small) from a folder outside the checkout,
writes its outputs there and nowhere else: the tracked files stay as they were."""

import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

CASES = {
    "render_depth.py": (["--size", "32"], ["depth.png"]),
    "shadows.py": (["--size", "32"], ["shadows.png"]),
    "sdf_slice.py": (["--size", "24"], ["sdf_slice.png"]),
    "accuracy_vs_time.py": (["--rays", "2000", "--grid", "5"], ["accuracy.md", "accuracy.png"]),
}


def _tracked_changes() -> str:
    """`git status` of the tracked files under examples/ and docs/ (what the examples once wrote)."""
    run = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "docs", "examples"],
                         cwd=ROOT, capture_output=True, text=True)
    return run.stdout if run.returncode == 0 else ""


@pytest.mark.parametrize("script", sorted(CASES))
def test_example_runs_anywhere_and_writes_only_where_it_runs(tmp_path, script):
    args, outputs = CASES[script]
    before = _tracked_changes()
    run = subprocess.run([sys.executable, str(ROOT / "examples" / script), *args], cwd=tmp_path,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    for name in outputs:
        assert (tmp_path / name).stat().st_size > 0, name
    assert _tracked_changes() == before

import shutil
import subprocess

import pytest

from vkray import _core


@pytest.mark.skipif(shutil.which("spirv-val") is None, reason="spirv-val (Debian: spirv-tools) is not installed")
@pytest.mark.parametrize("name", sorted(_core.spirv_modules()))
def test_embedded_spirv_validates(name, tmp_path):
    module = tmp_path / f"{name}.spv"
    module.write_bytes(_core.spirv_modules()[name])
    result = subprocess.run(
        ["spirv-val", "--target-env", "vulkan1.2", str(module)], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_shader_source_is_embedded():
    import pathlib

    sources = {p.name for p in (pathlib.Path(__file__).parents[1] / "shaders").iterdir() if p.suffix != ".glsl"}
    assert sources == set(_core.spirv_modules())

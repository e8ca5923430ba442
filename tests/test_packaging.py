"""What the wheel and the sdist carry: the committed SPIR-V (spirv/, used by builds without glslc)
is that of the shaders, the sdist carries it, and the extension module links only glibc's
libraries. The manylinux_2_28 wheel itself is checked by `bash scripts/build-wheel.sh --quick`."""

import re
import subprocess
import sys
import tarfile
from pathlib import Path
from typing import Dict, List, NamedTuple, Set, Tuple

import pytest

from vkray import _core

ROOT = Path(__file__).resolve().parents[1]
REFRESH = "VKRAY_UPDATE_SPIRV=1 cargo check"


class Entry(NamedTuple):
    source: int
    module: int


def fnv1a(data: bytes) -> int:
    """FNV-1a, 64 bits, as build.rs computes it."""
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def shader_text(name: str) -> str:
    return (ROOT / "shaders" / name).read_bytes().decode("utf-8").replace("\r\n", "\n")


def source_hash(name: str) -> Tuple[int, List[str]]:
    """build.rs's hash of a shader with the headers it includes (transitively): each file's name,
    its length in bytes and its text. Written twice (here and in build.rs, which has no Python);
    the manifest check below fails at once where the two disagree."""
    headers: Set[str] = set()
    pending = [shader_text(name)]
    while pending:
        for include in re.findall(r'^\s*#\s*include\s*"([^"]*)"', pending.pop(), re.MULTILINE):
            if include not in headers:
                headers.add(include)
                pending.append(shader_text(include))
    data = b""
    for file in [name, *sorted(headers)]:
        text = shader_text(file).encode()
        data += f"{file}\0{len(text)}\0".encode() + text
    return fnv1a(data), sorted(headers)


def manifest() -> Tuple[Dict[str, Entry], str]:
    """spirv/manifest.txt's entries by shader, and its header (which names the glslc it used)."""
    text = (ROOT / "spirv" / "manifest.txt").read_text()
    entries = {}
    for line in text.splitlines():
        if line.strip() and not line.startswith("#"):
            name, source, module = line.split()[:3]
            entries[name] = Entry(int(source, 16), int(module, 16))
    return entries, text.splitlines()[0]


def shader_names() -> List[str]:
    return sorted(p.name for p in (ROOT / "shaders").iterdir() if p.is_file() and p.suffix != ".glsl")


def test_committed_spirv_is_that_of_the_shaders():
    entries, header = manifest()
    embedded = _core.spirv_modules()
    problems = []
    if set(entries) != set(shader_names()):
        problems.append(f"spirv/manifest.txt lists {sorted(entries)}, shaders/ holds {shader_names()}")
    for name in shader_names():
        committed = ROOT / "spirv" / f"{name}.spv"
        if name not in entries or not committed.is_file():
            problems.append(f"shaders/{name} has no committed module")
            continue
        if entries[name].source != source_hash(name)[0]:
            problems.append(f"shaders/{name} (or a header it includes) changed since spirv/{name}.spv was compiled")
        module = committed.read_bytes()
        if fnv1a(module) != entries[name].module:
            problems.append(f"spirv/{name}.spv is not the module spirv/manifest.txt records")
        if embedded.get(name) != module:
            # The installed module was compiled by glslc (or taken from spirv/ where glslc was
            # absent, when they agree): a difference is a shader changed since the last refresh.
            problems.append(f"the module built into vkray here differs from spirv/{name}.spv")
    assert not problems, "\n".join(
        problems
        + [
            f"(vkray is built from the current shaders?) Refresh spirv/ with `{REFRESH}` and commit it;",
            f"spirv/manifest.txt says: {header}",
        ]
    )


def test_shader_hashes_follow_includes():
    # A change to a header counts for the shaders that include it, through other headers too
    # (trace_ray_query.comp includes common.glsl, which includes records.glsl; point_order.comp
    # points.glsl, which includes widen.glsl), and for no other.
    assert "records.glsl" in source_hash("trace_ray_query.comp")[1]
    assert source_hash("point_order.comp")[1] == ["points.glsl", "records.glsl", "widen.glsl"]
    assert "exact.glsl" not in source_hash("trace_ray_query.comp")[1]


def test_sdist_carries_the_spirv(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "maturin", "sdist", "--out", str(tmp_path)],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    (sdist,) = tmp_path.glob("vkray-*.tar.gz")
    with tarfile.open(sdist) as tar:
        members = {Path(*Path(m).parts[1:]).as_posix() for m in tar.getnames()}
    wanted = {"spirv/manifest.txt", "build.rs"}
    wanted |= {f"spirv/{n}.spv" for n in shader_names()} | {f"shaders/{n}" for n in shader_names()}
    assert wanted <= members, sorted(wanted - members)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ELF extension modules are Linux's")
def test_extension_module_links_only_glibc():
    # The Vulkan loader (ash "loaded") and CUDA (cudarc's dynamic loading) are opened at run time:
    # the module must not need them, nor libstdc++, to import where they are missing. libgcc_s
    # comes with a build linked by the system's cc (every manylinux policy allows it); the wheel
    # that scripts/build-wheel.sh links with zig does without it.
    allowed = {"libc.so.6", "libm.so.6", "libdl.so.2", "libpthread.so.0", "librt.so.1", "ld-linux-x86-64.so.2"}
    allowed.add("libgcc_s.so.1")
    dynamic = subprocess.run(["readelf", "-d", _core.__file__], check=True, capture_output=True, text=True).stdout
    needed = set(re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", dynamic))
    assert "libc.so.6" in needed, dynamic
    assert needed <= allowed, sorted(needed - allowed)

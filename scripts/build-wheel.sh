#!/usr/bin/env bash
# Builds vkray's Linux wheel for manylinux_2_28 (glibc >= 2.28: RHEL 8, Debian 10, Ubuntu 20.04 and
# later) on any Linux machine, and checks it: linked by zig against glibc 2.28's symbols
# (`maturin build --zig`, ziglang from PyPI: the machine's own glibc may be newer), audited by
# `auditwheel show` (the policy it names must be <= manylinux_2_28, and the extension module may
# need only glibc's libraries: the Vulkan loader and CUDA are loaded at run time), then installed
# into a fresh virtual environment where it must import and cast a ray.
#
#   bash scripts/build-wheel.sh          the release wheel, into dist/
#   bash scripts/build-wheel.sh --quick  CI's check: the same link against glibc 2.28 from an
#                                        unoptimized build without debug information (half the
#                                        build time; it calls a superset of the release build's
#                                        C functions), checked and then discarded
#
# Uses .venv's Python (PYTHON= names another), installing maturin, ziglang and auditwheel into it
# where missing. Respects CARGO_TARGET_DIR.
set -euo pipefail
cd "$(dirname "$0")/.."

quick=0
case "${1:-}" in
    "") ;;
    --quick) quick=1 ;;
    *) echo "usage: bash scripts/build-wheel.sh [--quick]" >&2; exit 2 ;;
esac

policy=manylinux_2_28
python=${PYTHON:-.venv/bin/python}
[ -x "$python" ] || python=python3
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
step() { echo "build-wheel: $*"; }
started=$SECONDS

missing=()
"$python" -c "import maturin" 2>/dev/null || missing+=("maturin>=1.5,<2")
"$python" -c "import ziglang" 2>/dev/null || missing+=(ziglang)
"$python" -c "import auditwheel" 2>/dev/null || missing+=(auditwheel)
if [ ${#missing[@]} -gt 0 ]; then
    step "installing ${missing[*]} into $("$python" -c 'import sys; print(sys.prefix)')"
    "$python" -m pip install -q "${missing[@]}"
fi
# maturin finds zig (`python -m ziglang`) and the interpreter through PATH.
bin=$(dirname "$("$python" -c 'import sys; print(sys.executable)')")
export PATH="$bin:$PATH"

# The CPU engine's Embree 4 (and the TBB it runs on) travels in the wheel, loaded at run time from
# vkray/_embree: the manylinux build embreex's wheel carries (glibc >= 2.27, RPATH $ORIGIN), taken
# from the installed embreex or downloaded.
embree_dir=python/vkray/_embree
rm -rf "$embree_dir" && mkdir -p "$embree_dir"
embree_libs=$("$python" -c 'import importlib.util, os; s = importlib.util.find_spec("embreex"); print(os.path.join(os.path.dirname(os.path.dirname(s.origin)), "embreex.libs") if s else "")')
if [ -z "$embree_libs" ] || [ ! -d "$embree_libs" ]; then
    step "downloading embreex's wheel for its Embree build"
    "$python" -m pip download -q --no-deps --only-binary=:all: embreex==4.4.0.post1 -d "$work/embreex"
    (cd "$work/embreex" && "$python" -m zipfile -e embreex-*.whl unpacked)
    embree_libs="$work/embreex/unpacked/embreex.libs"
fi
cp "$embree_libs"/libembree4*.so* "$embree_libs"/libtbb*.so* "$embree_dir"/
step "Embree for the CPU engine: $(ls "$embree_dir" | tr '\n' ' ')"

if [ $quick = 1 ]; then
    step "building an unoptimized wheel linked against glibc 2.28 (about 1-2 min on 2 cores from scratch)"
    CARGO_PROFILE_DEV_DEBUG=0 maturin build --profile dev --zig --compatibility $policy --out "$work/wheels"
else
    step "building the release wheel linked against glibc 2.28 (about 3-4 min on 2 cores from scratch)"
    maturin build --release --zig --compatibility $policy --out "$work/wheels"
fi
wheel=$(ls "$work"/wheels/vkray-*.whl)

step "auditwheel show $(basename "$wheel")"
auditwheel show "$wheel" | tee "$work/audit.txt"
# The narrowest policy auditwheel names, e.g. "manylinux_2_28_x86_64" (or a legacy alias).
tag=$(tr '\n' ' ' < "$work/audit.txt" | grep -oE 'platform tag: *"[^"]+"' | head -1 | grep -oE '"[^"]+"' | tr -d '"')
"$python" - "$tag" <<'EOF'
import re
import sys

tag = sys.argv[1]
aliases = {"manylinux1": (2, 5), "manylinux2010": (2, 12), "manylinux2014": (2, 17)}
m = re.fullmatch(r"manylinux_(\d+)_(\d+)_\w+", tag)
glibc = (int(m[1]), int(m[2])) if m else aliases.get(tag.split("_")[0])
if glibc is None or glibc > (2, 28):
    sys.exit(f"build-wheel: auditwheel names {tag or 'no manylinux policy'}: the wheel is not manylinux_2_28")
print(f"build-wheel: policy {tag} (glibc >= {glibc[0]}.{glibc[1]})")
EOF
# Only glibc's libraries: a link-time dependency on libvulkan, libcuda or libstdc++ would make the
# wheel fail to import where those are missing (auditwheel would accept libstdc++).
"$python" - "$wheel" <<'EOF'
import io
import sys
import zipfile

from elftools.elf.dynamic import DynamicSection
from elftools.elf.elffile import ELFFile
glibc = {"libc.so.6", "libm.so.6", "libdl.so.2", "libpthread.so.0", "librt.so.1", "ld-linux-x86-64.so.2"}
with zipfile.ZipFile(sys.argv[1]) as wheel:
    # The extension module (Embree's copy in vkray/_embree is manylinux2014's own build).
    modules = [n for n in wheel.namelist() if n.endswith(".so") and "/_embree/" not in n]
    assert modules, "build-wheel: no extension module in the wheel"
    for name in modules:
        with wheel.open(name) as f:
            elf = ELFFile(io.BytesIO(f.read()))
        needed = {t.needed for s in elf.iter_sections() if isinstance(s, DynamicSection)
                  for t in s.iter_tags() if t.entry.d_tag == "DT_NEEDED"}
        if needed - glibc:
            sys.exit(f"build-wheel: {name} needs {sorted(needed - glibc)} besides glibc")
        print(f"build-wheel: {name} needs {', '.join(sorted(needed))}")
EOF

step "installing it into a fresh virtual environment"
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$wheel"
(cd "$work" && "$work/venv/bin/python" - <<'EOF'
import sys

import numpy as np
import vkray

assert vkray.__file__.startswith(sys.prefix), vkray.__file__
devices = vkray.devices()
print("build-wheel: vkray.devices() =", devices)
if any(d.engine == "vulkan" for d in devices):
    device = vkray.Device([d.index for d in devices if d.engine == "vulkan"][0])
    mesh = device.mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]], np.int32))
    hits = device.scene([mesh]).intersect(np.array([[0.25, 0.25, 2]], np.float32), np.array([[0, 0, -1]], np.float32))
    assert hits.hit[0] and abs(hits.t[0] - 2) < 1e-6, (hits.hit, hits.t)
    print("build-wheel: a ray cast on", device, "hits at t =", hits.t[0])
cpu = vkray.Device("cpu")
mesh = cpu.mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]], np.int32))
hits = cpu.scene([mesh]).intersect(np.array([[0.25, 0.25, 2]], np.float32), np.array([[0, 0, -1]], np.float32))
assert hits.hit[0] and abs(hits.t[0] - 2) < 1e-6, (hits.hit, hits.t)
print("build-wheel: a ray cast on the CPU engine,", cpu.name, "from the wheel's own Embree, hits at t =", hits.t[0])
EOF
)

if [ $quick = 0 ]; then
    mkdir -p dist
    mv "$wheel" dist/
    step "dist/$(basename "$wheel") ($((SECONDS - started)) s)"
else
    step "the wheel passes ($((SECONDS - started)) s)"
fi

"""The public surface: exported names and option types, the core as the one judge of option
strings, offset_origins' precision keyword, and how the suite treats a missing meshes folder."""

import os
import pathlib
import shutil
import subprocess
import sys
from typing import get_args

import numpy as np
import pytest

import vkray
from test_precision import tiers

V = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float64)
F = np.array([[0, 1, 2]], np.int64)
O = np.array([[0.2, 0.2, 0.0]])  # noqa: E741
D = np.array([[0.0, 0.0, 1.0]])


def test_everything_exported_exists():
    for name in vkray.__all__:
        assert hasattr(vkray, name), name
    assert issubclass(vkray.ForkedDeviceError, vkray.VkrayError)
    for error in (vkray.NoDeviceError, vkray.UnsupportedError, vkray.VulkanError, vkray.ValidationError):
        assert issubclass(error, vkray.VkrayError) and issubclass(error, RuntimeError)
    assert vkray.PRECISIONS == _choices(vkray.Precision) == ("fast", "refined", "exact", "reference")


def _choices(option):
    """The strings of an option type: a Literal, a Union of Literals, Optional of either."""
    return tuple(a for arg in get_args(option) for a in (get_args(arg) or (arg,)) if isinstance(a, str))


def _each_option(device):
    """(argument name, its type, a call that passes the value to the core) for every option string."""
    mesh = device.mesh(V, F)
    scene = device.scene(mesh)
    return [
        ("precision", vkray.Precision, lambda value: scene.intersect(O, D, precision=value)),
        ("precision", vkray.Precision, lambda value: scene.occluded(O, D, precision=value)),
        ("cull", vkray.Cull, lambda value: scene.intersect(O, D, cull=value)),
        ("cull", vkray.Cull, lambda value: scene.occluded(O, D, cull=value)),
        ("build", vkray.Build, lambda value: device.mesh(V, F, build=value)),
        ("build", vkray.Build, lambda value: device.meshes([(V, F)], build=value)),
        ("build", vkray.Build, lambda value: device.mesh_from_parts([(V, F)], build=value)),
        ("build", vkray.Build, lambda value: device.spheres(V, 0.1, build=value)),
        ("build", vkray.Build, lambda value: device.scene(mesh, build=value)),
        ("vertex_format", vkray.VertexFormat, lambda value: device.mesh(V, F, vertex_format=value)),
        ("vertex_format", vkray.VertexFormat, lambda value: device.meshes([(V, F)], vertex_format=value)),
        ("vertex_format", vkray.VertexFormat, lambda value: device.mesh_from_parts([(V, F)], vertex_format=value)),
        ("backend", vkray.Backend, lambda value: vkray.Device(device.info.index, value)),
    ]


def test_option_types_match_what_the_core_accepts(any_device):
    """Every value of each Literal type is accepted (where the device has it); a value outside it
    is refused once, by the core, with a ValueError naming the argument and every choice."""
    backends = {"ray_query": any_device.info.ray_query, "pipeline": any_device.info.ray_tracing_pipeline}
    for name, option, call in _each_option(any_device):
        for value in _choices(option):
            if name == "backend" and not backends[value]:
                continue
            if name == "vertex_format" and value not in any_device.limits["vertex_formats"]:
                continue
            if name == "precision" and value == "exact" and "exact" not in tiers(any_device):
                continue
            call(value)
        expected = rf"{name} must be .*" + ".*".join(f"'{value}'" for value in _choices(option)) + ".*nonsense"
        with pytest.raises(ValueError, match=expected):
            call("nonsense")
        with pytest.raises(TypeError, match=name):
            call(1)


def test_offset_origins_is_far_enough_for_float32_traversal(device):
    """A triangle soup 1e4 from the origin: float64 hit points from an f64 tier, offset for the
    "fast" tier (the default), then shadow rays towards a light traced in the "fast" tier: none
    may hit the triangle it leaves. The f32 traversal's surface lies some f32 ulps of the scene
    away from the f64 one, so points offset by the float64 rule (precision="exact": a few hundred
    f64 ulps) start on either side of it, and about half of them hit their own triangle."""
    rng = np.random.default_rng(71)
    n = 2000
    corners = rng.uniform(0, 10, (n, 1, 3)) + rng.normal(scale=0.3, size=(n, 3, 3))
    v = corners.reshape(-1, 3) + 1e4
    f = np.arange(3 * n).reshape(n, 3)
    scene = device.scene(device.mesh(v, f))
    origins = np.column_stack([rng.uniform(-2, 12, (20000, 2)), np.full(20000, 15.0)]) + 1e4
    directions = np.column_stack([rng.uniform(-0.3, 0.3, (20000, 2)), -np.ones(20000)])
    f64_tier = "exact" if "exact" in tiers(device) else "reference"
    first = scene.intersect(origins, directions, precision=f64_tier, outputs=["prim_id", "normal", "position"])
    hit = first.hit
    assert hit.sum() > 5000 and first.position.dtype == np.float64
    to_light = np.array([5.0, 5.0, 30.0]) + 1e4 - first.position[hit]

    def self_hits(precision, tier):
        keywords = {} if precision is None else {"precision": precision}  # None: the default
        start = vkray.offset_origins(first.position[hit], first.normal[hit], to_light, **keywords)
        assert start.dtype == np.float64
        second = scene.intersect(start, to_light, tmax=1.0, precision=tier, outputs=["prim_id"])
        return int(np.sum(second.prim_id == first.prim_id[hit]))

    for tier in ("fast", "refined"):
        assert self_hits(tier, tier) == 0, tier
    assert self_hits(None, "fast") == 0
    # The float64 rule is too fine for f32 traversal (what the default used to do with float64).
    assert self_hits("exact", "fast") > 100
    # And in the f64 tiers, the float64 rule is enough.
    assert self_hits(f64_tier, f64_tier) == 0


def test_offset_origins_precision_rules():
    """float32 tiers: the float32 rule on the float32-rounded point, returned exactly as float64;
    f64 tiers: the float64 rule on float64 points; float32 points keep the float32 rule."""
    p = np.array([[1e4 + 0.1, -3e4 - 0.2, 0.3]])
    normal = np.array([[0.6, 0.0, 0.8]])
    fast = vkray.offset_origins(p, normal)
    f32 = vkray.offset_origins(p.astype(np.float32), normal)
    assert fast.dtype == np.float64 and f32.dtype == np.float32
    np.testing.assert_array_equal(fast, f32.astype(np.float64))
    np.testing.assert_array_equal(vkray.offset_origins(p, normal, precision="refined"), fast)
    exact = vkray.offset_origins(p, normal, precision="exact")
    np.testing.assert_array_equal(exact, vkray.offset_origins(p, normal, precision="reference"))
    step32 = np.abs(fast - p)[0, 0]
    step64 = np.abs(exact - p)[0, 0]
    assert step64 < 1e-8 < 0.1 < step32  # 154 ulps at 1e4 in float64; in float32
    assert (fast - p)[0, 2] > 0 and (exact - p)[0, 2] > 0  # along the normal
    assert ((fast - p) @ normal[0])[0] > 0.6 * 150 * np.spacing(np.float32(1e4)) * 0.99  # x: 153 f32 ulps
    np.testing.assert_array_equal(
        vkray.offset_origins(p.astype(np.float32), normal, precision="exact"), f32
    )


_SKIPPERS = """
import pytest

def test_wants_a_package():
    pytest.importorskip("a_package_setup_would_install")

def test_wants_cuda():
    pytest.skip("torch sees no CUDA GPU")

@pytest.mark.xfail(reason="a known defect", run=False)
def test_known_defect():
    pass
"""


@pytest.mark.parametrize("strict", [False, True])
def test_strict_skips_fail_for_want_of_what_setup_installs(tmp_path, strict):
    """Under VKRAY_STRICT_SKIPS=1 (scripts/test.sh, CI) a skip for want of a package fails, naming
    it; a skip for want of hardware (CUDA) stays a skip, as does an xfail; without it all skip."""
    shutil.copy(pathlib.Path(__file__).resolve().parent / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_skippers.py").write_text(_SKIPPERS)
    env = dict(os.environ, VKRAY_STRICT_SKIPS="1" if strict else "0")
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", str(tmp_path)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    out = run.stdout + run.stderr
    if strict:
        assert run.returncode == 1 and "1 failed, 1 skipped, 1 xfailed" in out, out
        assert "VKRAY_STRICT_SKIPS=1" in out and "a_package_setup_would_install" in out, out
    else:
        assert run.returncode == 0 and "2 skipped, 1 xfailed" in out, out


def test_shipped_meshes_load_as_trimesh_reads_them():
    """vkray.data's meshes: the counts its docstring states, the arrays trimesh's own OBJ reader
    makes of the same files (the independent loader), and closedness as trimesh judges it."""
    import gzip

    trimesh = pytest.importorskip("trimesh")
    table = {"stanford-bunny": (35947, 69451, False), "fandisk": (6475, 12946, True), "spot": (2930, 5856, True),
             "cow": (2903, 5804, True), "teapot": (3644, 6320, False)}
    assert set(table) == set(vkray.data.MESH_NAMES)
    for name, (n_vertices, n_faces, closed) in table.items():
        vertices, faces = vkray.data.load_mesh(name)
        assert vertices.dtype == np.float64 and faces.dtype == np.int64
        assert vertices.shape == (n_vertices, 3) and faces.shape == (n_faces, 3)
        with gzip.open(vkray.data.mesh_path(name), "rb") as f:
            theirs = trimesh.load(f, file_type="obj", process=False, maintain_order=True)
        np.testing.assert_array_equal(vertices, theirs.vertices)
        np.testing.assert_array_equal(faces, theirs.faces)
        assert theirs.is_watertight is closed, name
    with pytest.raises(ValueError, match="no shipped mesh named 'bunny'.*'stanford-bunny'"):
        vkray.data.load_mesh("bunny")

"""Bad input is refused with a clear error naming the argument (and row) before the GPU sees it;
the device keeps working afterwards."""

import numpy as np
import pytest

import vkray

V = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float64)
F = np.array([[0, 1, 2]], np.int64)


@pytest.mark.parametrize(
    "vertices, faces, error, match",
    [
        (V[:, :2], F, ValueError, r"vertices must have shape \(N, 3\)"),
        (V.ravel(), F, ValueError, "vertices must have shape"),
        (V.astype(complex), F, TypeError, "vertices must hold real numbers"),
        (np.array([["a", "b", "c"]]), F, TypeError, "vertices"),
        (V, F.astype(np.float32), TypeError, "faces must hold integers"),
        (V, F[:, :2], ValueError, r"faces must have shape \(F, 3\)"),
        (np.where([[0], [1], [0]], np.nan, V), F, ValueError, "vertices row 1 is not finite"),
        (np.where([[0], [0], [1]], np.inf, V), F, ValueError, "vertices row 2 is not finite"),
        (V, np.array([[0, 1, 2], [0, -1, 2]]), ValueError, "faces row 1"),
        (
            V,
            np.array([[0, 1, 2], [0, 1, 2], [0, 3, 2]]),
            ValueError,
            r"faces row 2 = \[0, 3, 2\] indexes outside the 3 vertices",
        ),
        (np.zeros((0, 3)), np.zeros((0, 3), np.int32), ValueError, "empty"),
        (V, np.zeros((0, 3), np.int32), ValueError, "faces is empty"),
    ],
)
def test_bad_meshes(any_device, vertices, faces, error, match):
    with pytest.raises(error, match=match):
        any_device.mesh(vertices, faces)


def test_bad_build_options(any_device):
    with pytest.raises(ValueError, match="build must be"):
        any_device.mesh(V, F, build="fastest")
    with pytest.raises(ValueError, match="build must be"):
        any_device.scene([], build="slow")


def test_bad_instances(any_device):
    mesh = any_device.mesh(V, F)
    with pytest.raises(TypeError, match="vkray.Mesh"):
        vkray.Instance(V)
    with pytest.raises(ValueError, match="24 bits"):
        vkray.Instance(mesh, custom_index=1 << 24)
    with pytest.raises(ValueError, match="custom_index"):
        vkray.Instance(mesh, custom_index=-1)
    with pytest.raises(ValueError, match="8 bits"):
        vkray.Instance(mesh, mask=256)
    with pytest.raises(ValueError, match=r"shape \(3, 4\) or \(4, 4\)"):
        vkray.Instance(mesh, np.eye(3))
    projective = np.eye(4)
    projective[3, 0] = 1
    with pytest.raises(ValueError, match=r"last row must be \[0, 0, 0, 1\]"):
        any_device.scene(vkray.Instance(mesh, projective))
    nan = np.eye(4)
    nan[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"instance 1: transform\[1, 3\] is not finite"):
        any_device.scene([mesh, vkray.Instance(mesh, nan)])
    with pytest.raises(TypeError, match="scene item 1 must be a Mesh, an Instance or a mesh object"):
        any_device.scene([mesh, "cow"])
    other = vkray.Device(any_device.info.index, any_device.backend)
    with pytest.raises(ValueError, match="another Device"):
        other.scene(mesh)


ORIGINS = np.array([[0.2, 0.2, 0.0], [0.3, 0.3, 0.0]])
DIRECTIONS = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    "origins, directions, kwargs, error, match",
    [
        (ORIGINS[:, :2], DIRECTIONS, {}, ValueError, r"origins must have shape \(\.\.\., 3\)"),
        (ORIGINS, DIRECTIONS[:, :2], {}, ValueError, "directions must have shape"),
        (ORIGINS, np.ones((3, 3)), {}, ValueError, "do not broadcast"),
        (ORIGINS.astype(complex), DIRECTIONS, {}, TypeError, "origins must hold real numbers"),
        (np.where([[0], [1]], np.nan, ORIGINS), DIRECTIONS, {}, ValueError, "origins row 1 is not finite"),
        (ORIGINS, np.where([[1], [0]], np.inf, DIRECTIONS), {}, ValueError, "directions row 0 is not finite"),
        (ORIGINS, np.array([[0, 0, 1.0], [0, 0, 0]]), {}, ValueError, "directions row 1 has zero length"),
        (ORIGINS, [[0, 0, 1.0], [0, 0, 1e-50]], {}, ValueError, "directions row 1 has zero length in float32"),
        (ORIGINS, DIRECTIONS, {"tmin": -1.0}, ValueError, "tmin of ray 0 must be finite and >= 0"),
        (ORIGINS, DIRECTIONS, {"tmin": 2.0, "tmax": 1.0}, ValueError, r"ray 0 has tmax \(1\) below tmin \(2\)"),
        (ORIGINS, DIRECTIONS, {"tmax": np.array([1.0, np.nan])}, ValueError, "ray 1 has tmax"),
        (ORIGINS, DIRECTIONS, {"tmin": np.array([0.0, np.inf])}, ValueError, "tmin of ray 1"),
        (ORIGINS, DIRECTIONS, {"tmax": np.ones(3)}, ValueError, "do not broadcast"),
        (ORIGINS, DIRECTIONS, {"tmin": "zero"}, TypeError, "tmin must hold real numbers"),
    ],
)
def test_bad_rays(any_device, origins, directions, kwargs, error, match):
    scene = any_device.scene(any_device.mesh(V, F))
    for query in (scene.intersect, scene.occluded):
        with pytest.raises(error, match=match):
            query(origins, directions, **kwargs)
    # Nothing reached the GPU: the device still answers.
    assert scene.intersect(ORIGINS, DIRECTIONS).hit.tolist() == [True, True]


def _big_endian(array):
    array = np.asarray(array)
    return array.astype(array.dtype.newbyteorder(">"))


def test_big_endian_arrays_are_converted_not_refused(any_device):
    """Arrays in non-native byte order (e.g. read from a big-endian file format) are numbers like
    any others: every argument that takes an array converts them to native order."""
    assert not _big_endian(V).dtype.isnative
    native = any_device.scene(any_device.mesh(V, F))
    scene = any_device.scene(any_device.mesh(_big_endian(V), _big_endian(F.astype(np.int32))))
    expected = native.intersect(ORIGINS, DIRECTIONS, tmin=0.5, tmax=2.0)
    for o, d in ((_big_endian(ORIGINS), DIRECTIONS), (ORIGINS, _big_endian(DIRECTIONS))):
        hits = scene.intersect(o, d, tmin=_big_endian([0.5, 0.5]), tmax=_big_endian([2.0, 2.0]),
                               mask=_big_endian(np.array([1, 255], np.int16)))
        np.testing.assert_array_equal(hits.t, expected.t)
        assert scene.occluded(o, d, tmin=_big_endian(0.5), tmax=_big_endian(2.0)).all()
    for faces in (_big_endian(F), _big_endian(F.astype(np.uint32)), _big_endian(F.astype(np.uint16))):
        assert any_device.mesh(_big_endian(V.astype(np.float32)), faces).triangle_count == 1
    assert any_device.meshes([(_big_endian(V), _big_endian(F))])[0].triangle_count == 1
    move = np.eye(4)
    move[2, 3] = -1.0
    parts = any_device.mesh_from_parts([(_big_endian(V), _big_endian(F), _big_endian(move))])
    np.testing.assert_array_equal(parts.vertices, V - [0, 0, 1])
    spheres = any_device.spheres(_big_endian(V), _big_endian([0.1, 0.2, 0.3]))
    assert spheres.vertex_count == 3
    mesh = any_device.mesh(V, F, allow_update=True)
    mesh.update(_big_endian(V + 1))
    placed = any_device.scene([vkray.Instance(mesh, _big_endian(move))], allow_update=True)
    placed.update(transforms=_big_endian(np.eye(4)[None]), masks=_big_endian(np.array([7], np.int32)))
    assert placed.instances[0].mask == 7
    assert placed.intersect([[1.2, 1.2, 0.0]], [0, 0, 1]).hit.all()
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(
        vkray.offset_origins(_big_endian(ORIGINS), _big_endian(normals), _big_endian(DIRECTIONS)),
        vkray.offset_origins(ORIGINS, normals, DIRECTIONS),
    )


def test_outputs_may_be_any_iterable(any_device):
    """A generator of field names is read once: its fields come back (it used to be spent by its
    own check and reported empty)."""
    scene = any_device.scene(any_device.mesh(V, F))
    hits = scene.intersect(ORIGINS, DIRECTIONS, outputs=(name for name in ("t", "normal")))
    assert hits.t is not None and hits.normal is not None and hits.uv is None
    assert scene.intersect(ORIGINS, DIRECTIONS, outputs=iter(["prim_id"])).prim_id.tolist() == [0, 0]
    with pytest.raises(ValueError, match="at least one"):
        scene.intersect(ORIGINS, DIRECTIONS, outputs=iter([]))
    with pytest.raises(TypeError, match="outputs must be hit field names"):
        scene.intersect(ORIGINS, DIRECTIONS, outputs=3)


def test_mesh_parts_take_affine_transforms_only(any_device):
    """A part's transform is refused as an `Instance`'s is: a projective 4×4 (last row not
    [0, 0, 0, 1]) or a non-finite entry, naming the part (its last row used to be dropped)."""
    projective = np.eye(4)
    projective[3, 0] = 0.5
    with pytest.raises(ValueError, match=r"part 1: transform's last row must be \[0, 0, 0, 1\]"):
        any_device.mesh_from_parts([(V, F), (V, F, projective)])
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match=r"part 0: transform\[0, 3\] is not finite"):
        any_device.mesh_from_parts([(V, F, nan)])
    affine = np.eye(4)
    affine[:3, 3] = [1, 2, 3]
    np.testing.assert_array_equal(any_device.mesh_from_parts([(V, F, affine)]).vertices, V + [1, 2, 3])
    np.testing.assert_array_equal(any_device.mesh_from_parts([(V, F, affine[:3])]).vertices, V + [1, 2, 3])


def test_opaque_takes_numpy_bools(any_device):
    """numpy's bools are True and False (np.False_ used to be taken as None: the geometry's own
    opacity); other values, 0 and 1 included, are refused."""
    mesh = any_device.mesh(V, F)
    for value, expected in ((np.False_, False), (np.True_, True), (False, False), (True, True), (None, None)):
        instance = vkray.Instance(mesh, opaque=value)
        assert instance.opaque is expected
        assert instance._flags() == {None: 0, True: 4, False: 8}[expected]
    for bad in (0, 1, "yes", np.int8(1), 1.0):
        with pytest.raises(TypeError, match="opaque must be True, False or None"):
            vkray.Instance(mesh, opaque=bad)


@pytest.mark.parametrize(
    "points, normals, directions, error, match",
    [
        (ORIGINS.astype(complex), DIRECTIONS, None, TypeError, "points must hold real numbers"),
        (ORIGINS, DIRECTIONS.astype(complex), None, TypeError, "normals must hold real numbers"),
        (ORIGINS, DIRECTIONS, DIRECTIONS.astype(complex), TypeError, "directions must hold real numbers"),
        (ORIGINS.astype(object), DIRECTIONS, None, TypeError, "points must hold real numbers"),
        (ORIGINS, [["a", "b", "c"]], None, TypeError, "normals must hold real numbers"),
        (ORIGINS, None, None, TypeError, "normals must be an array"),
        (ORIGINS, DIRECTIONS[:, :2], None, ValueError, r"normals must have shape \(\.\.\., 3\)"),
        (ORIGINS, np.ones((3, 3)), None, ValueError, "do not broadcast"),
        (ORIGINS, DIRECTIONS, np.ones((3, 3)), ValueError, "do not broadcast"),
    ],
)
def test_offset_origins_refuses_bad_input(points, normals, directions, error, match):
    """offset_origins used to drop imaginary parts and turn normals=None into NaN origins."""
    with pytest.raises(error, match=match):
        vkray.offset_origins(points, normals, directions)


def test_offset_origins_broadcasts_and_keeps_misses_nan():
    one = vkray.offset_origins([0.5, 0.5, 0.0], [0.0, 0.0, 1.0], [[0, 0, 1.0], [0, 0, -1.0]])
    assert one.shape == (2, 3) and one[0, 2] > 0 > one[1, 2]
    missed = vkray.offset_origins([[np.nan] * 3, [0.5, 0.5, 0.0]], [[np.nan] * 3, [0.0, 0.0, 1.0]])
    assert np.isnan(missed[0]).all() and np.isfinite(missed[1]).all()
    with pytest.raises(ValueError, match="precision must be 'fast', 'refined', 'exact' or 'reference', got \"double\""):
        vkray.offset_origins(ORIGINS, DIRECTIONS, precision="double")


_U64 = r"\[1, 2\*\*64 - 1\]"
_BYTE = r"\[0, 255\] \(8 bits\)"
_CUSTOM_INDEX = r"custom_index must be in \[0, 16777215\] \(24 bits\)"
_OUT_OF_RANGE = {
    # id: (action on (device, scene, mesh), error, message)
    "chunk_rays=-1": (
        lambda d, s, m: setattr(d, "chunk_rays", -1),
        ValueError,
        f"chunk_rays must be in {_U64}, got -1",
    ),
    "chunk_rays=2**70": (lambda d, s, m: setattr(d, "chunk_rays", 2**70), ValueError, f"chunk_rays must be in {_U64}"),
    "chunk_rays=0": (lambda d, s, m: setattr(d, "chunk_rays", 0), ValueError, f"chunk_rays must be in {_U64}"),
    "chunk_rays=True": (lambda d, s, m: setattr(d, "chunk_rays", True), TypeError, "chunk_rays must be an integer"),
    "chunk_rays=1000.0": (lambda d, s, m: setattr(d, "chunk_rays", 1000.0), TypeError, "chunk_rays must be an integer"),
    "chunk_rays='1000'": (lambda d, s, m: setattr(d, "chunk_rays", "1000"), TypeError, "chunk_rays must be an integer"),
    "host_threads=0": (
        lambda d, s, m: setattr(d, "host_threads", 0),
        ValueError,
        r"host_threads must be in \[1, 4096\], got 0",
    ),
    "host_threads=-2": (lambda d, s, m: setattr(d, "host_threads", -2), ValueError, "host_threads must be in"),
    "host_threads=10**6": (lambda d, s, m: setattr(d, "host_threads", 10**6), ValueError, "host_threads must be in"),
    "host_threads=True": (
        lambda d, s, m: setattr(d, "host_threads", True),
        TypeError,
        "host_threads must be an integer",
    ),
    "host_threads=2.0": (lambda d, s, m: setattr(d, "host_threads", 2.0), TypeError, "host_threads must be an integer"),
    "Device(host_threads=0)": (lambda d, s, m: vkray.Device(host_threads=0), ValueError, "host_threads must be in"),
    "DeviceGroup(host_threads=0)": (
        lambda d, s, m: vkray.DeviceGroup([0, 0], host_threads=0),
        ValueError,
        "host_threads must be in",
    ),
    "budget_bytes=2**70": (
        lambda d, s, m: d.meshes([(V, F)], budget_bytes=2**70),
        ValueError,
        f"budget_bytes .* {_U64}",
    ),
    "budget_bytes=-1": (lambda d, s, m: d.meshes([(V, F)], budget_bytes=-1), ValueError, f"budget_bytes .* {_U64}"),
    "budget_bytes=True": (
        lambda d, s, m: d.meshes([(V, F)], budget_bytes=True),
        TypeError,
        "budget_bytes must be an int",
    ),
    "mask=2**70": (lambda d, s, m: s.intersect(ORIGINS, DIRECTIONS, mask=2**70), ValueError, f"mask values .* {_BYTE}"),
    "mask=-2**70": (
        lambda d, s, m: s.occluded(ORIGINS, DIRECTIONS, mask=-(2**70)),
        ValueError,
        f"mask values .* {_BYTE}",
    ),
    "mask=[1, 2**70]": (lambda d, s, m: s.intersect(ORIGINS, DIRECTIONS, mask=[1, 2**70]), ValueError, "mask values"),
    "mask=1.0": (lambda d, s, m: s.intersect(ORIGINS, DIRECTIONS, mask=1.0), TypeError, "mask must hold integers"),
    "Instance mask=2**70": (lambda d, s, m: vkray.Instance(m, mask=2**70), ValueError, f"mask must be in {_BYTE}"),
    "Instance mask=uint64(256)": (
        lambda d, s, m: vkray.Instance(m, mask=np.uint64(256)),
        ValueError,
        f"mask .* {_BYTE}",
    ),
    "custom_index=2**70": (lambda d, s, m: vkray.Instance(m, custom_index=2**70), ValueError, _CUSTOM_INDEX),
    "custom_index=1.5": (lambda d, s, m: vkray.Instance(m, custom_index=1.5), TypeError, "custom_index must be an int"),
    "update masks=[2**70]": (lambda d, s, m: s.update(masks=[2**70]), ValueError, rf"masks\[0\] must be in {_BYTE}"),
    "update masks=[-1]": (lambda d, s, m: s.update(masks=[-1]), ValueError, rf"masks\[0\] must be in {_BYTE}"),
    "update masks=[1.0]": (lambda d, s, m: s.update(masks=[1.0]), TypeError, "masks must hold integers"),
    "update masks=[1, 2]": (lambda d, s, m: s.update(masks=[1, 2]), ValueError, r"masks must have shape \(1,\)"),
    "faces 2**70": (lambda d, s, m: d.mesh(V, [[0, 1, 2**70]]), ValueError, "faces row 0 holds an index too large"),
}


@pytest.mark.parametrize("action, error, match", list(_OUT_OF_RANGE.values()), ids=list(_OUT_OF_RANGE))
def test_integers_out_of_range_name_the_argument_and_range(any_device, action, error, match):
    """Integers beyond what the core's fixed-size integers hold are refused in Python, naming the
    argument and its range (they used to surface as OverflowError without either)."""
    mesh = any_device.mesh(V, F)
    scene = any_device.scene(mesh, allow_update=True)
    saved = any_device.chunk_rays
    try:
        with pytest.raises(error, match=match):
            action(any_device, scene, mesh)
    finally:
        any_device.chunk_rays = saved
    assert any_device.host_threads is None
    assert scene.intersect(ORIGINS, DIRECTIONS).hit.all()


def test_large_valid_integers_are_accepted(any_device):
    saved = any_device.chunk_rays
    try:
        any_device.chunk_rays = 2**64 - 1  # the core clamps chunks to what a dispatch covers
        assert any_device.chunk_rays == 2**64 - 1
        any_device.chunk_rays = np.int64(1)
        assert any_device.chunk_rays == 1
    finally:
        any_device.chunk_rays = saved
    assert any_device.meshes([(V, F)], budget_bytes=2**64 - 1)[0].triangle_count == 1
    mesh = any_device.mesh(V, F)
    instance = vkray.Instance(mesh, custom_index=np.uint32(2**24 - 1), mask=np.uint8(255))
    assert (instance.custom_index, instance.mask) == (2**24 - 1, 255)

"""Pictures for notebooks: Hits.image / _repr_png_ / show, the PNG encoder, the HTML summaries of
Device, Mesh and Scene, and vkray.preview. Small images (64×48) to stay fast on lavapipe."""

import html
import struct
import sys
import zlib

import numpy as np
import pytest

import vkray
from oracle import camera_rays, load_mesh
from vkray import _pictures

W, H = 64, 48
SIGNATURE = b"\x89PNG\r\n\x1a\n"
BACKGROUND = np.array(_pictures.BACKGROUND, np.uint8)


def decode_png(data: bytes) -> np.ndarray:
    """The pixels of an 8-bit, non-interlaced PNG whose rows use filter None or Up (what vkray
    writes): (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA uint8. Checks every chunk's CRC."""
    assert data[:8] == SIGNATURE
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        chunks.append((kind, body))
        pos += 12 + length
    assert chunks[0][0] == b"IHDR" and chunks[-1] == (b"IEND", b"")
    width, height, depth, colour_type, compression, filtering, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, compression, filtering, interlace) == (8, 0, 0, 0)
    channels = {0: 1, 2: 3, 6: 4}[colour_type]
    raw = np.frombuffer(zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT")), np.uint8)
    rows = raw.reshape(height, 1 + width * channels)
    out = np.zeros((height, width * channels), np.uint8)
    previous = np.zeros(width * channels, np.uint8)
    for y in range(height):
        kind = rows[y, 0]
        assert kind in (0, 2), f"filter {kind}"
        out[y] = rows[y, 1:] if kind == 0 else rows[y, 1:] + previous  # uint8: mod 256
        previous = out[y]
    return out.reshape(height, width, channels)[..., 0] if channels == 1 else out.reshape(height, width, channels)


def box(low=-1.0, high=1.0):
    """A closed axis-aligned cube, outward winding: (vertices (8, 3), faces (12, 3))."""
    v = np.array([[x, y, z] for x in (low, high) for y in (low, high) for z in (low, high)], np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    return v, f


def front_rays(width=W, height=H, half_width=2.0):
    """Parallel rays along -z from z=5 on a grid covering [-hw, hw] × [-hw·H/W, hw·H/W], row 0 on top."""
    half_height = half_width * height / width
    xs = np.linspace(-half_width, half_width, width)
    ys = np.linspace(half_height, -half_height, height)
    origins = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], 5.0), axis=-1)
    return origins, np.array([0.0, 0.0, -1.0])


def test_png_round_trip():
    rng = np.random.default_rng(0)
    for shape in ((5, 7, 3), (1, 1, 3), (9, 4), (3, 8, 4), (H, W, 3)):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        data = _pictures.png(image)
        assert data.startswith(SIGNATURE)
        np.testing.assert_array_equal(decode_png(data), image)
    with pytest.raises(TypeError, match="uint8"):
        _pictures.png(np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="at least one pixel"):
        _pictures.png(np.zeros((0, 4, 3), np.uint8))
    with pytest.raises(ValueError, match=r"\(2, 2, 2\)"):
        _pictures.png(np.zeros((2, 2, 2), np.uint8))


def luminance(rgb):
    return np.asarray(rgb, np.float64) @ [0.2126, 0.7152, 0.0722]


def test_colormap_lightness_increases():
    colours = _pictures.colormap(np.linspace(0, 1, 257))
    assert colours.dtype == np.uint8 and colours.shape == (257, 3)
    assert np.all(np.diff(luminance(colours)) > -0.5)  # rounding to uint8 aside
    assert np.all(np.diff(luminance(colours[::16])) > 5)
    np.testing.assert_array_equal(_pictures.colormap([-1.0, np.nan, 2.0]), colours[[0, 0, -1]])


def test_box_front_on(device):
    """A cube seen front-on by parallel rays: hits in the middle, misses at the corners, each
    field an (H, W, 3) uint8 image with the background where rays missed."""
    v, f = box()
    scene = device.scene(device.mesh(v, f))
    origins, direction = front_rays()
    hits = scene.intersect(origins, direction, outputs=vkray.HIT_FIELDS)
    assert hits.shape == (H, W)
    expected_hit = (np.abs(origins[..., 0]) <= 1) & (np.abs(origins[..., 1]) <= 1)
    inner = (np.abs(origins[..., 0]) < 0.95) & (np.abs(origins[..., 1]) < 0.95)
    outer = (np.abs(origins[..., 0]) > 1.05) | (np.abs(origins[..., 1]) > 1.05)
    np.testing.assert_array_equal(hits.hit[inner | outer], expected_hit[inner | outer])
    assert hits.hit[H // 2, W // 2] and not hits.hit[[0, 0, -1, -1], [0, -1, 0, -1]].any()
    for field in _pictures.IMAGE_FIELDS:
        image = hits.image(field)
        assert image.shape == (H, W, 3) and image.dtype == np.uint8, field
        assert (image[~hits.hit] == BACKGROUND).all(), field
        assert (image[hits.hit] != BACKGROUND).any(axis=-1).all(), field
    # The front face (normal +z) everywhere: one depth (the middle of the colormap), one normal colour.
    assert (hits.image("t")[inner] == _pictures.colormap(0.5)).all()
    assert (hits.image("normal")[inner] == [128, 128, 255]).all()
    # Ids: one colour per id; both triangles of the front face show.
    ids = hits.image("prim_id")[inner]
    assert len(np.unique(ids, axis=0)) == len(np.unique(hits.prim_id[inner])) == 2
    assert (hits.image("instance_id")[inner] == hits.image("instance_id")[H // 2, W // 2]).all()
    white = hits.image("t", background=(255, 255, 255))
    assert (white[~hits.hit] == 255).all()
    with pytest.raises(ValueError, match="background"):
        hits.image(background=(0, 0))


def test_depth_colours_are_monotone_in_t(device):
    """Nearer is lighter: sorted by t, the depth image's lightness never increases (beyond a
    level of rounding); the nearest hit is the colormap's top, the farthest its bottom."""
    v, f = load_mesh("spot")
    scene = device.scene(device.mesh(v, f))
    origin, directions = camera_rays(v, W, H)
    hits = scene.intersect(origin, directions.reshape(H, W, 3))
    image = hits.image("t")
    t = hits.t[hits.hit]
    order = np.argsort(t, kind="stable")
    light = luminance(image[hits.hit][order])
    assert hits.hit.sum() > 0.1 * H * W
    assert np.all(np.diff(light) <= 1.0)
    assert light[0] - light[-1] > 150
    np.testing.assert_array_equal(image[hits.hit][order[0]], _pictures.colormap(1.0))
    np.testing.assert_array_equal(image[hits.hit][order[-1]], _pictures.colormap(0.0))


def test_repr_png_decodes_to_the_depth_image(any_device):
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    origins, direction = front_rays()
    hits = scene.intersect(origins, direction)
    data = hits._repr_png_()
    assert data is not None and data.startswith(SIGNATURE)
    np.testing.assert_array_equal(decode_png(data), hits.image("t"))
    # Without t, the picture is of what there is.
    only_ids = scene.intersect(origins, direction, outputs=["prim_id"])
    np.testing.assert_array_equal(decode_png(only_ids._repr_png_()), only_ids.image("prim_id"))
    with pytest.raises(ValueError, match=r"no 't'.*outputs="):
        only_ids.image("t")
    with pytest.raises(ValueError, match="field must be one of"):
        hits.image("colour")


def test_other_shapes_are_no_image(any_device):
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    origins, direction = front_rays()
    for shape in ((H * W,), (4, H // 4, W), ()):
        o = origins.reshape(shape + (3,)) if shape else origins[0, 0]
        hits = scene.intersect(o, direction)
        assert hits._repr_png_() is None
        with pytest.raises(ValueError, match=f"2-D.*got shape {__import__('re').escape(str(shape))}"):
            hits.image()
    empty = scene.intersect(np.zeros((0, 5, 3)), direction)
    assert empty._repr_png_() is None and empty.image().shape == (0, 5, 3)


def test_show(any_device, monkeypatch):
    display = pytest.importorskip("IPython.display")
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect(*front_rays())
    shown = []
    monkeypatch.setattr(display, "display", shown.append)
    hits.show("normal")
    vkray.preview(scene, width=W, height=H).show()
    assert len(shown) == 2 and all(isinstance(x, display.Image) for x in shown)
    np.testing.assert_array_equal(decode_png(shown[0].data), hits.image("normal"))
    # Without IPython: a clear error, not an ImportError from deep inside.
    monkeypatch.setitem(sys.modules, "IPython.display", None)
    with pytest.raises(RuntimeError, match="needs IPython"):
        hits.show()


def test_html_summaries(any_device):
    name = html.escape(any_device.name)
    device_html = any_device._repr_html_()
    assert name in device_html and any_device.backend in device_html
    v, f = load_mesh("spot")
    mesh = any_device.mesh(v, f, compact=True)
    mesh_html = mesh._repr_html_()
    for text in (name, f"{len(f):,}", f"{len(v):,}", "compacted", f"{mesh.stats['bytes']:,} B"):
        assert text in mesh_html, text
    bv, bf = box()
    cube = any_device.mesh(bv, bf)
    spheres = any_device.spheres([[0, 0, 0], [3, 0, 0]], [0.5, 1.0])
    scene = any_device.scene([mesh, vkray.Instance(mesh, np.eye(4)), cube, spheres], allow_update=True)
    scene_html = scene._repr_html_()
    for text in (name, ">4<", ">3<", f"{2 * len(f) + 12:,}", "allow_update", f"{scene.stats['bytes']:,} B"):
        assert text in scene_html, text
    assert "spheres" in spheres._repr_html_() and ">2<" in spheres._repr_html_()
    # The spheres' radii count in the scene's bounds (centres 0 and 3 on x, radii 0.5 and 1).
    low, high = _pictures.scene_bounds(any_device.scene(spheres))
    np.testing.assert_allclose(low, [-0.5, -1, -1])
    np.testing.assert_allclose(high, [4, 1, 1])


def test_preview_frames_the_scene(device):
    v, f = load_mesh("spot")
    mesh = device.mesh(v, f)
    # Far from the origin, scaled up: the default camera finds it all the same.
    scene = device.scene(vkray.Instance(mesh, [[20, 0, 0, 1e3], [0, 20, 0, -500], [0, 0, 20, 40], [0, 0, 0, 1]]))
    picture = vkray.preview(scene, width=W, height=H)
    image = np.asarray(picture)
    assert image.shape == (H, W, 3) and image.dtype == np.uint8 and picture.shape == (H, W, 3)
    np.testing.assert_array_equal(np.asarray(vkray.preview(scene, width=W, height=H)), image)  # deterministic
    hit = (image != BACKGROUND).any(axis=-1)
    assert hit[H // 3 : 2 * H // 3, W // 3 : 2 * W // 3].mean() > 0.6  # most of the middle ninth
    border = np.concatenate([hit[0], hit[-1], hit[:, 0], hit[:, -1]])
    assert border.mean() < 0.1  # not cropped...
    rows, columns = np.flatnonzero(hit.any(axis=1)), np.flatnonzero(hit.any(axis=0))
    assert rows[-1] - rows[0] > 0.8 * H or columns[-1] - columns[0] > 0.8 * W  # ...but filled
    np.testing.assert_array_equal(decode_png(picture._repr_png_()), image)
    # From a given eye, looking at the scene's centre, framed as well.
    low, high = _pictures.scene_bounds(scene)
    centre_point = (low + high) / 2
    eye = centre_point + [0, 0, -3 * np.linalg.norm(high - low)]
    behind = np.asarray(vkray.preview(scene, width=W, height=H, eye=eye))
    hit = (behind != BACKGROUND).any(axis=-1)
    assert hit[H // 3 : 2 * H // 3, W // 3 : 2 * W // 3].mean() > 0.6
    rows, columns = np.flatnonzero(hit.any(axis=1)), np.flatnonzero(hit.any(axis=0))
    assert rows[-1] - rows[0] > 0.8 * H or columns[-1] - columns[0] > 0.8 * W
    assert not (behind == image).all()


def test_preview_shading_and_shadows(any_device, tmp_path):
    """A flat square, alone: shaded smoothly (no shadow acne: shadow rays leave it cleanly).
    With a cube between it and the light, part of the square goes dark."""
    square = any_device.mesh([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], [[0, 1, 2], [0, 2, 3]])
    alone = np.asarray(vkray.preview(any_device.scene(square), width=W, height=H)).astype(int)
    hit = (alone != BACKGROUND).any(axis=-1)
    both = hit[:, 1:] & hit[:, :-1]
    assert hit.mean() > 0.3 and np.abs(np.diff(alone, axis=1)[both]).max() <= 4
    lowest = alone[hit][:, 0].min()

    v, f = box(-0.4, 0.4)
    cube = any_device.mesh(v + [0, 0.6, 1.0], f)
    picture = vkray.preview(any_device.scene([square, cube]), width=W, height=H)
    shaded = np.asarray(picture).astype(int)
    on_square = (shaded != BACKGROUND).any(axis=-1) & (shaded[..., 0] > shaded[..., 2])  # its tint: red > blue
    dark = on_square & (shaded[..., 0] < lowest - 30)
    assert dark.sum() > 0.02 * on_square.sum()

    path = tmp_path / "preview.png"
    picture.save(path)
    np.testing.assert_array_equal(decode_png(path.read_bytes()), shaded)
    assert repr(picture) == f"<vkray.Picture {W}x{H}>"


def test_preview_of_spheres(any_device):
    """Spheres are framed by their balls: one sphere fills the picture's height, from any side."""
    scene = any_device.scene(any_device.spheres([[10.0, -3.0, 2.0]], 2.0))
    for eye in (None, [10, -3, -20], [40, 30, 10]):
        image = np.asarray(vkray.preview(scene, width=W, height=H, eye=eye))
        hit = (image != BACKGROUND).any(axis=-1)
        assert hit[H // 2, W // 2] and not hit[[0, 0, -1, -1], [0, -1, 0, -1]].any()
        rows = np.flatnonzero(hit.any(axis=1))
        assert rows[0] <= 2 and rows[-1] >= H - 3, eye  # the margin: a pixel or two
        assert 0.5 < hit.mean() < np.pi / 4 * H / W


def test_preview_arguments(any_device):
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    with pytest.raises(ValueError, match="width"):
        vkray.preview(scene, width=0)
    with pytest.raises(TypeError, match="height"):
        vkray.preview(scene, height=2.5)
    with pytest.raises(ValueError, match="eye"):
        vkray.preview(scene, eye=[1, 2])
    with pytest.raises(ValueError, match="same point"):
        vkray.preview(scene, eye=[0, 0, 0])  # the box's centre, the default target
    with pytest.raises(TypeError):
        vkray.preview(scene, 64, 48)  # keywords only

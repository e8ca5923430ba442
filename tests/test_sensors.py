"""vkray.sensors: camera rays against float64 reimplementations of Open3D's create_rays_pinhole (and
Open3D itself where it is installed), rays() bit for bit against a second float32 evaluation of the
shader's formulas, lidar geometry and presets, and every validation error."""

import importlib.util
import math
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from vkray.sensors import Lidar, OrthographicCamera, PinholeCamera

SENSORS_PY = pathlib.Path(__file__).resolve().parent.parent / "python" / "vkray" / "sensors.py"


# --------------------------------------------------------------------------------------------------
# Independent float64 reimplementations of Open3D's RaycastingScene::CreateRaysPinhole
# (cpp/open3d/t/geometry/RaycastingScene.cpp): pixel centres, unnormalized directions, (H, W, 6).


def open3d_rays_intrinsic(K, extrinsic, width, height):
    """create_rays_pinhole(intrinsic_matrix, extrinsic_matrix, width_px, height_px) in float64."""
    K = np.asarray(K, np.float64)
    extrinsic = np.asarray(extrinsic, np.float64)
    rotation, translation = extrinsic[:3, :3], extrinsic[:3, 3]
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float64)
    pixels = np.stack([columns + 0.5, rows + 0.5, np.ones_like(rows)], axis=-1)
    camera = np.linalg.solve(K, pixels.reshape(-1, 3).T)  # K^-1 (x + 0.5, y + 0.5, 1)
    world = (rotation.T @ camera).T.reshape(height, width, 3)
    rays = np.empty((height, width, 6))
    rays[..., :3] = -rotation.T @ translation
    rays[..., 3:] = world
    return rays


def open3d_look_at(fov_deg, center, eye, up, width, height):
    """The K and extrinsic create_rays_pinhole(fov_deg, center, eye, up, width_px, height_px) builds."""
    center, eye, up = (np.asarray(v, np.float64) for v in (center, eye, up))
    focal = 0.5 * width / math.tan(0.5 * math.radians(fov_deg))
    K = np.array([[focal, 0, 0.5 * width], [0, focal, 0.5 * height], [0, 0, 1]])
    z = (center - eye) / math.sqrt(np.sum((center - eye) ** 2))
    y = up / math.sqrt(np.sum(up**2))
    x = np.cross(y, z)
    x /= math.sqrt(np.sum(x**2))
    y = np.cross(z, x)
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = [x, y, z]
    extrinsic[:3, 3] = -extrinsic[:3, :3] @ eye
    return K, extrinsic


def open3d_rays_look_at(fov_deg, center, eye, up, width, height):
    K, extrinsic = open3d_look_at(fov_deg, center, eye, up, width, height)
    return open3d_rays_intrinsic(K, extrinsic, width, height)


def rotation(seed):
    """A random rotation matrix (det +1)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def rigid(seed, scale=5.0):
    matrix = np.eye(4)
    matrix[:3, :3] = rotation(seed)
    matrix[:3, 3] = np.random.default_rng(seed + 1000).uniform(-scale, scale, 3)
    return matrix


INTRINSIC_CASES = [
    (np.array([[500.0, 0, 320.3], [0, 510.0, 239.1], [0, 0, 1]]), rigid(1), 64, 48),
    (np.array([[80.0, 2.5, 17.0], [0, 75.0, 9.5], [0, 0, 1]]), rigid(2), 33, 21),  # skew, odd sizes
    (np.array([[1200.0, 0, 640], [0, 1200.0, 360], [0, 0, 1]]), np.eye(4), 1280, 720),
    (np.array([[3.0, 0, 1.5], [0, 3.0, 0.5], [0, 0, 1]]), rigid(3, scale=1e3), 3, 1),
]

LOOK_AT_CASES = [
    (60.0, [0.5, 0.5, 0.5], [-1, -1, -1], [0, 0, 1], 320, 240),  # Open3D's tutorial camera
    (90.0, [0, 0, 2], [2, 3, 0], [0, 1, 0], 64, 48),  # Open3D's ray_casting_to_image example
    (37.5, [1, 2, 3], [4, -5, 6], [0.1, 0.2, 1], 31, 17),
    (120.0, [10, 0, 0], [0, 0, 0], [0, 0, -1], 8, 100),
    (1.0, [0, 0, -100], [0, 0, 100], [1, 0, 0], 5, 5),
]


def assert_rays_close(camera, expected):
    origins, directions = camera.rays()
    scale = max(1.0, float(np.max(np.abs(expected[..., :3]))))
    np.testing.assert_allclose(origins, expected[..., :3], rtol=1e-6, atol=1e-6 * scale)
    np.testing.assert_allclose(directions, expected[..., 3:], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("K, extrinsic, width, height", INTRINSIC_CASES)
def test_pinhole_intrinsic_form_matches_open3d_formula(K, extrinsic, width, height):
    camera = PinholeCamera(width, height, K=K, extrinsic=extrinsic)
    assert camera.shape == (height, width)
    assert_rays_close(camera, open3d_rays_intrinsic(K, extrinsic, width, height))


@pytest.mark.parametrize("fov_deg, center, eye, up, width, height", LOOK_AT_CASES)
def test_pinhole_look_at_form_matches_open3d_formula(fov_deg, center, eye, up, width, height):
    camera = PinholeCamera(width, height, fov_deg=fov_deg, eye=eye, target=center, up=up)
    assert_rays_close(camera, open3d_rays_look_at(fov_deg, center, eye, up, width, height))
    K, extrinsic = open3d_look_at(fov_deg, center, eye, up, width, height)
    np.testing.assert_allclose(camera.K, K, rtol=1e-12)
    np.testing.assert_allclose(camera.extrinsic, extrinsic, rtol=1e-12, atol=1e-12 * np.abs(extrinsic).max())


@pytest.mark.parametrize("fov_deg, center, eye, up, width, height", LOOK_AT_CASES)
def test_the_two_forms_agree(fov_deg, center, eye, up, width, height):
    look_at = PinholeCamera(width, height, fov_deg=fov_deg, eye=eye, target=center, up=up)
    K, extrinsic = open3d_look_at(fov_deg, center, eye, up, width, height)
    intrinsic = PinholeCamera(width, height, K=K, extrinsic=extrinsic)
    for a, b in zip(look_at.rays(), intrinsic.rays()):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * max(1.0, float(np.abs(b).max())))
    # The look-at camera's own K and extrinsic rebuild it bit for bit.
    again = PinholeCamera(width, height, K=look_at.K, extrinsic=look_at.extrinsic)
    for a, b in zip(look_at.rays(), again.rays()):
        np.testing.assert_array_equal(a, b)


# create_rays_pinhole's output recorded from open3d 0.20.0 (pip wheel, CPU): the origin, then the
# directions row by row.
OPEN3D_EXTRINSIC = np.array(
    [
        [0.955336489125606, 0.0, 0.29552020666133955, 0.1],
        [0.29552020666133955, 0.0, -0.955336489125606, -2.5],
        [0.0, 1.0, 0.0, 3.3],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
_LEFT_TO_RIGHT = (-0.4330126941204071, -0.14433756470680237, 0.14433753490447998, 0.4330127239227295)
OPEN3D_RECORDED = [
    (
        dict(K=[[500.0, 0, 320.3], [0, 510.0, 239.1], [0, 0, 1]], extrinsic=OPEN3D_EXTRINSIC),
        (3, 2),
        [0.6432668566703796, -3.299999952316284, -2.417893171310425],
        [
            [
                [-0.7492902874946594, 1.0, 0.2579329013824463],
                [-0.7473796010017395, 1.0, 0.25852394104003906],
                [-0.7454689741134644, 1.0, 0.25911498069763184],
            ],
            [
                [-0.7487108707427979, 1.0, 0.2560596764087677],
                [-0.7468001842498779, 1.0, 0.2566507160663605],
                [-0.7448895573616028, 1.0, 0.25724175572395325],
            ],
        ],
    ),
    (
        dict(fov_deg=37.5, target=[1, 2, 3], eye=[4, -5, 6], up=[0.1, 0.2, 1]),
        (3, 2),
        [4.0, -5.0, 6.0],
        [
            [
                [-0.15767213702201843, 0.884799599647522, -0.5062462687492371],
                [-0.368200421333313, 0.8100066781044006, -0.47023487091064453],
                [-0.5787287354469299, 0.7352136969566345, -0.4342234432697296],
            ],
            [
                [-0.1542879045009613, 0.9751585125923157, -0.2987931966781616],
                [-0.36481618881225586, 0.9003655910491943, -0.2627817690372467],
                [-0.5753445029258728, 0.8255726099014282, -0.2267703413963318],
            ],
        ],
    ),
    (
        dict(fov_deg=60.0, target=[1, 0, 0], eye=[0, 0, 0], up=[0, 0, 1]),
        (4, 3),
        [0.0, 0.0, 0.0],
        [[[1.0, y, z] for y in _LEFT_TO_RIGHT] for z in (-0.28867512941360474, 0.0, 0.28867509961128235)],
    ),
]


@pytest.mark.parametrize("kwargs, size, origin, recorded", OPEN3D_RECORDED)
def test_pinhole_matches_recorded_open3d_output(kwargs, size, origin, recorded):
    recorded = np.array(recorded, np.float32)
    origins, directions = PinholeCamera(*size, **kwargs).rays()
    # The origin is the same float64 value rounded once; directions are Open3D's bit for bit
    # (Open3D 0.20 sums a*px + (b*py + c) in float32, as the shader does).
    np.testing.assert_array_equal(origins, np.broadcast_to(np.float32(origin), origins.shape))
    np.testing.assert_array_equal(directions, recorded)


def test_open3d_look_at_rolls_the_image_180_degrees():
    """Open3D's camera +y is `up`, and +y points down the image: up = world up gives images upside
    down and mirrored (a 180-degree roll); up = world down gives upright images."""
    kwargs = dict(fov_deg=60, eye=[0, 0, 0], target=[1, 0, 0])  # looking along +x, world z up
    _, upside_down = PinholeCamera(4, 3, up=[0, 0, 1], **kwargs).rays()
    assert upside_down[0, 0, 2] < 0 and upside_down[0, 0, 1] < 0  # top-left looks down and right
    _, upright = PinholeCamera(4, 3, up=[0, 0, -1], **kwargs).rays()
    assert upright[0, 0, 2] > 0 and upright[0, 0, 1] > 0  # top-left looks up and left (+y is left)


def test_against_open3d_itself():
    o3d = pytest.importorskip("open3d")
    scene = o3d.t.geometry.RaycastingScene
    for K, extrinsic, width, height in INTRINSIC_CASES:
        expected = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(extrinsic), width, height).numpy()
        origins, directions = PinholeCamera(width, height, K=K, extrinsic=extrinsic).rays()
        np.testing.assert_array_equal(origins, expected[..., :3])
        np.testing.assert_allclose(directions, expected[..., 3:], rtol=1e-6, atol=1e-6)
    for fov_deg, center, eye, up, width, height in LOOK_AT_CASES:
        expected = scene.create_rays_pinhole(
            fov_deg=fov_deg, center=center, eye=eye, up=up, width_px=width, height_px=height
        ).numpy()
        origins, directions = PinholeCamera(width, height, fov_deg=fov_deg, eye=eye, target=center, up=up).rays()
        np.testing.assert_allclose(origins, expected[..., :3], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(directions, expected[..., 3:], rtol=1e-6, atol=1e-6)


# --------------------------------------------------------------------------------------------------
# Bit for bit: rays() against a second float32 evaluation of the shader's formulas.


def f32(value):
    return np.float32(value)


def pinhole_loop(generator):
    """The pinhole formula one pixel at a time, in float32 scalars."""
    a, b, c = generator["axes"]
    origin = generator["origin"]
    out = np.empty((generator["rows"], generator["columns"], 3), np.float32)
    for y in range(generator["rows"]):
        py = f32(y + 0.5)
        for x in range(generator["columns"]):
            px = f32(x + 0.5)
            for j in range(3):
                out[y, x, j] = a[j] * px + (b[j] * py + c[j])
    return np.broadcast_to(origin, out.shape), out


def pinhole_grid(generator):
    """The pinhole formula on full 2-D coordinate grids."""
    a, b, c = generator["axes"]
    py, px = np.meshgrid(
        np.arange(generator["rows"]).astype(np.float32) + f32(0.5),
        np.arange(generator["columns"]).astype(np.float32) + f32(0.5),
        indexing="ij",
    )
    directions = np.stack([a[j] * px + (b[j] * py + c[j]) for j in range(3)], axis=-1)
    return np.broadcast_to(generator["origin"], directions.shape), directions


def small_and_large_cameras():
    for K, extrinsic, _, _ in INTRINSIC_CASES:
        yield PinholeCamera(13, 7, K=K, extrinsic=extrinsic), PinholeCamera(640, 480, K=K, extrinsic=extrinsic)
    for fov_deg, center, eye, up, _, _ in LOOK_AT_CASES:
        kwargs = dict(fov_deg=fov_deg, target=center, eye=eye, up=up)
        yield PinholeCamera(9, 11, **kwargs), PinholeCamera(333, 257, **kwargs)


@pytest.mark.parametrize("small, large", list(small_and_large_cameras()))
def test_pinhole_rays_bitwise(small, large):
    for camera, reference in ((small, pinhole_loop), (large, pinhole_grid)):
        origins, directions = camera.rays()
        expected_origins, expected_directions = reference(camera._generator())
        np.testing.assert_array_equal(directions.view(np.uint32), expected_directions.view(np.uint32))
        np.testing.assert_array_equal(origins.view(np.uint32), expected_origins.view(np.uint32))


@pytest.mark.parametrize("K, extrinsic, width, height", INTRINSIC_CASES)
def test_pinhole_generator_parameters(K, extrinsic, width, height):
    generator = PinholeCamera(width, height, K=K, extrinsic=extrinsic)._generator()
    matrix = extrinsic[:3, :3].T @ np.linalg.inv(K)
    np.testing.assert_array_equal(generator["axes"], matrix.T.astype(np.float32))  # rows a, b, c
    np.testing.assert_array_equal(generator["origin"], (-extrinsic[:3, :3].T @ extrinsic[:3, 3]).astype(np.float32))
    assert (generator["kind"], generator["columns"], generator["rows"]) == (1, width, height)


def ortho_reference(eye, target, up, extent, width, height):
    """Orthographic rays in float64: pixel centres on a plane through eye, Open3D's look-at axes."""
    _, extrinsic = open3d_look_at(60.0, target, eye, up, width, height)
    right, down, forward = extrinsic[:3, :3]
    pixel = extent / width
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (columns + 0.5 - width / 2) * pixel
    v = (rows + 0.5 - height / 2) * pixel
    origins = np.asarray(eye, np.float64) + u[..., None] * right + v[..., None] * down
    return origins, np.broadcast_to(forward, origins.shape)


ORTHO_CASES = [
    ([0, 0, 0], [1, 0, 0], [0, 0, -1], 4.0, 4, 2),
    ([1, 2, 3], [-4, 5, 1], [0.3, 0.1, 1], 2.5, 37, 23),
    ([100, -50, 20], [0, 0, 0], [0, 1, 0], 300.0, 640, 480),
    ([0, 0, 10], [0, 0, 0], [0, -1, 0], 1e-3, 5, 9),
]


@pytest.mark.parametrize("eye, target, up, extent, width, height", ORTHO_CASES)
def test_orthographic_matches_float64_formula(eye, target, up, extent, width, height):
    camera = OrthographicCamera(width, height, eye=eye, target=target, up=up, extent=extent)
    origins, directions = camera.rays()
    expected_origins, expected_directions = ortho_reference(eye, target, up, extent, width, height)
    scale = max(extent, float(np.max(np.abs(eye))))
    np.testing.assert_allclose(origins, expected_origins, rtol=1e-6, atol=1e-6 * scale)
    np.testing.assert_allclose(directions, expected_directions, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)
    # Square pixels: neighbours are extent / width apart along both axes.
    if width > 1:
        np.testing.assert_allclose(np.linalg.norm(origins[:, 1] - origins[:, 0], axis=-1), extent / width, rtol=1e-3)
    if height > 1:
        np.testing.assert_allclose(np.linalg.norm(origins[1] - origins[0], axis=-1), extent / width, rtol=1e-3)


@pytest.mark.parametrize("eye, target, up, extent, width, height", ORTHO_CASES)
def test_orthographic_rays_bitwise(eye, target, up, extent, width, height):
    camera = OrthographicCamera(width, height, eye=eye, target=target, up=up, extent=extent)
    generator = camera._generator()
    u, v, direction = generator["axes"]
    corner = generator["origin"]
    expected = np.empty((height, width, 3), np.float32)
    for y in range(height):
        py = f32(y + 0.5)
        for x in range(width):
            px = f32(x + 0.5)
            for j in range(3):
                expected[y, x, j] = (corner[j] + u[j] * px) + v[j] * py
    origins, directions = camera.rays()
    np.testing.assert_array_equal(origins.view(np.uint32), expected.view(np.uint32))
    np.testing.assert_array_equal(directions, np.broadcast_to(direction, directions.shape))
    # The parameters: float64 axes rounded once, and the corner from the rounded axes.
    _, extrinsic = open3d_look_at(60.0, target, eye, up, width, height)
    pixel = extent / width
    np.testing.assert_allclose(u, extrinsic[0, :3] * pixel, rtol=2.5e-7, atol=1e-300)
    np.testing.assert_allclose(v, extrinsic[1, :3] * pixel, rtol=2.5e-7, atol=1e-300)
    np.testing.assert_allclose(direction, extrinsic[2, :3], rtol=2.5e-7, atol=1e-300)
    u64, v64 = u.astype(np.float64), v.astype(np.float64)
    expected_corner = np.asarray(eye, np.float64) - u64 * (width / 2) - v64 * (height / 2)
    np.testing.assert_array_equal(corner, expected_corner.astype(np.float32))
    assert (generator["kind"], generator["columns"], generator["rows"]) == (2, width, height)


def test_orthographic_axes_are_the_pinhole_look_at_axes():
    eye, target, up = [1, 2, 3], [-4, 5, 1], [0.3, 0.1, 1]
    ortho = OrthographicCamera(8, 6, eye=eye, target=target, up=up, extent=2.0)._generator()["axes"]
    pinhole = PinholeCamera(8, 6, fov_deg=50, eye=eye, target=target, up=up).extrinsic[:3, :3]
    np.testing.assert_allclose(ortho[0] / np.linalg.norm(ortho[0]), pinhole[0], atol=1e-7)
    np.testing.assert_allclose(ortho[1] / np.linalg.norm(ortho[1]), pinhole[1], atol=1e-7)
    np.testing.assert_allclose(ortho[2], pinhole[2], atol=1e-7)


# --------------------------------------------------------------------------------------------------
# Lidar


def lidar_loop(generator, beams):
    """The lidar formula for some (channel, step) beams, in float32 scalars from the table."""
    table = generator["table"]
    rows = generator["rows"]
    r = generator["axes"]
    out = []
    for c, k in beams:
        ce, se = table[2 * c], table[2 * c + 1]
        ca, sa = table[2 * rows + 2 * k], table[2 * rows + 2 * k + 1]
        lx, ly, lz = ce * ca, ce * sa, se
        out.append([(r[j, 0] * lx + r[j, 1] * ly) + r[j, 2] * lz for j in range(3)])
    return np.array(out, np.float32)


def test_lidar_directions_and_table():
    elevations = [-30.0, -7.5, 0.0, 2.25, 89.0, 90.0, -90.0]
    lidar = Lidar(elevations, 360, azimuth_start_deg=-10.0)
    origins, directions = lidar.rays()
    assert lidar.shape == (7, 360) and len(lidar) == 7 * 360
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(origins, 0.0)
    d = directions.astype(np.float64)
    elevation = np.degrees(np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])))
    np.testing.assert_allclose(elevation, np.broadcast_to(np.array(elevations)[:, None], (7, 360)), atol=1e-4)
    horizontal = np.abs(np.array(elevations)) < 90  # the poles have no azimuth
    azimuth = np.degrees(np.arctan2(d[horizontal, :, 1], d[horizontal, :, 0]))
    expected = -10.0 + 360.0 * np.arange(360) / 360
    difference = (azimuth - expected + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(difference, 0.0, atol=1e-3)
    # The table: cos/sin of each elevation, then of each azimuth, interleaved, float32.
    generator = lidar._generator()
    e = np.radians(np.array(elevations))
    a = np.radians(-10.0 + (360.0 * np.arange(360)) / 360)
    channel_part = np.stack([np.cos(e), np.sin(e)], 1).ravel()
    step_part = np.stack([np.cos(a), np.sin(a)], 1).ravel()
    np.testing.assert_array_equal(generator["table"], np.concatenate([channel_part, step_part]).astype(np.float32))
    np.testing.assert_allclose(lidar.azimuths_deg, -10.0 + np.arange(360), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lidar_pose_and_bitwise(seed):
    pose = rigid(seed)
    elevations = np.random.default_rng(seed).uniform(-40, 40, 11)
    lidar = Lidar(elevations, 97, pose=pose, azimuth_start_deg=3.7, echoes=3)
    origins, directions = lidar.rays()
    local = Lidar(elevations, 97, azimuth_start_deg=3.7).rays()[1].astype(np.float64)
    np.testing.assert_allclose(directions, local @ pose[:3, :3].T, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(origins, np.broadcast_to(pose[:3, 3].astype(np.float32), origins.shape))
    generator = lidar._generator()
    np.testing.assert_array_equal(generator["axes"], pose[:3, :3].astype(np.float32))
    np.testing.assert_array_equal(generator["origin"], pose[:3, 3].astype(np.float32))
    assert (generator["kind"], generator["rows"], generator["columns"], generator["echoes"]) == (3, 11, 97, 3)
    # Bit for bit, every beam, and ray i = channel * steps + step.
    beams = [(c, k) for c in range(11) for k in range(97)]
    expected = lidar_loop(generator, beams)
    np.testing.assert_array_equal(directions.reshape(-1, 3).view(np.uint32), expected.view(np.uint32))


def test_lidar_presets():
    assert Lidar.PRESETS == ("VLP-16", "HDL-32E", "HDL-64E", "VLS-128", "OS1-128")
    published = {  # channels, lowest and highest elevation (degrees)
        "VLP-16": (16, -15.0, 15.0),
        "HDL-32E": (32, -30.67, 10.67),
        "HDL-64E": (64, -24.0 - 1 / 3, 2.0),
        "VLS-128": (128, -25.0, 15.0),
        "OS1-128": (128, -22.5, 22.5),
    }
    for name, (channels, lowest, highest) in published.items():
        lidar = Lidar.preset(name)
        elevations = lidar.elevations_deg
        assert lidar.shape[0] == channels == lidar.channels
        assert np.all(np.diff(elevations) > 0), name  # ascending, distinct
        assert elevations[0] == pytest.approx(lowest) and elevations[-1] == pytest.approx(highest), name
        assert repr(lidar).startswith(f"Lidar.preset('{name}'")
    np.testing.assert_allclose(np.diff(Lidar.preset("VLP-16").elevations_deg), 2.0)
    np.testing.assert_allclose(np.diff(Lidar.preset("HDL-32E").elevations_deg), 4 / 3, atol=0.011)
    spacing = np.diff(Lidar.preset("HDL-64E").elevations_deg)
    np.testing.assert_allclose(spacing[:32], 0.5)  # lower block, and the gap up to the upper block
    np.testing.assert_allclose(spacing[32:], 1 / 3)  # upper block
    assert np.diff(Lidar.preset("VLS-128").elevations_deg).min() == pytest.approx(0.11)
    np.testing.assert_allclose(np.diff(Lidar.preset("OS1-128").elevations_deg), 45 / 127)
    # Names ignore case, hyphens and underscores; options pass through.
    lidar = Lidar.preset("hdl_32e", azimuth_steps=100, max_range=80.0, echoes=2)
    assert lidar.shape == (32, 100) and lidar.tmax == 80.0 and lidar.max_range == 80.0 and lidar.echoes == 2
    assert Lidar.preset("vlp16").shape == (16, 1800)
    assert Lidar.preset("OS1-128").shape == (128, 1024)


# --------------------------------------------------------------------------------------------------
# Common interface


def every_sensor():
    return [
        PinholeCamera(7, 5, fov_deg=70, eye=[1, 2, 3], target=[0, 0, 0], up=[0, 0, 1], tmin=0.5, tmax=9.0),
        PinholeCamera(6, 4, K=INTRINSIC_CASES[1][0], extrinsic=INTRINSIC_CASES[1][1]),
        OrthographicCamera(5, 3, eye=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0], extent=2.0, tmax=100.0),
        Lidar([-10, 0, 10], 8, min_range=0.3, max_range=50.0, echoes=2),
        Lidar.preset("VLP-16", azimuth_steps=12, pose=rigid(4)),
    ]


@pytest.mark.parametrize("sensor", every_sensor(), ids=lambda s: type(s).__name__)
def test_interface(sensor):
    rows, columns = sensor.shape
    assert len(sensor) == rows * columns
    for array in sensor.rays():
        assert array.dtype == np.float32 and array.shape == (rows, columns, 3)
        assert array.flags.c_contiguous and np.all(np.isfinite(array))
    generator = sensor._generator()
    assert set(generator) == {"kind", "origin", "axes", "columns", "rows", "tmin", "tmax", "table", "echoes"}
    assert (generator["rows"], generator["columns"]) == sensor.shape
    assert generator["echoes"] == sensor.echoes
    assert (generator["tmin"], generator["tmax"]) == (sensor.tmin, sensor.tmax)
    assert generator["origin"].dtype == np.float32 and generator["origin"].shape == (3,)
    assert generator["axes"].dtype == np.float32 and generator["axes"].shape == (3, 3)
    assert generator["table"].dtype == np.float32 and generator["table"].ndim == 1
    expected_table = 2 * (rows + columns) if isinstance(sensor, Lidar) else 0
    assert generator["table"].size == expected_table
    assert all(type(generator[key]) is int for key in ("kind", "columns", "rows", "echoes"))
    assert all(type(generator[key]) is float for key in ("tmin", "tmax"))
    # repr rebuilds the sensor.
    rebuilt = eval(repr(sensor), {"PinholeCamera": PinholeCamera, "OrthographicCamera": OrthographicCamera,
                                  "Lidar": Lidar, "inf": math.inf})  # fmt: skip
    for a, b in zip(sensor.rays(), rebuilt.rays()):
        np.testing.assert_array_equal(a, b)


def test_cameras_record_one_echo_and_keep_their_parameters():
    camera = PinholeCamera(7, 5, fov_deg=70, eye=[1, 2, 3], target=[0, 0, 0], up=[0, 0, 1], tmin=0.5, tmax=9.0)
    assert camera.echoes == 1 and (camera.tmin, camera.tmax) == (0.5, 9.0)
    assert camera.fov_deg == 70 and camera.eye.tolist() == [1, 2, 3] and camera.target.tolist() == [0, 0, 0]
    intrinsic = PinholeCamera(6, 4, K=np.eye(3) * [2, 2, 1], extrinsic=np.eye(4))
    assert intrinsic.fov_deg is None and intrinsic.eye is None and intrinsic.up is None


def test_the_module_does_not_need_the_compiled_core():
    script = (
        "import importlib.util, sys\n"
        "sys.modules['vkray'] = None\n"
        "sys.modules['vkray._core'] = None\n"
        f"spec = importlib.util.spec_from_file_location('standalone_sensors', {str(SENSORS_PY)!r})\n"
        "module = importlib.util.module_from_spec(spec)\n"
        "spec.loader.exec_module(module)\n"
        "print(module.Lidar.preset('VLP-16').shape)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "(16, 1800)"
    assert importlib.util.find_spec("vkray.sensors") is not None


# --------------------------------------------------------------------------------------------------
# Validation: each error names the parameter.

LOOK = dict(fov_deg=60, eye=[0, 0, 0], target=[1, 0, 0], up=[0, 0, 1])
INTR = dict(K=[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]], extrinsic=np.eye(4))
ORTHO = dict(eye=[0, 0, 0], target=[1, 0, 0], up=[0, 0, 1], extent=2.0)


def look(**changes):
    """An 8x6 look-at pinhole camera with some arguments changed."""
    return PinholeCamera(8, 6, **{**LOOK, **changes})


def intr(**changes):
    """An 8x6 intrinsic-form pinhole camera with some arguments changed."""
    return PinholeCamera(8, 6, **{**INTR, **changes})


def ortho(**changes):
    """An 8x6 orthographic camera with some arguments changed."""
    return OrthographicCamera(8, 6, **{**ORTHO, **changes})


def with_entry(matrix, index, value):
    matrix = np.array(matrix, np.float64)
    matrix[index] = value
    return matrix


E4 = np.eye(4)
BAD = [
    # sizes
    (lambda: PinholeCamera(0, 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera(-4, 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera(2.5, 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera(640.0, 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera(True, 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera("640", 10, **LOOK), "width must be a positive integer"),
    (lambda: PinholeCamera(10, 0, **INTR), "height must be a positive integer"),
    (lambda: PinholeCamera(10, -1, **INTR), "height must be a positive integer"),
    (lambda: OrthographicCamera(10, 1.5, **ORTHO), "height must be a positive integer"),
    (lambda: OrthographicCamera(0, 3, **ORTHO), "width must be a positive integer"),
    (lambda: PinholeCamera(2**24 + 1, 1, **LOOK), "width must be at most 16777216"),
    (lambda: PinholeCamera(2**16, 2**16, **LOOK), r"65536 = 4294967296 rays, more than 2\*\*32 - 1"),
    (lambda: OrthographicCamera(2**16, 2**16, **ORTHO), r"more than 2\*\*32 - 1"),
    (lambda: Lidar([0.0, 1.0], 2**31), r"more than 2\*\*32 - 1"),
    (lambda: Lidar([0.0], 2**32), r"more than 2\*\*32 - 1"),
    (lambda: Lidar([0.0], 0), "azimuth_steps must be a positive integer"),
    (lambda: Lidar([0.0], -360), "azimuth_steps must be a positive integer"),
    (lambda: Lidar([0.0], 360.0), "azimuth_steps must be a positive integer"),
    (lambda: Lidar.preset("VLP-16", azimuth_steps=0), "azimuth_steps must be a positive integer"),
    # non-finite inputs
    (lambda: intr(K=with_entry(INTR["K"], (0, 0), np.nan)), "K must be finite"),
    (lambda: intr(extrinsic=with_entry(E4, (1, 3), np.inf)), "extrinsic must be finite"),
    (lambda: look(eye=[0, np.nan, 0]), "eye must be finite"),
    (lambda: look(target=[np.inf, 0, 0]), "target must be finite"),
    (lambda: look(up=[0, 0, np.nan]), "up must be finite"),
    (lambda: ortho(eye=[np.nan, 0, 0]), "eye must be finite"),
    (lambda: ortho(up=[np.inf, 0, 1]), "up must be finite"),
    (lambda: Lidar([0.0], 8, pose=with_entry(E4, (0, 3), np.nan)), "pose must be finite"),
    (lambda: Lidar([0.0, np.nan], 8), "elevations_deg must be finite"),
    (lambda: Lidar([np.inf], 8), "elevations_deg must be finite"),
    (lambda: Lidar([0.0], 8, azimuth_start_deg=np.nan), "azimuth_start_deg must be finite"),
    # K
    (lambda: intr(K=np.zeros((3, 3))), "K is singular"),
    (lambda: intr(K=[[1, 2, 3], [2, 4, 6], [0, 0, 1]]), "K is singular"),
    (lambda: intr(K=np.eye(4)), r"K must have shape \(3, 3\), got shape \(4, 4\)"),
    (lambda: intr(K=[1, 2, 3]), r"K must have shape \(3, 3\)"),
    (lambda: intr(K=np.eye(3) * 1j), "K must hold real numbers"),
    (lambda: intr(K=[["a"] * 3] * 3), "K must hold real numbers"),
    (lambda: intr(K=[[1, 0], [0, 1, 0], [0, 0, 1]]), "K must be an array"),
    (lambda: intr(K=np.eye(3) * 1e-40), "too large for float32"),
    # extrinsic and pose
    (lambda: intr(extrinsic=np.eye(3)), r"extrinsic must have shape \(4, 4\)"),
    (lambda: intr(extrinsic=np.diag([1.1, 1, 1, 1])), r"extrinsic\[:3, :3\] is not a rotation: it is not orthonormal"),
    (lambda: intr(extrinsic=np.diag([1, 1, -1, 1])), r"extrinsic\[:3, :3\] is not a rotation: its determinant"),
    (lambda: intr(extrinsic=with_entry(E4, (3, 0), 1)), r"extrinsic must have last row \[0, 0, 0, 1\]"),
    (lambda: intr(extrinsic=with_entry(E4, (3, 3), 2)), "extrinsic must have last row"),
    (lambda: Lidar([0.0], 8, pose=np.diag([1, -1, 1, 1])), r"pose\[:3, :3\] is not a rotation"),
    (lambda: Lidar([0.0], 8, pose=np.diag([1, 1, 1.00001, 1])), r"pose\[:3, :3\] is not a rotation"),
    (lambda: Lidar([0.0], 8, pose=with_entry(E4, (3, 2), 0.5)), "pose must have last row"),
    (lambda: Lidar([0.0], 8, pose=np.eye(3)), r"pose must have shape \(4, 4\)"),
    # look-at
    (lambda: look(fov_deg=0), r"fov_deg must be in \(0, 180\)"),
    (lambda: look(fov_deg=180), r"fov_deg must be in \(0, 180\)"),
    (lambda: look(fov_deg=-30), r"fov_deg must be in \(0, 180\)"),
    (lambda: look(fov_deg=np.nan), "fov_deg must be finite"),
    (lambda: look(fov_deg="60"), "fov_deg must be a real number"),
    (lambda: look(target=[0, 0, 0]), "eye and target must differ"),
    (lambda: ortho(eye=[1, 0, 0]), "eye and target must differ"),
    (lambda: look(up=[2, 0, 0]), "up must not be parallel to the view direction"),
    (lambda: look(up=[-1, 0, 1e-9]), "up must not be parallel"),
    (lambda: ortho(up=[1, 0, 0]), "up must not be parallel"),
    (lambda: look(up=[0, 0, 0]), "up must be a nonzero vector"),
    (lambda: look(eye=[0, 0]), r"eye must have shape \(3,\)"),
    (lambda: ortho(target=[[1, 0, 0]]), r"target must have shape \(3,\)"),
    # extent
    (lambda: ortho(extent=0.0), "extent must be > 0"),
    (lambda: ortho(extent=-2.0), "extent must be > 0"),
    (lambda: ortho(extent=np.nan), "extent must be finite"),
    (lambda: ortho(extent=np.inf), "extent must be finite"),
    (lambda: ortho(eye=[1e39, 0, 0], target=[0, 0, 0]), "overflows float32"),
    # elevations
    (lambda: Lidar([0.0, 90.5], 8), r"elevations_deg must lie within \[-90, 90\]: channel 1 is 90.5"),
    (lambda: Lidar([-91.0], 8), r"within \[-90, 90\]"),
    (lambda: Lidar([], 8), "elevations_deg is empty"),
    (lambda: Lidar(np.zeros((2, 2)), 8), "elevations_deg must be 1-D"),
    (lambda: Lidar(5.0, 8), "elevations_deg must be 1-D"),
    (lambda: Lidar(["up"], 8), "elevations_deg must hold real numbers"),
    # ranges
    (lambda: Lidar([0.0], 8, min_range=-1.0), "min_range must be >= 0"),
    (lambda: Lidar([0.0], 8, min_range=5.0, max_range=5.0), "max_range must be greater than min_range"),
    (lambda: Lidar([0.0], 8, min_range=5.0, max_range=2.0), "max_range must be greater than min_range"),
    (lambda: Lidar([0.0], 8, max_range=0.0), "max_range must be greater than min_range"),
    (lambda: Lidar([0.0], 8, min_range=math.inf), "max_range must be greater than min_range"),
    (lambda: Lidar([0.0], 8, min_range=np.nan), "min_range must not be NaN"),
    (lambda: Lidar([0.0], 8, max_range=np.nan), "max_range must not be NaN"),
    (lambda: Lidar.preset("VLP-16", max_range=-3.0), "max_range must be greater than min_range"),
    (lambda: look(tmin=-0.1), "tmin must be >= 0"),
    (lambda: look(tmin=2.0, tmax=1.0), "tmax must be greater than tmin"),
    (lambda: ortho(tmax=np.nan), "tmax must not be NaN"),
    (lambda: ortho(tmin=np.nan), "tmin must not be NaN"),
    # echoes
    (lambda: Lidar([0.0], 8, echoes=0), "echoes must be a positive integer"),
    (lambda: Lidar([0.0], 8, echoes=-2), "echoes must be a positive integer"),
    (lambda: Lidar([0.0], 8, echoes=1.5), "echoes must be a positive integer"),
    # the two pinhole forms
    (lambda: intr(fov_deg=60), "either K and extrinsic, or fov_deg, eye, target and up, not a mix"),
    (lambda: PinholeCamera(8, 6, K=INTR["K"], eye=[0, 0, 0]), "not a mix: got K, eye"),
    (lambda: look(extrinsic=E4), "not a mix"),
    (lambda: PinholeCamera(8, 6, K=INTR["K"]), "given K is missing extrinsic"),
    (lambda: PinholeCamera(8, 6, extrinsic=E4), "given extrinsic is missing K"),
    (lambda: PinholeCamera(8, 6, fov_deg=60, eye=[0, 0, 0]), "given fov_deg, eye is missing target, up"),
    (lambda: PinholeCamera(8, 6, eye=[0, 0, 0], target=[1, 0, 0], up=[0, 0, 1]), "is missing fov_deg"),
    (lambda: PinholeCamera(8, 6), "needs either K and extrinsic, or fov_deg, eye, target and up"),
    # presets
    (lambda: Lidar.preset("HDL-128"), "unknown lidar preset 'HDL-128': the choices are VLP-16, HDL-32E, HDL-64E, VLS"),
    (lambda: Lidar.preset(""), "unknown lidar preset"),
    (lambda: Lidar.preset(16), "preset name must be a string"),
]


@pytest.mark.parametrize("make, match", BAD, ids=[match[:40] for _, match in BAD])
def test_validation(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_nearly_parallel_up_is_accepted_above_the_threshold():
    camera = look(up=[1, 0, 1e-4])
    assert np.all(np.isfinite(camera.rays()[1]))

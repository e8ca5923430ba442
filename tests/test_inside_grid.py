"""`contains` at the exact tier through a scene's inside grid (src/scene/inside_grid.rs): a query
of 32768 points or more builds it (on a GPU, the scene's second such query), and then every query
of any size answers most points with one lookup, the rest by short rays to the nearest region's
answer (on a GPU, by the GPU's own exact test). The grid must change no answer:
each test holds the exact tier against the reference tier (the host's f64 test, which never uses
the grid) or against an analytic oracle, on every engine, with points near and on the surfaces,
far from the origin, under transforms and mirrors, across scene updates and from several threads.
"""

import threading

import numpy as np
import pytest
import trimesh

import vkray

# A query of this many points builds the grid (GRID_MIN_POINTS in src/trace/grid_contains.rs).
GRID_POINTS = 1 << 15


def hard_points(vertices: np.ndarray, faces: np.ndarray, n: int = 40000, seed: int = 0) -> np.ndarray:
    """Uniform points in the box grown by 10% per side, points within 1e-3 to 1e-12 of the
    surface on both sides, every vertex, and edge midpoints: at least GRID_POINTS in all."""
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0), vertices.max(0)
    grow = 0.1 * (hi - lo)
    uniform = rng.uniform(lo - grow, hi + grow, (n, 3))
    tm = trimesh.Trimesh(vertices, faces, process=False)
    on, index = trimesh.sample.sample_surface(tm, 6000, seed=seed)
    size = float(np.ptp(vertices, axis=0).max())
    offsets = size * 10.0 ** rng.uniform(-12, -3, (len(on), 1)) * rng.choice([-1.0, 1.0], (len(on), 1))
    near = on + offsets * tm.face_normals[index]
    edges = vertices[faces[:, [0, 1, 2]]] + vertices[faces[:, [1, 2, 0]]]
    midpoints = 0.5 * edges.reshape(-1, 3)[rng.choice(3 * len(faces), 2000)]
    points = np.concatenate([uniform, near, on, vertices, midpoints])
    assert len(points) >= GRID_POINTS
    return points


def mesh_of(name: str):
    v, f = vkray.data.load_mesh(name)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def on_host(device) -> bool:
    """Whether `device` runs queries on the host's cores (the CPU engine, Vulkan on a CPU): there
    the first large query of a scene builds the grid, on a GPU the second."""
    return device.info.device_type == "cpu"


def assert_grid_used(device, scene, method: str) -> None:
    """After a scene's first large query: on the host's engines it kept a grid that decides most
    cells; on a GPU none yet."""
    grid = scene._core.inside_grid(method == "winding")
    if not on_host(device):
        assert grid is None
        return
    assert_grid_decides(grid)


def assert_grid_decides(grid) -> None:
    assert grid is not None and grid["cells"] > 100_000 and grid["regions"] >= 1
    assert grid["undecided"] < 0.1, grid


def assert_same(exact: np.ndarray, reference: np.ndarray, what: str) -> None:
    wrong = np.flatnonzero(exact != reference)
    assert wrong.size == 0, f"{what}: {wrong.size} points differ from the reference tier, first rows {wrong[:8]}"


@pytest.mark.parametrize(
    "name, method",
    [("fandisk", "parity"), ("fandisk", "winding"), ("cow", "parity"), ("stanford-bunny", "winding")],
)
def test_grid_answers_equal_the_reference_tier(device, name, method):
    v, f = mesh_of(name)
    scene = device.scene([device.mesh(v, f)])
    points = hard_points(v, f)
    exact = scene.contains(points, method=method)
    assert_grid_used(device, scene, method)
    reference = scene.contains(points, method=method, precision="reference")
    assert_same(exact, reference, f"{name} by {method}")
    # The grid built above answers small queries too (fewer points than would build it).
    assert_same(scene.contains(points[-3000:], method=method), reference[-3000:], "a small query after")
    # Sanity: the sets are neither all inside nor all outside.
    assert 0.05 < exact[:40000].mean() < 0.9


@pytest.mark.parametrize(
    "name, method", [("fandisk", "parity"), ("stanford-bunny", "winding"), ("cow", "winding")]
)
def test_grid_with_the_engines_own_test_near_surfaces(device, monkeypatch, name, method):
    """`VKRAY_CONTAINS_GRID=engine`, the way a GPU uses the grid, on every engine, the points
    marked on the host's cores (`VKRAY_GRID_MARKS=host`; a GPU's default reads the grid in its own
    ray pass, `test_contains_reads_the_grid_on_the_device`): the first large query builds it and
    the engine's own exact test answers the points of undecided cells (and, by winding number, of
    the cells near a cap's holes), not the host's short rays."""
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
    monkeypatch.setenv("VKRAY_GRID_MARKS", "host")
    v, f = mesh_of(name)
    scene = device.scene([device.mesh(v, f)])
    points = hard_points(v, f, seed=3)
    scene.intersect(points[:7], np.ones((7, 3)))
    exact = scene.contains(points, method=method)
    assert_grid_decides(scene._core.inside_grid(method == "winding"))
    # The engine's profile counts the points it answered: those of undecided cells only.
    assert 7 < device.last_trace_profile["rays"] < len(points) - 20000
    reference = scene.contains(points, method=method, precision="reference")
    assert_same(exact, reference, f"{name} by {method}, undecided points by the engine")
    assert_same(scene.contains(points[-3000:], method=method), reference[-3000:], "a small query after")
    assert 0.05 < exact[:40000].mean() < 0.9


def on_cell_faces(points: np.ndarray, grid: dict, seed: int = 11) -> np.ndarray:
    """`points` with one coordinate each moved onto the nearest face between two of the grid's
    cells (its corner plus a whole number of cells, in f64): where a device must find the very
    cell the host finds, or read a neighbour's answer."""
    rng = np.random.default_rng(seed)
    corner, cell = np.asarray(grid["corner"]), grid["cell"]
    moved = points.copy()
    axis = rng.integers(0, 3, len(points))
    rows = np.arange(len(points))
    k = np.round((points[rows, axis] - corner[axis]) / cell)
    moved[rows, axis] = corner[axis] + k * cell
    return moved


def scene_with_its_grid(device, v: np.ndarray, f: np.ndarray, method: str, seed: int):
    """A scene of the mesh whose first large query (`VKRAY_CONTAINS_GRID=engine`) built its
    inside grid, and `hard_points` with 20,000 of them moved onto the faces between its cells."""
    scene = device.scene([device.mesh(v, f)])
    points = hard_points(v, f, seed=seed)
    scene.contains(points, method=method)
    grid = scene._core.inside_grid(method == "winding")
    assert_grid_decides(grid)
    return scene, np.concatenate([points, on_cell_faces(points[:20000], grid)])


@pytest.mark.parametrize("name, method", [("fandisk", "parity"), ("stanford-bunny", "winding")])
def test_signed_distances_through_the_grid(device, monkeypatch, name, method):
    """On a GPU a signed distance's sign rays skip the points whose cells the scene's inside grid
    decides (exact.glsl grid_crossings: the host's cell arithmetic in f64): every sign equals the
    reference tier's, for points near and on the surface and on the faces between cells."""
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
    v, f = mesh_of(name)
    scene, points = scene_with_its_grid(device, v, f, method, seed=7)
    signed = scene.signed_distance(points, method=method, precision="exact")
    reference = scene.signed_distance(points, method=method, precision="reference")
    wrong = np.flatnonzero(np.signbit(signed) != np.signbit(reference))
    assert wrong.size == 0, f"{name}: {wrong.size} signs differ from the reference tier, first rows {wrong[:8]}"
    assert 0.05 < np.signbit(signed[:40000]).mean() < 0.9
    np.testing.assert_allclose(np.abs(signed), np.abs(reference), rtol=1e-12, atol=0)
    # Several threads at once on a scene of the same mesh whose grid is on the device yet (each
    # may copy it there; the first copy kept): every thread's signs equal the reference tier's.
    scene = device.scene([device.mesh(v, f)])
    scene.contains(points, method=method)
    found = [None] * 4

    def sign(k: int) -> None:
        found[k] = scene.signed_distance(points[k::4], method=method, precision="exact")

    threads = [threading.Thread(target=sign, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(4):
        np.testing.assert_array_equal(np.signbit(found[k]), np.signbit(reference[k::4]), err_msg=f"thread {k}")


@pytest.mark.parametrize("name, method", [("fandisk", "parity"), ("stanford-bunny", "winding")])
def test_contains_reads_the_grid_on_the_device(device, monkeypatch, name, method):
    """`contains` on a GPU reads the scene's inside grid in the sign's ray pass (the points sorted
    by cell, a decided cell's points casting no ray, sign_points.comp writing a byte a point;
    trace/vulkan/inside_points.rs) rather than marking every point on the host's cores: every
    answer equals the reference tier's, for f64 and f32 points near and on the surface and on the
    faces between cells, in chunks and from several threads; a point that is not finite is named."""
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
    monkeypatch.setenv("VKRAY_GRID_MARKS", "device")
    v, f = mesh_of(name)
    scene, points = scene_with_its_grid(device, v, f, method, seed=11)
    reference = scene.contains(points, method=method, precision="reference")
    assert 0.05 < reference.mean() < 0.9
    for kind in (np.float64, np.float32):
        p = points.astype(kind)
        expected = reference if kind is np.float64 else scene.contains(p, method=method, precision="reference")
        inside = scene.contains(p, method=method)
        if device.backend != "cpu":
            # Every point went through the GPU's ray pass (the host's marks would send only the
            # points of undecided cells).
            assert device.last_trace_profile["rays"] == len(p)
        wrong = np.flatnonzero(inside != expected)
        assert wrong.size == 0, f"{name} {kind.__name__}: {wrong.size} answers differ, first rows {wrong[:8]}"
    # Chunks of 10,000 points (each its own rows of the answers and of the CPU's points).
    monkeypatch.setenv("VKRAY_POINT_CHUNK", "10000")
    np.testing.assert_array_equal(scene.contains(points, method=method), reference)
    monkeypatch.delenv("VKRAY_POINT_CHUNK")
    bad = points.copy()
    bad[40001, 1] = np.inf
    with pytest.raises(ValueError, match="points row 40001 is not finite"):
        scene.contains(bad, method=method)
    found = [None] * 4

    def ask(k: int) -> None:
        found[k] = scene.contains(points[k::4], method=method)

    threads = [threading.Thread(target=ask, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(4):
        np.testing.assert_array_equal(found[k], reference[k::4], err_msg=f"thread {k}")


def hole_points(vertices: np.ndarray, faces: np.ndarray, n: int = 40000, seed: int = 5) -> np.ndarray:
    """Points about a mesh's holes, where the caps over them add their winding number: about
    boundary vertices in every direction (the caps' fans span the holes from their mean corners),
    half at 1e-4 to 5% of the mesh's size (log-uniform), half at up to 25% (uniform)."""
    rng = np.random.default_rng(seed)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, inverse, counts = np.unique(np.sort(edges, 1), axis=0, return_inverse=True, return_counts=True)
    corners = np.unique(edges[counts[inverse.ravel()] == 1])
    size = float(np.ptp(vertices, axis=0).max())
    at = vertices[rng.choice(corners, n)]
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    near = 10.0 ** rng.uniform(-4, np.log10(0.05), (n, 1))
    wide = rng.uniform(0, 0.25, (n, 1))
    return at + direction * size * np.where(np.arange(n)[:, None] % 2 == 0, near, wide)


@pytest.mark.parametrize("way", ["host", "engine"])
def test_grid_near_the_caps_over_holes(device, monkeypatch, way):
    """The bunny's holes: the cells about their caps' fans are decided where a bound on the caps'
    winding number keeps it below the limit (`CapGeometry::winding_stays_within`), which leaves
    few cells to the points' own test; every point about the holes is answered as the reference
    tier answers it, the undecided ones by the host's short rays or by the engine's own test."""
    if way == "engine":
        monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
        # The points marked on the host's cores, so that the engine's profile counts the points
        # of undecided cells alone (a GPU's own ray pass reads the grid for every point).
        monkeypatch.setenv("VKRAY_GRID_MARKS", "host")
    v, f = mesh_of("stanford-bunny")
    scene = device.scene([device.mesh(v, f)])
    points = hole_points(v, f)
    if way == "engine" or on_host(device):
        exact = scene.contains(points, method="winding")
        if way == "engine":
            # The engine answered the undecided points only: 67% of these (79% where the area's
            # bound alone decided the cells about the caps).
            assert device.last_trace_profile["rays"] < 0.72 * len(points)
    else:
        scene.contains(points, method="winding")
        exact = scene.contains(points, method="winding")
    grid = scene._core.inside_grid(True)
    assert_grid_decides(grid)
    # The area's bound alone left 6.9% of the cells near the caps.
    assert 0 < grid["near_caps"] < 0.02, grid
    reference = scene.contains(points, method="winding", precision="reference")
    assert_same(exact, reference, f"about the bunny's holes ({way})")
    assert 0.05 < exact.mean() < 0.95


def test_grid_checks_the_points_and_puts_far_ones_outside(device, monkeypatch):
    """The grid's one pass over the points checks them (a NaN or an infinity is refused, naming
    its row, as without the grid) and answers points far beyond the scene, even beyond float32's
    range, outside; points inside keep their answers."""
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
    v, f = mesh_of("fandisk")
    scene = device.scene([device.mesh(v, f)])
    points = hard_points(v, f, seed=6)
    reference = scene.contains(points, precision="reference")
    assert_same(scene.contains(points), reference, "fandisk")
    assert_grid_decides(scene._core.inside_grid(False))
    for bad in (np.nan, np.inf, -np.inf):
        broken = points.copy()
        broken[40001, 1] = bad
        with pytest.raises(ValueError, match="points row 40001 is not finite"):
            scene.contains(broken)
    far = points.copy()
    far[[5, 6, 7, 8]] = [[1e300, 0.0, 0.0], [0.0, -1e39, 0.0], [0.0, 0.0, 3e38], [-1e20, 1e20, 1e20]]
    expected = reference.copy()
    expected[[5, 6, 7, 8]] = False
    assert_same(scene.contains(far), expected, "far points")
    far32 = points.astype(np.float32)
    far32[[5, 6, 7, 8]] = [[3.4e38, 0.0, 0.0], [0.0, -3e38, 0.0], [0.0, 0.0, 3e38], [-1e20, 1e20, 1e20]]
    assert_same(scene.contains(far32), scene.contains(far32, precision="reference"), "float32")


def test_the_gpus_way_builds_the_grid_at_the_second_large_query(device, monkeypatch):
    """A GPU's grid (on the host's engines, `VKRAY_CONTAINS_GRID=gpu`): its build (several GPU
    queries' time) waits for the scene's second query of 32768 points or more, and again after
    an update drops it; every answer equals the reference tier's, and the points of undecided
    cells go to the engine's own exact test (its profile counts them)."""
    if on_host(device):
        monkeypatch.setenv("VKRAY_CONTAINS_GRID", "gpu")
    # Marked on the host's cores: the engine's profile then counts the undecided points alone.
    monkeypatch.setenv("VKRAY_GRID_MARKS", "host")
    v, f = mesh_of("stanford-bunny")
    scene = device.scene([device.mesh(v, f)], allow_update=True)
    points = hard_points(v, f, seed=5)
    reference = scene.contains(points, method="winding", precision="reference")
    for when in ("built", "updated"):
        assert_same(scene.contains(points, method="winding"), reference, f"the first query once {when}, no grid")
        assert scene._core.inside_grid(True) is None
        scene.intersect(points[:7], np.ones((7, 3)))
        assert_same(scene.contains(points, method="winding"), reference, f"the second query once {when}, a grid")
        assert_grid_decides(scene._core.inside_grid(True))
        assert 7 < device.last_trace_profile["rays"] < len(points) - 20000, "the undecided points by the engine"
        scene.update()
        assert scene._core.inside_grid(True) is None


def convex_inside(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, margin: float) -> np.ndarray:
    """Inside a convex closed mesh (outward faces): on the inner side of every face's plane; NaN
    where a point lies within `margin` of a plane that decides it."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    heights = np.einsum("fk,pk->pf", normals, points) - np.einsum("fk,fk->f", normals, a)[None, :]
    highest = heights.max(axis=1)
    answer = (highest <= 0).astype(float)
    answer[np.abs(highest) <= margin] = np.nan
    return answer


@pytest.mark.parametrize("offset", [0.0, 1e7])
def test_grid_answers_a_convex_mesh_analytically(device, offset):
    """An icosphere, near the origin and 1e7 away: inside exactly where every face's plane has the
    point on its inner side (points within 1e-6 of a deciding plane are left out)."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = np.asarray(sphere.vertices, np.float64) + offset
    f = np.asarray(sphere.faces, np.int64)
    scene = device.scene([device.mesh(v, f)])
    rng = np.random.default_rng(4)
    points = rng.uniform(-1.2, 1.2, (GRID_POINTS + 8000, 3)) + offset
    truth = convex_inside(v - offset, f, points - offset, 1e-6)
    for method in ("parity", "winding"):
        inside = scene.contains(points, method=method)
        decided = ~np.isnan(truth)
        assert decided.mean() > 0.99
        wrong = np.flatnonzero(inside[decided] != truth[decided])
        assert wrong.size == 0, f"{method}: {wrong.size} points answered against the planes"


@pytest.mark.parametrize("name, method", [("stanford-bunny", "winding"), ("cow", "parity")])
def test_grid_of_one_turned_stretched_mirrored_instance_far_away(device, name, method):
    """One instance turned, stretched along one axis, mirrored and moved 1e7 away: the grid's own
    short rays (parity), or its counts and the mirrored caps (winding), against the reference."""
    v, f = mesh_of(name)
    transform = np.eye(4)
    turn = trimesh.transformations.rotation_matrix(0.9, [0.2, 1.0, 0.4])[:3, :3]
    transform[:3, :3] = turn @ np.diag([-1.0, 1.7, 0.8])
    transform[:3, 3] = [1e7, -2e7, 5e6]
    scene = device.scene([vkray.Instance(device.mesh(v, f), transform)])
    placed = v @ transform[:3, :3].T + transform[:3, 3]
    points = hard_points(placed, f, seed=8)
    exact = scene.contains(points, method=method)
    assert_grid_used(device, scene, method)
    assert_same(exact, scene.contains(points, method=method, precision="reference"), f"{name} placed far")
    assert 0.02 < exact[:40000].mean() < 0.9


def test_grid_of_placed_and_mirrored_instances(device):
    """Two instances of a closed mesh, one turned, one mirrored and moved, overlapping: both
    methods against the reference tier."""
    v, f = mesh_of("cow")
    mesh = device.mesh(v, f)
    size = float(np.ptp(v, axis=0).max())
    turn = np.eye(4)
    turn[:3, :3] = trimesh.transformations.rotation_matrix(0.7, [0.3, 1.0, 0.2])[:3, :3]
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[:3, 3] = [0.4 * size, 0.1 * size, 0.0]
    scene = device.scene([vkray.Instance(mesh, turn), vkray.Instance(mesh, mirror)])
    both = np.concatenate([v, (v * [-1, 1, 1]) + mirror[:3, 3]])
    points = hard_points(both, np.concatenate([f, f + len(v)]), seed=2)
    for method in ("parity", "winding"):
        exact = scene.contains(points, method=method)
        assert_same(exact, scene.contains(points, method=method, precision="reference"), method)


def test_grid_follows_the_scene_update(device):
    """A grid built before `Scene.update` moved the instance answers nothing after it."""
    v, f = mesh_of("fandisk")
    mesh = device.mesh(v, f)
    scene = device.scene([vkray.Instance(mesh)], allow_update=True)
    points = hard_points(v, f, seed=3)
    first = scene.contains(points)
    moved = np.eye(4)
    moved[:3, 3] = 0.3 * np.ptp(v, axis=0)
    scene.update(transforms=moved[None])
    after = scene.contains(points)
    assert_same(after, scene.contains(points, precision="reference"), "after the update")
    assert (after != first).sum() > 100


def test_grid_after_a_mesh_update_raises_until_the_scene_updates(device):
    v, f = mesh_of("cow")
    mesh = device.mesh(v, f, allow_update=True)
    scene = device.scene([mesh], allow_update=True)
    points = hard_points(v, f, seed=5)
    scene.contains(points)  # builds the grid
    mesh.update(v * 0.5)
    with pytest.raises(ValueError, match="update"):
        scene.contains(points[:10])
    scene.update()
    assert_same(scene.contains(points), scene.contains(points, precision="reference"), "after the mesh update")


@pytest.mark.parametrize("way", ["the engine's", "a GPU's"])
def test_grid_built_by_several_threads_at_once(device, monkeypatch, way):
    """Four threads ask a fresh scene at once (on the host's engines each may build a grid, one
    is kept; the GPU's way builds one at a time, the others going on without it): every answer
    is the reference tier's, and a grid is kept."""
    if way == "a GPU's" and on_host(device):
        monkeypatch.setenv("VKRAY_CONTAINS_GRID", "gpu")
    v, f = mesh_of("stanford-bunny")
    scene = device.scene([device.mesh(v, f)])
    points = hard_points(v, f, n=30000, seed=6)
    reference = scene.contains(points, method="winding", precision="reference")
    answers: list = [None] * 4
    errors: list = []

    def ask(k: int) -> None:
        try:
            answers[k] = scene.contains(points, method="winding")
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=ask, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    for k, a in enumerate(answers):
        assert_same(a, reference, f"thread {k}")
    if on_host(device) or way == "a GPU's":
        # Four large queries (and the reference tier's, which counts none): a build by now.
        assert_grid_decides(scene._core.inside_grid(True))

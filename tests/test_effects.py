"""Effects a scene calls for: opacity (cut-outs, the threshold rule, transmittance), the variant
each query runs (`Scene.explain`), and sensors whose rays the shaders generate. Oracles: Embree and
the reference tier on the mesh without the triangles that let rays through, numpy products over
brute-force hits, and the sensors' own numpy rays."""

import threading

import numpy as np
import pytest

import oracle
import vkray

GPU_TIERS = ("fast", "exact")
ALL_TIERS = ("fast", "refined", "exact", "reference")


@pytest.fixture(scope="module")
def bunny():
    return oracle.load_mesh("stanford-bunny")


def rays_at(vertices, n=3000, seed=0):
    origins, directions = oracle.random_rays(vertices, n, seed=seed)
    eye, camera = oracle.camera_rays(vertices, 48, 48)
    return np.vstack([origins, np.broadcast_to(eye, camera.shape)]), np.vstack([directions, camera])


def random_opacity(faces, seed, cut=0.3):
    """Opacity per triangle: a fraction `cut` of cut-outs (0), the rest random in (0, 1]."""
    rng = np.random.default_rng(seed)
    opacity = rng.uniform(0.05, 1.0, len(faces))
    opacity[rng.random(len(faces)) < cut] = 0.0
    opacity[rng.random(len(faces)) < 0.3] = 1.0
    return opacity


# --- Opacity -------------------------------------------------------------------------------------


@pytest.mark.parametrize("precision", ALL_TIERS)
def test_cut_outs_are_skipped_as_if_removed_embree(device, bunny, precision):
    """Cut-out triangles (opacity 0) let every ray through: the closest hits are Embree's on the
    mesh without them (to within f32 rounding at edges), and no hit is ever a cut-out."""
    v, f = bunny
    opacity = np.where(np.random.default_rng(1).random(len(f)) < 0.3, 0.0, 1.0)
    keep = np.nonzero(opacity > 0)[0]
    scene = device.scene([device.mesh(v, f, opacity=opacity)])
    o, d = rays_at(v)
    hits = scene.intersect(o, d, precision=precision)
    assert (opacity[hits.prim_id[hits.hit]] > 0).all()
    ray = oracle.embree([(v, f[keep])], o, d)
    expected = np.where(ray["geomID"] >= 0, keep[np.maximum(ray["primID"], 0)], -1)
    assert np.mean(hits.prim_id == expected) > 0.999
    both = hits.hit & (expected >= 0)
    np.testing.assert_allclose(hits.t[both], ray["tfar"][both], rtol=1e-4)
    np.testing.assert_array_equal(scene.occluded(o, d, precision=precision), hits.hit)


@pytest.mark.parametrize("threshold", [0.3, 0.5, 1.0])
def test_threshold_rule_equals_the_mesh_of_solid_triangles(device, bunny, threshold):
    """A triangle stops rays where its opacity reaches opacity_threshold: the exact tier on the
    translucent mesh gives the reference tier's hits on the mesh of only those triangles, in
    every query that stops at triangles (closest, occluded, count, all hits)."""
    v, f = bunny
    opacity = random_opacity(f, seed=2)
    solid = np.nonzero(opacity >= np.float32(threshold))[0]
    translucent = device.scene([device.mesh(v, f, opacity=opacity)])
    reduced = device.scene([device.mesh(v, f[solid])])
    o, d = rays_at(v, 1500)
    got = translucent.intersect(o, d, precision="exact", opacity_threshold=threshold)
    want = reduced.intersect(o, d, precision="reference")
    np.testing.assert_array_equal(got.prim_id, np.where(want.hit, solid[np.maximum(want.prim_id, 0)], -1))
    np.testing.assert_array_equal(got.t, want.t)
    for precision in ("fast", "exact", "reference"):
        occluded = translucent.occluded(o, d, precision=precision, opacity_threshold=threshold)
        assert np.mean(occluded == want.hit) > 0.999
    exact_counts = translucent.count(o, d, precision="exact", opacity_threshold=threshold)
    np.testing.assert_array_equal(exact_counts, reduced.count(o, d, precision="reference"))
    all_hits = translucent.intersect_all(o, d, precision="exact", opacity_threshold=threshold)
    np.testing.assert_array_equal(all_hits.counts, exact_counts)
    assert np.isin(all_hits.prim_id, solid).all()


@pytest.mark.parametrize("precision", ALL_TIERS)
def test_transmittance_is_the_product_over_every_crossing(device, bunny, precision):
    """transmittance = prod(1 - opacity) over every crossing in [tmin, tmax], against numpy over
    brute-force hits (rays whose crossings are all clear of edges, where every tier agrees)."""
    v, f = bunny
    opacity = random_opacity(f, seed=3, cut=0.1)
    scene = device.scene([device.mesh(v, f, opacity=opacity)])
    o, d = rays_at(v, 800, seed=4)
    tmax = np.where(np.arange(len(o)) % 3 == 0, 0.8, np.inf)
    brute = oracle.all_hits_brute(v[f], o, d, tmax=tmax)
    factors = 1.0 - opacity[brute["tri"]].astype(np.float32).astype(np.float64)
    expected = np.ones(len(o))
    np.multiply.at(expected, brute["ray"], factors)
    clear = np.ones(len(o), bool)
    clear[brute["ray"][brute["margin"] < 1e-5]] = False
    got = scene.transmittance(o, d, tmax=tmax, precision=precision)
    assert got.dtype == (np.float32 if precision == "fast" else np.float64)
    assert clear.mean() > 0.9
    rtol = 1e-5 if precision == "fast" else 1e-12
    np.testing.assert_allclose(got[clear], expected[clear], rtol=rtol, atol=1e-12)
    assert ((got >= 0) & (got <= 1)).all()


@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_transmittance_counts_each_crossing_once_at_shared_edges(device, offset):
    """Rays through the vertices and edges a heightfield's triangles share cross its surface once:
    the exact tiers multiply by 1 - opacity once, far from the origin too."""
    vertices, faces, _ = oracle.heightfield(12, seed=5, offset=offset)
    scene = device.scene([device.mesh(vertices, faces, opacity=0.25)])
    targets = oracle.shared_targets(vertices, faces, 12)
    o, d = oracle.rays_through(targets, seed=6)
    for precision in ("exact", "reference"):
        np.testing.assert_array_equal(scene.transmittance(o, d, precision=precision), 0.75)


def test_forced_opaque_instances_block_and_forced_non_opaque_ones_confirm(device, bunny):
    """Instance(opaque=True) blocks wherever its mesh is (its opacity is not read); opaque=False
    sends an opaque mesh's triangles through the opacity path, which confirms them all."""
    v, f = bunny
    opacity = random_opacity(f, seed=7)
    o, d = rays_at(v, 1000)
    plain = device.scene([device.mesh(v, f)])
    forced = device.scene([vkray.Instance(device.mesh(v, f, opacity=opacity), opaque=True)])
    non_opaque = device.scene([vkray.Instance(device.mesh(v, f), opaque=False)])
    want = plain.intersect(o, d, precision="exact")
    for precision in GPU_TIERS + ("reference",):
        np.testing.assert_array_equal(forced.intersect(o, d, precision=precision).prim_id, want.prim_id)
        assert (forced.transmittance(o, d, precision=precision)[want.hit] == 0).all()
        np.testing.assert_array_equal(non_opaque.intersect(o, d, precision=precision).prim_id, want.prim_id)


def test_opacity_per_part_and_bad_opacity(any_device, bunny):
    v, f = bunny
    quad_v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    mesh = any_device.mesh_from_parts([(quad_v, quad_f), (quad_v + [0, 0, 1], quad_f)], opacity=[0.0, None])
    np.testing.assert_array_equal(mesh.opacity, [0, 0, 1, 1])
    scene = any_device.scene([mesh])
    hits = scene.intersect([0.1, 0.2, -1], [0, 0, 1], outputs=["t", "geometry_id"])
    assert hits.t == pytest.approx(2.0) and hits.geometry_id == 1
    assert any_device.mesh(v, f, opacity=1.0).opacity is None
    for bad, message in [
        (1.5, r"opacity\[0\] must be in \[0, 1\]"),
        (np.nan, r"opacity\[0\] must be in \[0, 1\]"),
        (np.ones(3), "one per triangle"),
        ("x", "opacity"),
    ]:
        with pytest.raises((ValueError, TypeError), match=message):
            any_device.mesh(v, f, opacity=bad)
    with pytest.raises(ValueError, match="2 parts"):
        any_device.mesh_from_parts([(quad_v, quad_f), (quad_v, quad_f)], opacity=[0.5])
    for threshold in (0.0, 1.5, np.nan, -1.0):
        with pytest.raises(ValueError, match="opacity_threshold"):
            scene.intersect([0, 0, -1], [0, 0, 1], opacity_threshold=threshold)
    spheres = any_device.scene([any_device.spheres([[0, 0, 0]], 1.0)])
    assert spheres.transmittance([[0, 0, -5], [0, 2, -5]], [0, 0, 1]).tolist() == [0.0, 1.0]


def test_transmittance_and_sensors_from_several_threads(device, bunny):
    """Queries share the scene: four threads, each transmittance and a GPU camera, same answers."""
    v, f = bunny
    scene = device.scene([device.mesh(v, f, opacity=random_opacity(f, seed=8))])
    o, d = rays_at(v, 2000)
    camera = vkray.PinholeCamera(40, 30, fov_deg=50, eye=v.mean(0) + [0, 0, 0.4], target=v.mean(0), up=[0, -1, 0])
    want = (scene.transmittance(o, d, precision="exact"), scene.intersect(camera, outputs=["t"]).t)
    results, errors = [], []

    def work():
        try:
            for _ in range(3):
                results.append((scene.transmittance(o, d, precision="exact"), scene.intersect(camera, outputs=["t"]).t))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert len(results) == 12
    for got in results:
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


# --- Variants ------------------------------------------------------------------------------------


def test_explain_follows_the_ray_tracing_guidance(device, bunny):
    v, f = bunny
    opaque = device.scene([device.mesh(v, f)])
    translucent = device.scene([device.mesh(v, f, opacity=random_opacity(f, seed=9))])
    with_spheres = device.scene([device.mesh(v, f), device.spheres([[0, 0, 10]], 0.5)])
    pipeline = device.backend == "pipeline"
    skips_boxes = lambda e: "SkipAABBs" in e["ray_flags"] + e["pipeline_flags"]  # noqa: E731
    if device.engine == "cpu":
        # No shader variant: Embree's traversal, its hit filter only where the scene or the query
        # calls for it (none for opaque closest hits and occlusion: Embree's plain path).
        assert opaque.explain("closest")["filter"] == [] and opaque.explain("occluded")["filter"] == []
        assert "Embree" in opaque.explain("closest")["stages"][0]
        assert translucent.explain("closest")["filter"] == ["opacity"]
        assert translucent.explain("closest", opacity_threshold=1.0)["filter"] == ["opacity"]
        assert opaque.explain("closest", cull="back")["filter"] == ["culling"]
        assert opaque.explain("all")["filter"] == ["every hit"] == opaque.explain("count")["filter"]
        assert translucent.explain("transmittance")["filter"] == ["every hit"]
        assert "f64" in opaque.explain("closest", precision="exact")["stages"][0]
        assert opaque.explain("closest", precision="exact")["filter"] == []
        return

    closest = opaque.explain("closest", outputs=["t"])
    assert "CullNoOpaque" in closest["ray_flags"]
    assert closest["outputs"] == ["t"]
    if pipeline:
        assert closest["stages"] == ["ray generation", "miss", "closest-hit"]  # no any-hit, no intersection
        # SkipAABBs is a pipeline flag where the device has primitive culling, else absent.
        assert skips_boxes(closest) == device.limits["ray_traversal_primitive_culling"]
    else:
        assert skips_boxes(closest) and closest["ray_query_branches"] == []

    occluded = opaque.explain("occluded")
    assert "TerminateOnFirstHit" in occluded["ray_flags"] and occluded["outputs"] == ["prim_id"]
    if pipeline:
        assert "SkipClosestHitShader" in occluded["ray_flags"]
        assert not any("closest-hit" in s for s in occluded["stages"])

    assert all("any-hit" not in s for s in opaque.explain("closest")["stages"])
    lets_through = translucent.explain("closest")
    assert "CullNoOpaque" not in lets_through["ray_flags"]
    if pipeline:
        assert "any-hit (opacity)" in lets_through["stages"]
        assert "intersection (spheres)" in with_spheres.explain("closest")["stages"]
        assert all("intersection" not in s for s in translucent.explain("closest")["stages"])
    else:
        assert any("opacity" in b for b in lets_through["ray_query_branches"])
        assert any("spheres" in b for b in with_spheres.explain("closest")["ray_query_branches"])
        assert not skips_boxes(with_spheres.explain("closest"))

    every = opaque.explain("all")
    assert "NoOpaque" in every["ray_flags"]
    assert (pipeline and "any-hit (every hit)" in every["stages"]) or not pipeline
    transmit = translucent.explain("transmittance")
    assert transmit["outputs"] == ["t"] and "NoOpaque" in transmit["ray_flags"]
    # Through opaque triangles only, light is kept or not: the occlusion variant answers.
    assert opaque.explain("transmittance")["ray_flags"] == occluded["ray_flags"]
    culled = opaque.explain("closest", cull="back")
    assert "CullBackFacingTriangles" in culled["ray_flags"]
    exact = opaque.explain("closest", precision="exact")
    assert (pipeline and "intersection (exact f64 test)" in exact["stages"]) or not pipeline
    assert opaque.explain("closest", sensor=True)["specialization"]["RAY_SOURCE"] == 1
    assert opaque.explain("closest", precision="reference")["specialization"] == {}
    with pytest.raises(ValueError, match="kind must be one of"):
        opaque.explain("nearest")


# --- Sensors -------------------------------------------------------------------------------------


def sensors_around(v):
    centre = (v.min(0) + v.max(0)) / 2
    size = float(np.ptp(v, axis=0).max())
    pose = np.eye(4)
    pose[:3, 3] = centre + [size, 0.1 * size, 0.0]
    return [
        vkray.PinholeCamera(64, 48, fov_deg=60, eye=centre + [0, 0, 2 * size], target=centre, up=[0, -1, 0]),
        vkray.PinholeCamera(
            32,
            24,
            K=np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]),
            extrinsic=np.array(
                [[1.0, 0, 0, -centre[0]], [0, -1, 0, centre[1]], [0, 0, -1, centre[2] + 2 * size], [0, 0, 0, 1]]
            ),
        ),
        vkray.OrthographicCamera(
            64, 48, eye=centre + [0, 0, 2 * size], target=centre, up=[0, -1, 0], extent=1.2 * size
        ),
        vkray.Lidar.preset("vlp16", azimuth_steps=360, pose=pose),
        vkray.Lidar([-10.0, 0.0, 10.0], 100, pose=pose, min_range=0.01, max_range=1.5 * size),
    ]


@pytest.mark.parametrize("precision", ALL_TIERS)
def test_sensor_rays_generated_on_the_gpu_give_the_uploaded_rays_hits(device, bunny, precision):
    """The shaders generate a sensor's rays (nothing uploaded); `Sensor.rays()` holds the same rays,
    so both give the same hits: bit for bit, but for an orthographic camera in the fast tier, whose
    per-pixel origins the GPU moves into the scene's frame in float32 (the host does it in f64)."""
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    for sensor in sensors_around(v):
        o, d = sensor.rays()
        generated = scene.intersect(sensor, precision=precision)
        uploaded = scene.intersect(o, d, tmin=sensor.tmin, tmax=sensor.tmax, precision=precision)
        assert generated.t.shape == sensor.shape
        assert generated.hit.any(), sensor
        if isinstance(sensor, vkray.OrthographicCamera) and precision in ("fast", "refined"):
            assert np.mean(generated.prim_id == uploaded.prim_id) > 0.99
            same = generated.prim_id == uploaded.prim_id
            np.testing.assert_allclose(generated.t[same], uploaded.t[same], rtol=1e-5)
            continue
        for field in ("t", "prim_id", "uv", "normal"):
            np.testing.assert_array_equal(getattr(generated, field), getattr(uploaded, field), err_msg=repr(sensor))
        if precision in GPU_TIERS:
            np.testing.assert_array_equal(
                scene.count(sensor, precision=precision),
                scene.count(o, d, precision=precision, tmin=sensor.tmin, tmax=sensor.tmax),
            )
            np.testing.assert_array_equal(scene.occluded(sensor, precision=precision), generated.hit)


def test_far_sensors_and_every_query_kind(device, bunny):
    """A camera far from the scene (whose rays the host advances) is generated on the host instead,
    with the same hits; every query takes a sensor and shapes its answer like the sensor."""
    v, f = bunny
    scene = device.scene([device.mesh(v, f, opacity=random_opacity(f, seed=10, cut=0.0))])
    centre = (v.min(0) + v.max(0)) / 2
    far = vkray.PinholeCamera(32, 24, fov_deg=0.001, eye=centre + [0, 0, 1e4], target=centre, up=[0, -1, 0])
    o, d = far.rays()
    np.testing.assert_array_equal(scene.intersect(far, outputs=["t"]).t, scene.intersect(o, d, outputs=["t"]).t)
    lidar = sensors_around(v)[3]
    assert scene.transmittance(lidar).shape == lidar.shape
    all_hits = scene.intersect_all(lidar, precision="exact")
    np.testing.assert_array_equal(all_hits.counts, scene.count(lidar, precision="exact"))
    lo, ld = lidar.rays()
    np.testing.assert_array_equal(
        scene.transmittance(lidar, precision="exact"), scene.transmittance(lo, ld, precision="exact")
    )


def test_lidar_echoes_are_the_first_returns_along_each_beam(device):
    """echoes=k: fields of shape (channels, steps, k), the k nearest hits (intersect_all's), then
    misses; the first echo is intersect's."""
    quad_v = np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], float)
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    # Walls at x = 1, 2, 3.5, their diagonals clear of the beams (the fast tier may hit an edge twice).
    walls = [(quad_v @ np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0.0]]).T + [x, 0.3, 0.2], quad_f) for x in (1, 2, 3.5)]
    scene = device.scene([device.mesh_from_parts(walls, opacity=[0.3, 0.6, 1.0])])
    single = vkray.Lidar([-5.0, 0.0, 5.0], 8)
    echoes = vkray.Lidar([-5.0, 0.0, 5.0], 8, echoes=2)
    for precision in ("fast", "exact"):
        hits = scene.intersect(echoes, precision=precision, outputs=["t", "geometry_id"], opacity_threshold=0.2)
        assert hits.t.shape == (3, 8, 2)
        first = scene.intersect(single, precision=precision, outputs=["t", "geometry_id"], opacity_threshold=0.2)
        np.testing.assert_array_equal(hits.t[..., 0], first.t)
        forward = np.isin(np.arange(8), [0, 1, 7])  # the beams at azimuths 0, 45 and 315 degrees meet the walls
        assert (hits.geometry_id[:, forward] == [0, 1]).all()
        assert np.isinf(hits.t[:, ~forward]).all() and (hits.geometry_id[:, ~forward] == -1).all()


def test_bad_sensor_calls(any_device, bunny):
    v, f = bunny
    scene = any_device.scene([any_device.mesh(v, f)])
    camera = vkray.PinholeCamera(8, 8, fov_deg=60, eye=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0])
    with pytest.raises(TypeError, match="without directions"):
        scene.intersect(camera, np.ones((64, 3)))
    with pytest.raises(TypeError, match="range is its own"):
        scene.intersect(camera, tmax=1.0)
    with pytest.raises(TypeError, match="directions are needed"):
        scene.intersect(np.zeros((4, 3)))
    for bad in (dict(width=0, height=8), dict(width=8, height=8, eye=[np.nan, 0, 1])):
        kwargs = dict(width=8, height=8, fov_deg=60, eye=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0])
        kwargs.update(bad)
        with pytest.raises(ValueError):
            vkray.PinholeCamera(**kwargs)
    with pytest.raises(ValueError, match="rotation"):
        vkray.Lidar([0.0], 10, pose=np.diag([2.0, 1.0, 1.0, 1.0]))

"""Rays packed by the GPU (shaders/pack_rays.comp: always for CUDA arrays; for host arrays with
VKRAY_PACK=gpu, which imports them in place and writes the hits straight into the result arrays)
answer bit for bit as rays packed on the host (geometry/rays.rs Rays::pack, the default). The
oracle: the same query (closest hits, occlusion, counts) on a device that packs on the host
(itself checked against Embree elsewhere), on rays that exercise every branch of the packing:
float32 and float64 arrays, one origin for many rays, per-ray bounds, far rays advanced towards
the scene, invalid rays (the same error, naming the same row), spheres and instances; and several
threads at once."""

from __future__ import annotations

import re

import numpy as np
import pytest

import oracle
import vkray
from conftest import BACKENDS, VALIDATION


def devices_packing(backend: str, monkeypatch) -> tuple[vkray.Device, vkray.Device]:
    """(packs on the host, packs on the GPU): VKRAY_PACK is read when a device opens."""
    monkeypatch.setenv("VKRAY_PACK", "host")
    host = vkray.Device(backend=backend, validation=VALIDATION)
    monkeypatch.setenv("VKRAY_PACK", "gpu")
    gpu = vkray.Device(backend=backend, validation=VALIDATION)
    return host, gpu


@pytest.fixture(scope="module", params=BACKENDS)
def pair(request):
    with pytest.MonkeyPatch.context() as monkeypatch:
        yield devices_packing(request.param, monkeypatch)


def scenes(pair, build):
    return tuple(build(device) for device in pair)


def assert_same_hits(a: vkray.Hits, b: vkray.Hits) -> None:
    for name in vkray.HIT_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)


def bunny_scenes(pair):
    v, f = oracle.load_mesh("stanford-bunny")
    return v, scenes(pair, lambda d: d.scene([d.mesh(v, f)]))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_random_rays_as_the_host_packs_them(pair, dtype):
    v, (host, gpu) = bunny_scenes(pair)
    o, d = oracle.random_rays(v, 20_000, seed=1)
    o, d = o.astype(dtype), d.astype(dtype)
    expected = host.intersect(o, d, outputs=list(vkray.HIT_FIELDS))
    assert expected.hit.sum() > 1000
    assert_same_hits(gpu.intersect(o, d, outputs=list(vkray.HIT_FIELDS)), expected)
    np.testing.assert_array_equal(gpu.occluded(o, d), host.occluded(o, d))
    counts = host.count(o, d)
    assert counts.max() >= 4
    np.testing.assert_array_equal(gpu.count(o, d), counts)
    assert gpu.device.last_trace_profile["ray_bytes"] == 0  # packed by the GPU


def test_one_origin_many_directions_and_per_ray_bounds(pair):
    v, (host, gpu) = bunny_scenes(pair)
    rng = np.random.default_rng(2)
    eye = v.mean(axis=0) + np.array([0.0, 0.0, 0.3])
    d = rng.normal(size=(5000, 3)).astype(np.float32)
    tmin = rng.uniform(0.0, 0.05, 5000)
    tmax = rng.uniform(0.05, 1.0, 5000)
    assert_same_hits(gpu.intersect(eye, d), host.intersect(eye, d))
    assert_same_hits(gpu.intersect(eye, d, tmin=tmin, tmax=tmax), host.intersect(eye, d, tmin=tmin, tmax=tmax))
    assert_same_hits(gpu.intersect(eye, d, tmin=0.01, tmax=0.2), host.intersect(eye, d, tmin=0.01, tmax=0.2))


@pytest.mark.parametrize("distance", [1e4, 1e7, 1e12])
def test_far_rays_are_advanced_as_the_host_advances_them(pair, distance):
    """Rays from far away are moved towards the scene in f64 before f32 traversal; their t is
    the distance from where they started. Some pass by, some end before the scene (tmax), some
    point away."""
    v, (host, gpu) = bunny_scenes(pair)
    rng = np.random.default_rng(3)
    target = v[rng.integers(0, len(v), 3000)]
    away = rng.normal(size=(3000, 3))
    away /= np.linalg.norm(away, axis=1, keepdims=True)
    o = target + away * distance
    d = -away + rng.normal(scale=0.03 / distance, size=away.shape)  # within the bunny's reach
    d[::7] *= -1  # pointing away
    tmax = np.where(np.arange(3000) % 5 == 0, distance * 0.5, np.inf)  # ending before the scene
    expected = host.intersect(o, d, tmax=tmax)
    assert expected.hit.sum() > 500
    assert_same_hits(gpu.intersect(o, d, tmax=tmax), expected)
    np.testing.assert_array_equal(gpu.count(o, d, tmax=tmax), host.count(o, d, tmax=tmax))


def test_spheres_and_instances(pair):
    rng = np.random.default_rng(4)
    centers, radii = rng.uniform(-5, 5, (200, 3)), rng.uniform(0.1, 0.5, 200)
    v, f = oracle.load_mesh("stanford-bunny")

    def build(device):
        bunny = device.mesh(v, f)
        turned = np.eye(4)
        turned[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, -2]]  # rotation, scale and mirror
        turned[:3, 3] = [0.3, 0.0, 0.0]
        return device.scene([device.spheres(centers, radii), bunny, vkray.Instance(bunny, turned, custom_index=7)])

    host, gpu = scenes(pair, build)
    o = rng.uniform(-6, 6, (10_000, 3))
    d = rng.normal(size=(10_000, 3))
    every = list(vkray.HIT_FIELDS)
    assert_same_hits(gpu.intersect(o, d, outputs=every), host.intersect(o, d, outputs=every))


@pytest.mark.parametrize("bad", ["nan_origin", "zero_direction", "inf_direction", "negative_tmin", "tmax_below"])
def test_invalid_rays_raise_the_same_error(pair, bad):
    v, (host, gpu) = bunny_scenes(pair)
    o, d = oracle.random_rays(v, 3000, seed=5)
    tmin, tmax = np.zeros(3000), np.full(3000, np.inf)
    row = 1234
    if bad == "nan_origin":
        o[row, 1] = np.nan
    elif bad == "zero_direction":
        d[row] = 0.0
    elif bad == "inf_direction":
        d[row, 2] = np.inf
    elif bad == "negative_tmin":
        tmin[row] = -1.0
    else:
        tmax[row] = -0.5
    with pytest.raises(ValueError) as expected:
        host.intersect(o, d, tmin=tmin, tmax=tmax)
    assert str(row) in str(expected.value)
    with pytest.raises(ValueError, match=f"^{re.escape(str(expected.value))}$"):
        gpu.intersect(o, d, tmin=tmin, tmax=tmax)


def test_several_threads(pair):
    v, (host, gpu) = bunny_scenes(pair)
    batches = [oracle.random_rays(v, 4000, seed=10 + k) for k in range(6)]
    expected = [host.intersect(o, d) for o, d in batches]
    found = oracle.in_threads(len(batches), lambda k: gpu.intersect(*batches[k]))
    for a, b in zip(found, expected):
        assert_same_hits(a, b)


def test_the_gpu_packed_query_is_profiled(pair):
    v, (host, gpu) = bunny_scenes(pair)
    o, d = oracle.random_rays(v, 1000, seed=6)
    gpu.intersect(o, d)
    profile = gpu.device.last_trace_profile
    assert profile["rays"] == 1000 and profile["chunks"] >= 1

"""Arrays from any object that speaks DLPack (``__dlpack__`` / ``__dlpack_device__``: torch, cupy,
jax, numpy >= 1.22). Host-memory arrays are read in place (no copy) and answer exactly as numpy
does; arrays on a device vkray cannot read raise a TypeError naming that device. The results are
numpy arrays, which speak DLPack themselves. The oracle: the same query on numpy arrays (itself
checked against Embree and brute force elsewhere), and numpy's own view of the same memory."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import oracle
from vkray import _arrays


class DLPackOnly:
    """An array reachable only through DLPack (no __array__, no buffer protocol): what a
    torch/cupy/jax array looks like to code that must not call numpy's conversions."""

    def __init__(self, array: np.ndarray):
        self._array = array

    def __dlpack__(self, **kwargs):
        return self._array.__dlpack__(**kwargs)

    def __dlpack_device__(self):
        return self._array.__dlpack_device__()


class OnAnotherDevice:
    """A DLPack array on CUDA device 1 (its data never reached)."""

    def __dlpack__(self, **kwargs):
        raise AssertionError("vkray must not ask for the data of an array it cannot read")

    def __dlpack_device__(self):
        return (2, 1)


@pytest.fixture(scope="module")
def bunny():
    return oracle.load_mesh("stanford-bunny")


def rays_at(vertices, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0), vertices.max(0)
    origins = rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo), (n, 3))
    targets = rng.uniform(lo, hi, (n, 3))
    return origins, targets - origins


def test_host_arrays_are_read_in_place(bunny):
    v, _ = bunny
    o, _ = rays_at(v, 100, seed=1)
    seen = _arrays.real_coordinates("origins", DLPackOnly(o))
    assert np.shares_memory(seen, o) and seen.dtype == np.float64
    seen32 = _arrays.real_coordinates("origins", DLPackOnly(o.astype(np.float32)))
    assert seen32.dtype == np.float32


@pytest.mark.parametrize("precision", ["fast", "exact"])
def test_dlpack_rays_and_points_answer_as_numpy(any_device, bunny, precision):
    v, f = bunny
    scene = any_device.scene([any_device.mesh(DLPackOnly(v), DLPackOnly(f.astype(np.int32)))])
    o, d = rays_at(v, 2000, seed=2)
    expected = scene.intersect(o, d, precision=precision)
    hits = scene.intersect(DLPackOnly(o), DLPackOnly(d), precision=precision)
    for name in ("t", "prim_id", "instance_id", "uv", "normal"):
        np.testing.assert_array_equal(getattr(hits, name), getattr(expected, name))
    # Strided views (every other ray, float32) go through as numpy's do.
    o32, d32 = o[::2].astype(np.float32), d[::2].astype(np.float32)
    np.testing.assert_array_equal(
        scene.intersect(DLPackOnly(o32), DLPackOnly(d32), precision=precision).t,
        scene.intersect(o32, d32, precision=precision).t,
    )
    np.testing.assert_array_equal(
        scene.occluded(DLPackOnly(o), DLPackOnly(d), precision=precision),
        scene.occluded(o, d, precision=precision),
    )
    np.testing.assert_array_equal(
        scene.distance(DLPackOnly(o), precision=precision), scene.distance(o, precision=precision)
    )
    # The results speak DLPack: another library takes them without a copy.
    assert np.shares_memory(np.from_dlpack(hits.t), hits.t)


def test_arrays_on_another_device_are_refused_by_name(any_device, bunny):
    v, f = bunny
    scene = any_device.scene([any_device.mesh(v, f)])
    o, d = rays_at(v, 10, seed=3)
    with pytest.raises(TypeError, match=r"origins lives on cuda:1 \(DLPack device type 2\)"):
        scene.intersect(OnAnotherDevice(), d)
    with pytest.raises(TypeError, match="points lives on cuda:1"):
        scene.closest_points(OnAnotherDevice())
    with pytest.raises(TypeError, match="vertices lives on cuda:1"):
        any_device.mesh(OnAnotherDevice(), f)


def test_several_threads_with_dlpack_arrays(any_device, bunny):
    v, f = bunny
    scene = any_device.scene([any_device.mesh(v, f)])
    batches = [rays_at(v, 500, seed=10 + k) for k in range(4)]
    expected = [scene.intersect(o, d).prim_id for o, d in batches]
    found = [None] * 4

    def work(k):
        o, d = batches[k]
        found[k] = scene.intersect(DLPackOnly(o), DLPackOnly(d)).prim_id

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for got, want in zip(found, expected):
        np.testing.assert_array_equal(got, want)


def test_torch_cpu_tensors(any_device, bunny):
    torch = pytest.importorskip("torch")
    v, f = bunny
    scene = any_device.scene([any_device.mesh(torch.from_numpy(v), torch.from_numpy(f))])
    o, d = rays_at(v, 1000, seed=4)
    expected = scene.intersect(o, d)
    to, td = torch.from_numpy(o), torch.from_numpy(d)
    hits = scene.intersect(to, td)
    np.testing.assert_array_equal(hits.t, expected.t)
    # A non-contiguous tensor (a transposed buffer) reads as its values.
    transposed = torch.from_numpy(np.ascontiguousarray(o.T)).T
    assert not transposed.is_contiguous()
    np.testing.assert_array_equal(scene.intersect(transposed, td).prim_id, expected.prim_id)
    back = torch.from_dlpack(hits.t)
    assert back.data_ptr() == hits.t.ctypes.data


class _DeviceTypeEnum:
    """A DLPack device type as Open3D gives it: an enum object with a ``value``, which ``int()``
    refuses (pybind11's enums of Open3D's DLDeviceType)."""

    def __init__(self, value: int):
        self.value = value

    def __int__(self):
        raise TypeError("int() argument must be a string, a bytes-like object or a real number, not 'DLDeviceType'")


class EnumDevice(DLPackOnly):
    """A host array whose ``__dlpack_device__`` names its device type with such an enum."""

    def __dlpack_device__(self):
        kind, index = self._array.__dlpack_device__()
        return (_DeviceTypeEnum(int(kind)), index)


def test_device_types_given_as_enums_are_read(any_device, bunny):
    """Open3D's tensors name their device type with an enum: read as its value, in the Python
    layer and in the core, and the answer is numpy's."""
    v, f = bunny
    scene = any_device.scene(any_device.mesh(v, f))
    o, d = rays_at(v, 500, seed=7)
    want = scene.intersect(o, d, outputs=["t", "prim_id"])
    got = scene.intersect(EnumDevice(o), EnumDevice(d), outputs=["t", "prim_id"])
    np.testing.assert_array_equal(got.prim_id, want.prim_id)
    np.testing.assert_array_equal(got.t, want.t)
    assert _arrays.dlpack_device(EnumDevice(o)) == (1, 0)
    np.testing.assert_array_equal(scene.count(EnumDevice(o), d), scene.count(o, d))


def test_cuda_answers_need_a_cuda_device(any_device, bunny):
    """cuda=True answers in CUDA memory: a device that shares none with CUDA says so (the CUDA
    machines' tests check the answers themselves, tests/test_cuda_queries.py)."""
    if any_device.cuda_device is not None:
        pytest.skip("this device shares memory with CUDA")
    v, f = bunny
    scene = any_device.scene([any_device.mesh(v, f)])
    o, d = oracle.random_rays(v, 10, seed=3)
    for query in (scene.intersect, scene.occluded, scene.count, scene.intersect_all, scene.transmittance):
        with pytest.raises(TypeError, match="does not share memory with CUDA"):
            query(o, d, cuda=True)


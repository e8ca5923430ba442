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
        (V, np.array([[0, 1, 2], [0, 1, 2], [0, 3, 2]]), ValueError, r"faces row 2 = \[0, 3, 2\] indexes outside the 3 vertices"),
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
    with pytest.raises(TypeError, match="scene item 1 must be a Mesh or an Instance"):
        any_device.scene([mesh, "cow"])
    other = vkray.Device(any_device.info.index, any_device.backend)
    with pytest.raises(ValueError, match="another Device"):
        other.scene(mesh)


O = np.array([[0.2, 0.2, 0.0], [0.3, 0.3, 0.0]])
D = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    "origins, directions, kwargs, error, match",
    [
        (O[:, :2], D, {}, ValueError, r"origins must have shape \(\.\.\., 3\)"),
        (O, D[:, :2], {}, ValueError, "directions must have shape"),
        (O, np.ones((3, 3)), {}, ValueError, "do not broadcast"),
        (O.astype(complex), D, {}, TypeError, "origins must hold real numbers"),
        (np.where([[0], [1]], np.nan, O), D, {}, ValueError, "origins row 1 is not finite"),
        (O, np.where([[1], [0]], np.inf, D), {}, ValueError, "directions row 0 is not finite"),
        (O, np.array([[0, 0, 1.0], [0, 0, 0]]), {}, ValueError, "directions row 1 has zero length"),
        (O, np.array([[0, 0, 1.0], [0, 0, 1e-50]]), {}, ValueError, "directions row 1 has zero length in float32"),
        (O, D, {"tmin": -1.0}, ValueError, "tmin of ray 0 must be finite and >= 0"),
        (O, D, {"tmin": 2.0, "tmax": 1.0}, ValueError, r"ray 0 has tmax \(1\) below tmin \(2\)"),
        (O, D, {"tmax": np.array([1.0, np.nan])}, ValueError, "ray 1 has tmax"),
        (O, D, {"tmin": np.array([0.0, np.inf])}, ValueError, "tmin of ray 1"),
        (O, D, {"tmax": np.ones(3)}, ValueError, "do not broadcast"),
        (O, D, {"tmin": "zero"}, TypeError, "tmin must hold real numbers"),
    ],
)
def test_bad_rays(any_device, origins, directions, kwargs, error, match):
    scene = any_device.scene(any_device.mesh(V, F))
    for query in (scene.intersect, scene.occluded):
        with pytest.raises(error, match=match):
            query(origins, directions, **kwargs)
    # Nothing reached the GPU: the device still answers.
    assert scene.intersect(O, D).hit.tolist() == [True, True]

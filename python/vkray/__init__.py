"""vkray: Vulkan ray-tracing acceleration structures from numpy arrays, and batched ray casting.

>>> import numpy as np, vkray
>>> device = vkray.Device()
>>> mesh = device.mesh(vertices, faces)          # (V, 3) floats, (F, 3) ints -> BLAS
>>> scene = device.scene([mesh])                 # instances -> TLAS
>>> hits = scene.intersect(origins, directions)  # (N, 3) rays -> Hits of numpy arrays
"""

from . import data  # the meshes shipped with vkray: vkray.data.load_mesh
from ._core import (
    CudaArray,
    ForkedDeviceError,
    NoDeviceError,
    UnsupportedError,
    ValidationError,
    VkrayError,
    VulkanError,
)
from ._device import Device, DeviceInfo, Instance, Mesh, MeshObject, Scene, default_device, devices
from ._device_group import DeviceGroup, GroupInstance, GroupMesh, GroupScene
from ._options import (
    CLOSEST_FIELDS,
    DEFAULT_FIELDS,
    HIT_FIELDS,
    PRECISIONS,
    Backend,
    Build,
    Cull,
    Precision,
    VertexFormat,
)
from ._pictures import Picture
from ._preview import preview
from ._queries import PointQuery, RayQuery, SceneLike
from ._results import AllHits, Closest, Hits
from ._secondary import offset_origins
from .sensors import Lidar, OrthographicCamera, PinholeCamera, Sensor

__all__ = [
    "data",
    "AllHits",
    "CudaArray",
    "CLOSEST_FIELDS",
    "Closest",
    "DEFAULT_FIELDS",
    "HIT_FIELDS",
    "PRECISIONS",
    "Backend",
    "Build",
    "Cull",
    "Precision",
    "VertexFormat",
    "offset_origins",
    "Lidar",
    "OrthographicCamera",
    "PinholeCamera",
    "Sensor",
    "preview",
    "Picture",
    "Device",
    "DeviceGroup",
    "DeviceInfo",
    "GroupInstance",
    "GroupMesh",
    "GroupScene",
    "SceneLike",
    "RayQuery",
    "PointQuery",
    "MeshObject",
    "Hits",
    "Instance",
    "Mesh",
    "Scene",
    "devices",
    "default_device",
    "VkrayError",
    "ForkedDeviceError",
    "NoDeviceError",
    "UnsupportedError",
    "VulkanError",
    "ValidationError",
]
__version__ = "0.1.0"

"""vkray: Vulkan ray-tracing acceleration structures from numpy arrays, and batched ray casting.

>>> import numpy as np, vkray
>>> device = vkray.Device()
>>> mesh = device.mesh(vertices, faces)          # (V, 3) floats, (F, 3) ints -> BLAS
>>> scene = device.scene([mesh])                 # instances -> TLAS
>>> hits = scene.intersect(origins, directions)  # (N, 3) rays -> Hits of numpy arrays
"""

from . import data  # the meshes shipped with vkray: vkray.data.load_mesh
from ._api import (
    CLOSEST_FIELDS,
    DEFAULT_FIELDS,
    HIT_FIELDS,
    PRECISIONS,
    AllHits,
    Backend,
    Build,
    Closest,
    Cull,
    Device,
    DeviceInfo,
    Hits,
    Instance,
    Mesh,
    Precision,
    Scene,
    VertexFormat,
    devices,
)
from ._core import (
    CudaArray,
    ForkedDeviceError,
    NoDeviceError,
    UnsupportedError,
    ValidationError,
    VkrayError,
    VulkanError,
)
from ._group import DeviceGroup, GroupInstance, GroupMesh, GroupScene, SceneLike
from ._pictures import Picture, preview
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
    "Hits",
    "Instance",
    "Mesh",
    "Scene",
    "devices",
    "VkrayError",
    "ForkedDeviceError",
    "NoDeviceError",
    "UnsupportedError",
    "VulkanError",
    "ValidationError",
]
__version__ = "0.1.0"

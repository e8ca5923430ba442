"""Private extension module (Rust, src/python/mod.rs). Use the classes in `vkray` instead.

Arrays arrive C-contiguous, in native byte order and of the dtypes below (vkray._arrays sees to
that); option strings are checked here, with a ValueError naming the argument and the choices.
"""

from typing import Any, Callable, Dict, List, Literal, Optional, Sequence, Tuple, Union, final

import numpy as np
from numpy.typing import NDArray

from ._options import Backend, Build, Cull, Precision, VertexFormat

__all__ = [
    "devices",
    "spirv_modules",
    "host_memory_available",
    "counts_of_offsets",
    "ray_index_of_offsets",
    "Device",
    "Mesh",
    "Scene",
    "VkrayError",
    "NoDeviceError",
    "UnsupportedError",
    "VulkanError",
    "ValidationError",
    "ForkedDeviceError",
    "CudaArray",
    "CudaBatch",
]

# (N, 3) float32 or float64.
_Vec3s = Union[NDArray[np.float32], NDArray[np.float64]]
# (F, 3) triangle corner indices.
_Indices = Union[NDArray[np.int32], NDArray[np.int64], NDArray[np.uint32], NDArray[np.uint16]]
# tmin, tmax, radii: one value for all, or float64 (N,).
_PerItem = Union[float, NDArray[np.float64]]

class VkrayError(RuntimeError):
    """Base class of vkray's own errors."""

class NoDeviceError(VkrayError):
    """No usable Vulkan device (or loader) was found."""

class UnsupportedError(VkrayError):
    """The device lacks something the request needs."""

class VulkanError(VkrayError):
    """A Vulkan call failed."""

class ValidationError(VkrayError):
    """The Khronos validation layer reported a problem."""

class ForkedDeviceError(VkrayError):
    """A Device was used in a forked child of the process that opened it."""

def devices() -> List[Dict[str, Any]]:
    """The usable devices, best first (each as `vkray.DeviceInfo`'s fields)."""

def spirv_modules() -> Dict[str, bytes]:
    """The SPIR-V modules embedded in this build, by source name."""

def host_memory_available() -> Optional[int]:
    """Host memory a new allocation can still count on (bytes), or None where unknown."""

def ray_index_of_offsets(offsets: NDArray[np.int64]) -> NDArray[np.int64]:
    """Each hit's ray (int64, H) from CSR offsets (int64, N + 1; nondecreasing from 0), on all cores."""

def counts_of_offsets(offsets: NDArray[np.int64]) -> NDArray[np.int64]:
    """Each ray's count of hits (int64, N) from CSR offsets (int64, N + 1), on all cores."""

@final
class Device:
    def __new__(
        cls,
        selector: Optional[str] = None,
        backend: Optional[Backend] = None,
        validation: bool = False,
        library_paths: Sequence[str] = ...,
    ) -> Device: ...
    @property
    def info(self) -> Dict[str, Any]: ...
    @property
    def backend(self) -> Union[Backend, Literal["cpu"]]: ...
    @property
    def validation(self) -> bool: ...
    @property
    def limits(self) -> Dict[str, Any]: ...
    @property
    def last_trace_profile(self) -> Dict[str, Optional[float]]: ...
    @property
    def idle_memory(self) -> Dict[str, int]: ...
    def release_idle_memory(self) -> None: ...
    @property
    def chunk_rays(self) -> int: ...
    @chunk_rays.setter
    def chunk_rays(self, rays: int) -> None: ...
    @property
    def host_threads(self) -> Optional[int]: ...
    @host_threads.setter
    def host_threads(self, threads: Optional[int]) -> None: ...
    @property
    def cuda_device(self) -> Optional[int]: ...
    def cuda_read(self, value: Any, name: str) -> Tuple[NDArray[np.uint8], str, List[int], List[int]]: ...
    def cuda_write(self, bytes: NDArray[np.uint8], dtype: str, shape: List[int]) -> CudaArray: ...
    def pinned_answers(self, on: bool) -> None: ...
    def mesh(
        self,
        vertices: _Vec3s,
        faces: _Indices,
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        vertex_format: VertexFormat = "float32",
        opacity: Optional[NDArray[np.float32]] = None,
    ) -> Mesh: ...
    def spheres(self, centers: _Vec3s, radii: _PerItem, build: Build = "fast_trace", compact: bool = False) -> Mesh: ...
    def mesh_parts(
        self,
        parts: Sequence[Tuple[_Vec3s, _Indices]],
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        vertex_format: VertexFormat = "float32",
        opacity: Optional[NDArray[np.float32]] = None,
    ) -> Mesh: ...
    def meshes(
        self,
        items: Sequence[Tuple[_Vec3s, _Indices]],
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        budget_bytes: Optional[int] = None,
        vertex_format: VertexFormat = "float32",
        progress: Optional[Callable[[int, int], object]] = None,
    ) -> List[Mesh]: ...
    def scene(
        self,
        # (mesh, float64 (3, 4) or (4, 4) transform or None, custom_index, mask, flags); flags:
        # 1 cull_disable, 2 flip_facing, 4 force opaque, 8 force non-opaque.
        items: Sequence[Tuple[Mesh, Optional[NDArray[np.float64]], int, int, int]],
        build: Build = "fast_build",
        allow_update: bool = False,
        compact: bool = False,
    ) -> Scene: ...

@final
class Mesh:
    # Made by Device.mesh and its siblings only: no constructor.
    @property
    def vertex_count(self) -> int: ...
    @property
    def triangle_count(self) -> int: ...
    @property
    def part_count(self) -> int: ...
    @property
    def kind(self) -> str: ...
    @property
    def stats(self) -> Dict[str, Any]: ...
    def update(self, vertices: _Vec3s) -> None: ...

@final
class Scene:
    # Made by Device.scene only: no constructor.
    def update(
        self, transforms: Optional[NDArray[np.float64]] = None, masks: Optional[NDArray[np.uint8]] = None
    ) -> None: ...
    @property
    def instance_count(self) -> int: ...
    @property
    def stats(self) -> Dict[str, Any]: ...
    def inside_grid(self, winding: bool) -> Optional[Dict[str, Any]]: ...
    def trace(
        self,
        origins: _Vec3s,
        directions: _Vec3s,
        tmin: _PerItem,
        tmax: _PerItem,
        query: str,
        fields: List[str],
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Union[int, NDArray[np.uint8], None] = None,
        contacts: bool = False,
        progress: Optional[Callable[[int, int], object]] = None,
        opacity_threshold: float = 0.5,
        sensor: Optional[Dict[str, Any]] = None,
        out: Optional[Dict[str, NDArray[Any]]] = None,
    ) -> Dict[str, NDArray[Any]]: ...
    def stays_on_gpu(self, query: str, precision: Precision = "fast", fields: List[str] = ...) -> bool: ...
    def trace_cuda(
        self,
        origins: Any,
        directions: Any,
        tmin: Any,
        tmax: Any,
        query: str,
        fields: List[str],
        cull: Cull = None,
        mask: int = 255,
        opacity_threshold: float = 0.5,
        precision: Precision = "fast",
    ) -> Dict[str, CudaArray]: ...
    def trace_cuda_all(
        self,
        origins: Any,
        directions: Any,
        tmin: Any,
        tmax: Any,
        fields: List[str],
        cull: Cull = None,
        mask: int = 255,
        opacity_threshold: float = 0.5,
        precision: Precision = "fast",
        max_hits: Optional[int] = None,
    ) -> Optional[Tuple[List[int], Dict[str, CudaArray]]]: ...
    def cuda_batch(
        self,
        origins: Any,
        directions: Any,
        tmin: Any,
        tmax: Any,
        fields: List[str],
        mask: int = 255,
    ) -> CudaBatch: ...
    def trace_cuda_piece(
        self,
        batch: CudaBatch,
        start: int,
        stop: int,
        query: str,
        cull: Cull = None,
        opacity_threshold: float = 0.5,
    ) -> None: ...
    def trace_all(
        self,
        origins: _Vec3s,
        directions: _Vec3s,
        tmin: _PerItem,
        tmax: _PerItem,
        fields: List[str],
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Union[int, NDArray[np.uint8], None] = None,
        max_hits: Optional[int] = None,
        contacts: bool = False,
        progress: Optional[Callable[[int, int], object]] = None,
        opacity_threshold: float = 0.5,
        sensor: Optional[Dict[str, Any]] = None,
    ) -> Dict[str, NDArray[Any]]: ...
    def count(
        self,
        origins: _Vec3s,
        directions: _Vec3s,
        tmin: _PerItem,
        tmax: _PerItem,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Union[int, NDArray[np.uint8], None] = None,
        progress: Optional[Callable[[int, int], object]] = None,
        opacity_threshold: float = 0.5,
        sensor: Optional[Dict[str, Any]] = None,
    ) -> NDArray[np.int32]: ...
    def explain(
        self,
        kind: str,
        fields: List[str],
        precision: Precision = "fast",
        cull: Cull = None,
        opacity_threshold: float = 0.5,
        sensor: bool = False,
    ) -> Optional[Dict[str, Any]]: ...
    def closest_points(
        self,
        points: _Vec3s,
        fields: List[str],
        max_distance: float = ...,
        precision: Precision = "reference",
        progress: Optional[Callable[[int, int], object]] = None,
    ) -> Dict[str, NDArray[Any]]: ...
    def contains(
        self,
        points: _Vec3s,
        precision: Precision = "exact",
        winding: bool = False,
        progress: Optional[Callable[[int, int], object]] = None,
    ) -> NDArray[np.bool_]: ...
    def contains_cuda(self, points: Any, winding: bool = False) -> Optional[CudaArray]: ...
    def signed_distance(
        self,
        points: _Vec3s,
        max_distance: float,
        precision: Precision,
        contains_precision: Precision,
        winding: bool,
        progress: Optional[Callable[[int, int], object]] = None,
    ) -> NDArray[np.float64]: ...

@final
class CudaBatch:
    """A batch of CUDA rays traced in pieces by several devices (`DeviceGroup`), its hits
    allocated on the GPU that holds the rays."""

    def __len__(self) -> int: ...
    @property
    def shape(self) -> Tuple[int, ...]: ...
    def finish(self) -> Dict[str, CudaArray]: ...

@final
class CudaArray:
    """A query's answer in CUDA memory owned by vkray (queries of CUDA arrays): read it without a
    copy through DLPack (``torch.from_dlpack(a)``, ``cupy.from_dlpack(a)``), or copy it to numpy.
    ``dtype`` is numpy's name of its elements (float32, float64, int32, int64, bool)."""

    @property
    def shape(self) -> Tuple[int, ...]: ...
    @property
    def dtype(self) -> str: ...
    def __len__(self) -> int: ...
    def __dlpack_device__(self) -> Tuple[int, int]: ...
    def __dlpack__(
        self,
        *,
        stream: Optional[int] = None,
        max_version: Optional[Tuple[int, int]] = None,
        dl_device: Optional[Tuple[int, int]] = None,
        copy: Optional[bool] = None,
    ) -> Any: ...
    def numpy(self) -> NDArray[Any]: ...
    def __array__(self, dtype: Any = None, copy: Optional[bool] = None) -> NDArray[Any]: ...

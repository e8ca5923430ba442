"""Private extension module (Rust). Use the classes in `vkray` instead."""

from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

class VkrayError(RuntimeError): ...
class NoDeviceError(VkrayError): ...
class UnsupportedError(VkrayError): ...
class VulkanError(VkrayError): ...
class ValidationError(VkrayError): ...

def devices() -> List[Dict[str, Any]]: ...
def spirv_modules() -> Dict[str, bytes]: ...

class Device:
    def __init__(self, selector: Optional[str] = None, backend: Optional[str] = None, validation: bool = False) -> None: ...
    @property
    def info(self) -> Dict[str, Any]: ...
    @property
    def backend(self) -> str: ...
    @property
    def validation(self) -> bool: ...
    @property
    def limits(self) -> Dict[str, Any]: ...
    @property
    def last_trace_profile(self) -> Dict[str, float]: ...
    chunk_rays: int
    def meshes(
        self,
        items: List[Tuple[np.ndarray, np.ndarray]],
        build: str = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        budget_bytes: Optional[int] = None,
        vertex_format: str = "float32",
    ) -> List[Mesh]: ...
    def mesh_parts(
        self,
        parts: List[Tuple[np.ndarray, np.ndarray]],
        build: str = ...,
        allow_update: bool = ...,
        compact: bool = ...,
        vertex_format: str = ...,
    ) -> Mesh: ...
    def mesh(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        build: str = ...,
        allow_update: bool = ...,
        compact: bool = ...,
        vertex_format: str = ...,
    ) -> Mesh: ...
    def scene(
        self,
        items: Sequence[Tuple[Mesh, Optional[np.ndarray], int, int, int]],
        build: str = ...,
        allow_update: bool = ...,
        compact: bool = ...,
    ) -> Scene: ...

class Mesh:
    @property
    def vertex_count(self) -> int: ...
    @property
    def triangle_count(self) -> int: ...
    @property
    def part_count(self) -> int: ...
    @property
    def stats(self) -> Dict[str, Any]: ...
    def update(self, vertices: np.ndarray) -> None: ...

class Scene:
    @property
    def instance_count(self) -> int: ...
    def update(self, transforms: Optional[np.ndarray] = None, masks: Optional[np.ndarray] = None) -> None: ...
    @property
    def stats(self) -> Dict[str, Any]: ...
    def trace(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        tmin: Union[float, np.ndarray],
        tmax: Union[float, np.ndarray],
        query: str,
        fields: List[str],
        precision: str = "fast",
        cull: Optional[str] = None,
        mask: Union[int, np.ndarray, None] = None,
    ) -> Dict[str, np.ndarray]: ...

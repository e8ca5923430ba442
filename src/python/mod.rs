//! The one binding module: maps the core to `vkray._core`. Arrays arrive C-contiguous with an
//! accepted dtype (the Python layer sees to that); inputs are read while the GIL is held and every
//! wait on the GPU runs with the GIL released.

use std::sync::{Arc, RwLock};

use numpy::{
    PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::error::{Error, Result};
use crate::geometry::arrays::{instance_transform, Indices, Vec3s};
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::accel::{BuildOptions, BuildPreference, BuildStats};
use crate::gpu::context::{Backend, Context, DeviceInfo, DeviceRequest, Wait};
use crate::scene::{Instance, InstanceFlags, Mesh, MeshKind, Scene, IDENTITY};
use crate::trace::request::{Cull, Precision};
use crate::trace::{Field, HitSink, Query, Request, Tracer};

create_exception!(_core, VkrayError, PyRuntimeError, "Base class of vkray's own errors.");
create_exception!(_core, NoDeviceError, VkrayError, "No usable Vulkan device (or loader) was found.");
create_exception!(_core, UnsupportedError, VkrayError, "The device lacks something the request needs.");
create_exception!(_core, VulkanError, VkrayError, "A Vulkan call failed.");
create_exception!(_core, ValidationError, VkrayError, "The Khronos validation layer reported a problem.");

impl From<Error> for PyErr {
    fn from(error: Error) -> PyErr {
        let message = error.to_string();
        match error {
            Error::InvalidValue(_) => PyValueError::new_err(message),
            Error::InvalidType(_) => PyTypeError::new_err(message),
            Error::NoDevice(_) => NoDeviceError::new_err(message),
            Error::Unsupported(_) => UnsupportedError::new_err(message),
            Error::Vulkan { .. } | Error::Allocation(_) => VulkanError::new_err(message),
            Error::Validation(_) => ValidationError::new_err(message),
        }
    }
}

/// Waits with the GIL released, so other Python threads run while the GPU works.
struct ReleaseGil<'py>(Python<'py>);

impl Wait for ReleaseGil<'_> {
    fn wait(&self, block: &(dyn Fn() -> Result<()> + Sync)) -> Result<()> {
        self.0.detach(block)
    }
}

fn info_dict<'py>(py: Python<'py>, info: &DeviceInfo) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("index", info.index)?;
    d.set_item("name", &info.name)?;
    d.set_item("device_type", info.device_type)?;
    d.set_item("is_software", info.is_software)?;
    d.set_item("api_version", &info.api_version)?;
    d.set_item("driver", &info.driver)?;
    d.set_item("ray_query", info.ray_query)?;
    d.set_item("ray_tracing_pipeline", info.ray_tracing_pipeline)?;
    d.set_item("shader_float64", info.shader_float64)?;
    Ok(d)
}

fn stats_dict<'py>(py: Python<'py>, stats: &BuildStats, options: &BuildOptions) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("build", options.preference.name())?;
    d.set_item("allow_update", options.allow_update)?;
    d.set_item("compacted", options.compact)?;
    d.set_item("built_bytes", stats.built_size)?;
    d.set_item("bytes", stats.size)?;
    d.set_item("scratch_bytes", stats.scratch_size)?;
    d.set_item("update_scratch_bytes", stats.update_scratch_size)?;
    d.set_item("build_seconds", stats.build_seconds)?;
    d.set_item("batch", stats.batch)?;
    Ok(d)
}

/// The usable devices, best first.
#[pyfunction]
fn devices(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    let infos = crate::gpu::context::list_devices()?;
    infos.iter().map(|info| info_dict(py, info)).collect()
}

/// The SPIR-V modules embedded in this build, by source name (for `spirv-val` in the tests).
#[pyfunction]
fn spirv_modules(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    for (name, bytes) in crate::gpu::shaders::ALL {
        d.set_item(*name, pyo3::types::PyBytes::new(py, bytes))?;
    }
    Ok(d)
}

fn build_options(build: &str, allow_update: bool, compact: bool) -> Result<BuildOptions> {
    Ok(BuildOptions { preference: BuildPreference::parse(build)?, allow_update, compact })
}

/// A borrowed (N, 3) float32/float64 C-contiguous array.
enum Vec3Array<'py> {
    F32(PyReadonlyArray2<'py, f32>),
    F64(PyReadonlyArray2<'py, f64>),
}

impl<'py> Vec3Array<'py> {
    fn extract(name: &str, array: &Bound<'py, PyAny>) -> PyResult<Self> {
        let wrong = || PyTypeError::new_err(format!("{name} must be a float32 or float64 array of shape (N, 3)"));
        let borrowed = if let Ok(a) = array.downcast::<PyArray2<f32>>() {
            Vec3Array::F32(a.readonly())
        } else if let Ok(a) = array.downcast::<PyArray2<f64>>() {
            Vec3Array::F64(a.readonly())
        } else {
            return Err(wrong());
        };
        let columns = match &borrowed {
            Vec3Array::F32(a) => a.shape()[1],
            Vec3Array::F64(a) => a.shape()[1],
        };
        if columns != 3 {
            return Err(wrong());
        }
        Ok(borrowed)
    }

    fn view(&self) -> PyResult<Vec3s<'_>> {
        Ok(match self {
            Vec3Array::F32(a) => Vec3s::F32(a.as_slice()?),
            Vec3Array::F64(a) => Vec3s::F64(a.as_slice()?),
        })
    }
}

/// A borrowed (F, 3) C-contiguous array of triangle corner indices.
enum IndexArray<'py> {
    U16(PyReadonlyArray2<'py, u16>),
    U32(PyReadonlyArray2<'py, u32>),
    I32(PyReadonlyArray2<'py, i32>),
    I64(PyReadonlyArray2<'py, i64>),
}

impl<'py> IndexArray<'py> {
    fn extract(array: &Bound<'py, PyAny>) -> PyResult<Self> {
        let borrowed = if let Ok(a) = array.downcast::<PyArray2<u16>>() {
            IndexArray::U16(a.readonly())
        } else if let Ok(a) = array.downcast::<PyArray2<u32>>() {
            IndexArray::U32(a.readonly())
        } else if let Ok(a) = array.downcast::<PyArray2<i32>>() {
            IndexArray::I32(a.readonly())
        } else if let Ok(a) = array.downcast::<PyArray2<i64>>() {
            IndexArray::I64(a.readonly())
        } else {
            return Err(PyTypeError::new_err("faces must be an int32, int64, uint32 or uint16 array of shape (F, 3)"));
        };
        if array.downcast::<numpy::PyUntypedArray>()?.shape()[1] != 3 {
            return Err(PyTypeError::new_err("faces must have shape (F, 3)"));
        }
        Ok(borrowed)
    }

    fn view(&self) -> PyResult<Indices<'_>> {
        Ok(match self {
            IndexArray::U16(a) => Indices::U16(a.as_slice()?),
            IndexArray::U32(a) => Indices::U32(a.as_slice()?),
            IndexArray::I32(a) => Indices::I32(a.as_slice()?),
            IndexArray::I64(a) => Indices::I64(a.as_slice()?),
        })
    }
}

/// tmin or tmax: one float for every ray, or a borrowed (N,) float64 array.
enum Bound1<'py> {
    All(f64),
    Each(PyReadonlyArray1<'py, f64>),
}

impl<'py> Bound1<'py> {
    fn extract(name: &str, value: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(array) = value.downcast::<PyArray1<f64>>() {
            return Ok(Bound1::Each(array.readonly()));
        }
        value
            .extract::<f64>()
            .map(Bound1::All)
            .map_err(|_| PyTypeError::new_err(format!("{name} must be a float or a float64 array of shape (N,)")))
    }

    fn view(&self) -> PyResult<PerRay<'_>> {
        Ok(match self {
            Bound1::All(v) => PerRay::All(*v),
            Bound1::Each(a) => PerRay::Each(a.as_slice()?),
        })
    }
}

/// Per-ray masks: one 8-bit value or a uint8 array.
enum MaskArray<'py> {
    All(u8),
    Each(PyReadonlyArray1<'py, u8>),
}

impl<'py> MaskArray<'py> {
    fn extract(value: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(array) = value.downcast::<PyArray1<u8>>() {
            return Ok(MaskArray::Each(array.readonly()));
        }
        value
            .extract::<u8>()
            .map(MaskArray::All)
            .map_err(|_| PyValueError::new_err("mask must be an integer in [0, 255] or a uint8 array of shape (N,)"))
    }

    fn view(&self) -> PyResult<Masks<'_>> {
        Ok(match self {
            MaskArray::All(m) => Masks::All(*m),
            MaskArray::Each(a) => Masks::Each(a.as_slice()?),
        })
    }
}

/// A Vulkan device able to build acceleration structures and trace rays.
#[pyclass(name = "Device", module = "vkray._core", frozen)]
struct PyDevice {
    ctx: Arc<Context>,
    tracer: Arc<Tracer>,
}

#[pymethods]
impl PyDevice {
    #[new]
    #[pyo3(signature = (selector=None, backend=None, validation=false))]
    fn new(py: Python<'_>, selector: Option<String>, backend: Option<&str>, validation: bool) -> PyResult<Self> {
        let request = DeviceRequest { selector, backend: backend.map(Backend::parse).transpose()?, validation }
            .with_environment()?;
        let (ctx, tracer) = py.detach(|| -> Result<_> {
            let ctx = Context::new(&request)?;
            let tracer = Arc::new(Tracer::new(&ctx)?);
            Ok((ctx, tracer))
        })?;
        Ok(PyDevice { ctx, tracer })
    }

    #[getter]
    fn info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        info_dict(py, &self.ctx.info)
    }

    #[getter]
    fn backend(&self) -> &'static str {
        self.ctx.backend.name()
    }

    #[getter]
    fn validation(&self) -> bool {
        self.ctx.validation
    }

    #[getter]
    fn limits<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let l = &self.ctx.limits;
        let d = PyDict::new(py);
        d.set_item("min_acceleration_structure_scratch_offset_alignment", l.min_scratch_offset_alignment)?;
        d.set_item("max_primitive_count", l.max_primitive_count)?;
        d.set_item("max_instance_count", l.max_instance_count)?;
        d.set_item("max_geometry_count", l.max_geometry_count)?;
        d.set_item("max_compute_work_group_count", l.max_compute_work_group_count.to_vec())?;
        d.set_item("max_compute_work_group_size", l.max_compute_work_group_size.to_vec())?;
        d.set_item("max_push_constants_size", l.max_push_constants_size)?;
        d.set_item("shader_group_handle_size", l.shader_group_handle_size)?;
        d.set_item("shader_group_handle_alignment", l.shader_group_handle_alignment)?;
        d.set_item("shader_group_base_alignment", l.shader_group_base_alignment)?;
        d.set_item("max_ray_dispatch_invocation_count", l.max_ray_dispatch_invocation_count)?;
        d.set_item("timestamp_period_ns", l.timestamp_period)?;
        d.set_item("timestamp_valid_bits", l.timestamp_valid_bits)?;
        d.set_item("vertex_formats", l.vertex_formats.iter().map(|f| f.name()).collect::<Vec<_>>())?;
        Ok(d)
    }

    /// Where the host's time went in this device's last trace, in seconds.
    #[getter]
    fn last_trace_profile<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let p = self.tracer.last_profile();
        let d = PyDict::new(py);
        d.set_item("rays", p.rays)?;
        d.set_item("chunks", p.chunks)?;
        d.set_item("pack", p.pack)?;
        d.set_item("submit", p.submit)?;
        d.set_item("wait", p.wait)?;
        d.set_item("unpack", p.unpack)?;
        d.set_item("total", p.total)?;
        d.set_item("gpu_upload", p.gpu_upload)?;
        d.set_item("gpu_trace", p.gpu_trace)?;
        d.set_item("gpu_readback", p.gpu_readback)?;
        d.set_item("host_f64", p.host_f64)?;
        Ok(d)
    }

    #[getter]
    fn get_chunk_rays(&self) -> usize {
        self.tracer.chunk_rays()
    }

    #[setter]
    fn set_chunk_rays(&self, rays: usize) -> PyResult<()> {
        Ok(self.tracer.set_chunk_rays(rays)?)
    }

    #[pyo3(signature = (vertices, faces, build="fast_trace", allow_update=false, compact=false, vertex_format="float32"))]
    #[allow(clippy::too_many_arguments)]
    fn mesh(
        &self,
        py: Python<'_>,
        vertices: &Bound<'_, PyAny>,
        faces: &Bound<'_, PyAny>,
        build: &str,
        allow_update: bool,
        compact: bool,
        vertex_format: &str,
    ) -> PyResult<PyMesh> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let vertices = Vec3Array::extract("vertices", vertices)?;
        let faces = IndexArray::extract(faces)?;
        let mesh = Mesh::build(&self.ctx, vertices.view()?, faces.view()?, options, format, &ReleaseGil(py))?;
        Ok(PyMesh { mesh: Arc::new(mesh) })
    }

    /// A set of spheres: (N, 3) centres and radii (one float, or float64 (N,)).
    #[pyo3(signature = (centers, radii, build="fast_trace", compact=false))]
    fn spheres(
        &self,
        py: Python<'_>,
        centers: &Bound<'_, PyAny>,
        radii: &Bound<'_, PyAny>,
        build: &str,
        compact: bool,
    ) -> PyResult<PyMesh> {
        let options = build_options(build, false, compact)?;
        let centers = Vec3Array::extract("centers", centers)?;
        let radii = Bound1::extract("radii", radii)?;
        let mesh = Mesh::spheres(&self.ctx, centers.view()?, radii.view()?, options, &ReleaseGil(py))?;
        Ok(PyMesh { mesh: Arc::new(mesh) })
    }

    /// One mesh of several parts (geometries), each (vertices, faces) with transforms baked in.
    #[pyo3(signature = (parts, build="fast_trace", allow_update=false, compact=false, vertex_format="float32"))]
    fn mesh_parts(
        &self,
        py: Python<'_>,
        parts: Vec<(Bound<'_, PyAny>, Bound<'_, PyAny>)>,
        build: &str,
        allow_update: bool,
        compact: bool,
        vertex_format: &str,
    ) -> PyResult<PyMesh> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let arrays = parts
            .iter()
            .map(|(v, f)| Ok((Vec3Array::extract("vertices", v)?, IndexArray::extract(f)?)))
            .collect::<PyResult<Vec<_>>>()?;
        let views = arrays.iter().map(|(v, f)| Ok((v.view()?, f.view()?))).collect::<PyResult<Vec<_>>>()?;
        let mesh = Mesh::build_parts(&self.ctx, &views, options, format, &ReleaseGil(py))?;
        Ok(PyMesh { mesh: Arc::new(mesh) })
    }

    /// Many meshes in as few submissions as `budget_bytes` of build scratch allow.
    #[pyo3(signature = (items, build="fast_trace", allow_update=false, compact=false, budget_bytes=None, vertex_format="float32"))]
    #[allow(clippy::too_many_arguments)]
    fn meshes(
        &self,
        py: Python<'_>,
        items: Vec<(Bound<'_, PyAny>, Bound<'_, PyAny>)>,
        build: &str,
        allow_update: bool,
        compact: bool,
        budget_bytes: Option<u64>,
        vertex_format: &str,
    ) -> PyResult<Vec<PyMesh>> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let arrays = items
            .iter()
            .map(|(v, f)| Ok((Vec3Array::extract("vertices", v)?, IndexArray::extract(f)?)))
            .collect::<PyResult<Vec<_>>>()?;
        let views = arrays.iter().map(|(v, f)| Ok([(v.view()?, f.view()?)])).collect::<PyResult<Vec<_>>>()?;
        let items: Vec<&[(Vec3s, Indices)]> = views.iter().map(|v| v.as_slice()).collect();
        let meshes =
            Mesh::build_many(&self.ctx, &items, options, format, budget_bytes.unwrap_or(u64::MAX), &ReleaseGil(py))?;
        Ok(meshes.into_iter().map(|mesh| PyMesh { mesh: Arc::new(mesh) }).collect())
    }

    /// `items`: (mesh, transform or None, custom_index, mask) per instance.
    #[pyo3(signature = (items, build="fast_build", allow_update=false, compact=false))]
    fn scene(
        &self,
        py: Python<'_>,
        items: Vec<InstanceItem<'_>>,
        build: &str,
        allow_update: bool,
        compact: bool,
    ) -> PyResult<PyScene> {
        let options = build_options(build, allow_update, compact)?;
        let mut instances = Vec::with_capacity(items.len());
        for (i, (mesh, transform, custom_index, mask, flags)) in items.iter().enumerate() {
            let transform = match transform {
                None => IDENTITY,
                Some(t) => {
                    let t = t.downcast::<PyArray2<f64>>().map_err(|_| {
                        PyTypeError::new_err(format!(
                            "instance {i}: transform must be a float64 (3, 4) or (4, 4) array"
                        ))
                    })?;
                    let rows = t.shape()[0];
                    let t = t.readonly();
                    instance_transform(t.as_slice()?, rows).map_err(|e| match e {
                        Error::InvalidValue(m) => Error::InvalidValue(format!("instance {i}: {m}")),
                        Error::InvalidType(m) => Error::InvalidType(format!("instance {i}: {m}")),
                        other => other,
                    })?
                }
            };
            let flags = InstanceFlags {
                cull_disable: flags & 1 != 0,
                flip_facing: flags & 2 != 0,
                force_opaque: flags & 4 != 0,
                force_no_opaque: flags & 8 != 0,
            };
            if flags.force_opaque && flags.force_no_opaque {
                return Err(PyValueError::new_err(format!("instance {i} cannot be forced both opaque and non-opaque")));
            }
            instances.push(Instance {
                mesh: mesh.mesh.clone(),
                transform,
                custom_index: *custom_index,
                mask: *mask,
                flags,
            });
        }
        let scene = Scene::build(&self.ctx, &instances, options, &ReleaseGil(py))?;
        Ok(PyScene { scene: RwLock::new(scene), tracer: self.tracer.clone() })
    }
}

/// A triangle mesh and its bottom-level acceleration structure.
#[pyclass(name = "Mesh", module = "vkray._core", frozen)]
struct PyMesh {
    mesh: Arc<Mesh>,
}

#[pymethods]
impl PyMesh {
    #[getter]
    fn vertex_count(&self) -> usize {
        self.mesh.vertex_count
    }

    #[getter]
    fn triangle_count(&self) -> usize {
        self.mesh.triangle_count
    }

    #[getter]
    fn part_count(&self) -> usize {
        self.mesh.part_count()
    }

    #[getter]
    fn kind(&self) -> &'static str {
        match self.mesh.kind {
            MeshKind::Triangles => "triangles",
            MeshKind::Spheres => "spheres",
        }
    }

    #[getter]
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = stats_dict(py, &self.mesh.stats, &self.mesh.options)?;
        d.set_item("update_seconds", self.mesh.last_update_seconds())?;
        d.set_item("vertex_format", self.mesh.vertex_format.name())?;
        d.set_item("vertex_bytes", self.mesh.vertex_format.stride() * self.mesh.vertex_count)?;
        Ok(d)
    }

    /// Moves the vertices ((V, 3), same V) and refits the BLAS in place.
    fn update(&self, py: Python<'_>, vertices: &Bound<'_, PyAny>) -> PyResult<()> {
        let vertices = Vec3Array::extract("vertices", vertices)?;
        self.mesh.update(vertices.view()?, &ReleaseGil(py))?;
        Ok(())
    }
}

/// Instances under a top-level acceleration structure, ready for queries.
#[pyclass(name = "Scene", module = "vkray._core", frozen)]
struct PyScene {
    /// Queries share it, `update` takes it alone; neither waits for the other (a wait that held
    /// the GIL could deadlock with a query that needs the GIL back): contention is an error.
    scene: RwLock<Scene>,
    tracer: Arc<Tracer>,
}

const FIELD_NAMES: [(&str, Field); 7] = [
    ("t", Field::T),
    ("prim_id", Field::Prim),
    ("instance_id", Field::Instance),
    ("custom_index", Field::Custom),
    ("uv", Field::Uv),
    ("normal", Field::Normal),
    ("geometry_id", Field::Geometry),
];

/// (mesh, transform or None, custom_index, mask, flags) of one instance, as the Python layer
/// passes it; flags: 1 cull_disable, 2 flip_facing, 4 force_opaque, 8 force_no_opaque.
type InstanceItem<'py> = (PyRef<'py, PyMesh>, Option<Bound<'py, PyAny>>, u32, u8, u8);

impl PyScene {
    fn read(&self) -> PyResult<std::sync::RwLockReadGuard<'_, Scene>> {
        self.scene.try_read().map_err(|_| PyRuntimeError::new_err("the scene is being updated by another thread"))
    }
}

#[pymethods]
impl PyScene {
    /// Refits the TLAS: new `transforms` ((N, 3, 4) or (N, 4, 4) float64) and/or `masks` ((N,) uint8)
    /// for its N instances, and its meshes' own updates.
    #[pyo3(signature = (transforms=None, masks=None))]
    fn update(
        &self,
        py: Python<'_>,
        transforms: Option<PyReadonlyArray3<'_, f64>>,
        masks: Option<PyReadonlyArray1<'_, u8>>,
    ) -> PyResult<()> {
        let transforms = match &transforms {
            None => None,
            Some(t) => {
                let rows = t.shape()[1];
                let values = t.as_slice()?;
                let per = rows * 4;
                if t.shape()[2] != 4 || per == 0 {
                    return Err(PyValueError::new_err("transforms must have shape (N, 3, 4) or (N, 4, 4)"));
                }
                Some(values.chunks_exact(per).map(|m| instance_transform(m, rows)).collect::<crate::Result<Vec<_>>>()?)
            }
        };
        let masks = masks.as_ref().map(|m| m.as_slice().map(|m| m.to_vec())).transpose()?;
        let mut scene = self
            .scene
            .try_write()
            .map_err(|_| PyRuntimeError::new_err("the scene is in use by a query running in another thread"))?;
        scene.update(transforms, masks, &ReleaseGil(py))?;
        Ok(())
    }

    #[getter]
    fn instance_count(&self) -> PyResult<usize> {
        Ok(self.read()?.instance_count)
    }

    #[getter]
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let scene = self.read()?;
        let d = stats_dict(py, &scene.stats, &scene.options)?;
        d.set_item("update_seconds", scene.last_update_seconds())?;
        Ok(d)
    }

    /// Traces rays; returns {field name: array} for the fields asked for.
    /// `query` is "closest" or "occluded"; `precision` one of the tiers of `Precision`.
    #[pyo3(signature = (origins, directions, tmin, tmax, query, fields, precision="fast", cull=None, mask=None))]
    #[allow(clippy::too_many_arguments)]
    fn trace<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        query: &str,
        fields: Vec<String>,
        precision: &str,
        cull: Option<&str>,
        mask: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let precision = Precision::parse(precision)?;
        let cull = Cull::parse(cull)?;
        let mask = mask.map(MaskArray::extract).transpose()?.unwrap_or(MaskArray::All(0xFF));
        let wide = precision.is_f64();
        let query = match query {
            "closest" => Query::Closest,
            "occluded" => Query::Occluded,
            other => {
                return Err(PyValueError::new_err(format!("query must be 'closest' or 'occluded', got {other:?}")))
            }
        };
        let origins = Vec3Array::extract("origins", origins)?;
        let directions = Vec3Array::extract("directions", directions)?;
        let tmin = Bound1::extract("tmin", tmin)?;
        let tmax = Bound1::extract("tmax", tmax)?;
        let result = PyDict::new(py);
        let rays = Rays {
            origins: origins.view()?,
            directions: directions.view()?,
            tmin: tmin.view()?,
            tmax: tmax.view()?,
            mask: mask.view()?,
        };
        let n = rays.len();

        let mut arrays: Vec<(Field, Bound<'py, PyAny>)> = Vec::new();
        let mut position = None;
        for name in &fields {
            if name == "position" {
                let array = if wide {
                    unsafe { PyArray2::<f64>::new(py, [n, 3], false) }.into_any()
                } else {
                    unsafe { PyArray2::<f32>::new(py, [n, 3], false) }.into_any()
                };
                result.set_item(name, &array)?;
                position = Some(array);
                continue;
            }
            let Some((_, field)) = FIELD_NAMES.iter().find(|(n, _)| n == name) else {
                return Err(PyValueError::new_err(format!("unknown hit field {name:?}")));
            };
            let array: Bound<'py, PyAny> = match (field, wide) {
                (Field::T, false) => unsafe { PyArray1::<f32>::new(py, [n], false) }.into_any(),
                (Field::T, true) => unsafe { PyArray1::<f64>::new(py, [n], false) }.into_any(),
                (Field::Uv, false) => unsafe { PyArray2::<f32>::new(py, [n, 2], false) }.into_any(),
                (Field::Uv, true) => unsafe { PyArray2::<f64>::new(py, [n, 2], false) }.into_any(),
                (Field::Normal, _) => unsafe { PyArray2::<f32>::new(py, [n, 3], false) }.into_any(),
                _ => unsafe { PyArray1::<i32>::new(py, [n], false) }.into_any(),
            };
            result.set_item(name, &array)?;
            arrays.push((*field, array));
        }
        let mut sink = HitSink::default();
        for (field, array) in &arrays {
            // SAFETY: freshly created, C-contiguous arrays nobody else holds yet; written only
            // through this slice until trace returns.
            let bytes = unsafe {
                let untyped = array.downcast_unchecked::<numpy::PyUntypedArray>();
                let len = untyped.len() * field.bytes_per_ray(wide) / field_elements(*field);
                let ptr = (*untyped.as_array_ptr()).data as *mut u8;
                std::slice::from_raw_parts_mut(ptr, len)
            };
            sink.set(*field, bytes);
        }
        if let Some(array) = &position {
            // SAFETY: as above; (n, 3) floats of 4 or 8 bytes.
            sink.position = Some(unsafe {
                let untyped = array.downcast_unchecked::<numpy::PyUntypedArray>();
                let ptr = (*untyped.as_array_ptr()).data as *mut u8;
                std::slice::from_raw_parts_mut(ptr, n * 3 * if wide { 8 } else { 4 })
            });
        }
        let request = Request { query, precision, cull };
        self.tracer.trace(&*self.read()?, &rays, request, &mut sink, &ReleaseGil(py))?;
        Ok(result)
    }
}

fn field_elements(field: Field) -> usize {
    match field {
        Field::Uv => 2,
        Field::Normal => 3,
        _ => 1,
    }
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_function(wrap_pyfunction!(devices, m)?)?;
    m.add_function(wrap_pyfunction!(spirv_modules, m)?)?;
    m.add_class::<PyDevice>()?;
    m.add_class::<PyMesh>()?;
    m.add_class::<PyScene>()?;
    m.add("VkrayError", py.get_type::<VkrayError>())?;
    m.add("NoDeviceError", py.get_type::<NoDeviceError>())?;
    m.add("UnsupportedError", py.get_type::<UnsupportedError>())?;
    m.add("VulkanError", py.get_type::<VulkanError>())?;
    m.add("ValidationError", py.get_type::<ValidationError>())?;
    Ok(())
}

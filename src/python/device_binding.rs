//! `vkray._core.Device`: opens a device and builds meshes and scenes on it.

use std::path::PathBuf;
use std::sync::{Arc, RwLock};

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::calls::{run, run_reporting};
use super::cuda_staging;
use super::device_engines::{cuda_of, opened_cuda, DeviceTracer};
use super::dlpack::{self, PyCudaArray};
use super::mesh_binding::PyMesh;
use super::numpy_views::{Bound1, IndexArray, Vec3Array};
use super::scene_binding::{InstanceItem, PyScene};
use crate::error::{Error, Result};
use crate::geometry::arrays::instance_transform;
use crate::geometry::build_options::{BuildOptions, BuildPreference};
use crate::geometry::interrupt::NoInterrupt;
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::context::{Backend, Context, DeviceInfo, DeviceRequest};
use crate::gpu::cuda::Cuda;
use crate::scene::{Instance, InstanceFlags, Mesh, MeshBatch, MeshInput, IDENTITY};
use crate::trace::{CpuEngine, Engine, Tracer, VulkanEngine};

/// The CPU engine's entry of `devices()`, in the keys of a Vulkan device's.
pub(super) fn cpu_info_dict<'py>(py: Python<'py>, engine: &CpuEngine) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("index", 0)?;
    d.set_item("name", engine.name())?;
    d.set_item("device_type", "cpu")?;
    d.set_item("is_software", false)?;
    d.set_item("api_version", "")?;
    let v = engine.embree_version();
    d.set_item("driver", format!("Embree {}.{}.{}", v / 10000, v / 100 % 100, v % 100))?;
    d.set_item("ray_query", false)?;
    d.set_item("ray_tracing_pipeline", false)?;
    d.set_item("shader_float64", true)?;
    d.set_item("engine", "cpu")?;
    Ok(d)
}

pub(super) fn info_dict<'py>(py: Python<'py>, info: &DeviceInfo) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("engine", "vulkan")?;
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

fn build_options(build: &str, allow_update: bool, compact: bool) -> Result<BuildOptions> {
    Ok(BuildOptions { preference: BuildPreference::parse(build)?, allow_update, compact })
}

/// A device that builds hierarchies and traces rays: a Vulkan device, or the CPU engine.
#[pyclass(name = "Device", module = "vkray._core", frozen)]
pub(super) struct PyDevice {
    /// The Vulkan device (None for the CPU engine).
    ctx: Option<Arc<Context>>,
    tracer: Arc<DeviceTracer>,
}

impl PyDevice {
    /// Builds one mesh on the device's engine.
    fn build_one(&self, item: MeshInput, options: BuildOptions, format: VertexFormat) -> Result<Mesh> {
        let batch = MeshBatch { items: &[item], options, format, scratch_budget: u64::MAX, interrupt: &NoInterrupt };
        let mut meshes = self.tracer.engine().build_meshes(batch)?;
        Ok(meshes.pop().expect("one mesh per input"))
    }

    /// This device's CUDA device, where its GPU shares memory with CUDA; else the TypeError of
    /// CUDA arrays it cannot read, naming `array` where given.
    fn cuda_for(&self, py: Python<'_>, array: Option<(&str, &Bound<'_, PyAny>)>) -> PyResult<Arc<Cuda>> {
        // Without the GIL: the first call opens CUDA (cuInit, a lock of the open devices).
        if let Some(cuda) = run(py, |_| Ok(cuda_of(&self.tracer)?.1))? {
            return Ok(cuda);
        }
        let device = self.tracer.engine().name();
        Err(match array {
            Some((name, value)) => dlpack::unreadable(device, [(name, value), (name, value)]),
            None => PyTypeError::new_err(format!("{device} does not share memory with CUDA")),
        })
    }
}

#[pymethods]
impl PyDevice {
    /// `selector` "cpu" (or `VKRAY_DEVICE=cpu`) opens the CPU engine, Embree loaded from the
    /// first of `library_paths` (folders) that has it; anything else a Vulkan device.
    #[new]
    #[pyo3(signature = (selector=None, backend=None, validation=false, library_paths=Vec::new()))]
    fn new(
        py: Python<'_>,
        selector: Option<String>,
        backend: Option<&str>,
        validation: bool,
        library_paths: Vec<PathBuf>,
    ) -> PyResult<Self> {
        let request = DeviceRequest { selector, backend: backend.map(Backend::parse).transpose()?, validation }
            .with_environment()?;
        if request.selector.as_deref().is_some_and(|s| s.trim().eq_ignore_ascii_case("cpu")) {
            if backend.is_some() {
                return Err(PyValueError::new_err("the CPU engine has no backend: leave backend=None"));
            }
            let tracer: Arc<DeviceTracer> = Arc::new(Tracer::new(run(py, |_| CpuEngine::new(&library_paths))?));
            return Ok(PyDevice { ctx: None, tracer });
        }
        let (ctx, tracer) = run(py, |_| -> Result<_> {
            let ctx = Context::new(&request)?;
            let tracer: Arc<DeviceTracer> = Arc::new(Tracer::new(VulkanEngine::new(&ctx)?));
            Ok((ctx, tracer))
        })?;
        Ok(PyDevice { ctx: Some(ctx), tracer })
    }

    #[getter]
    fn info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        match (&self.ctx, self.tracer.engine().as_any().downcast_ref::<CpuEngine>()) {
            (Some(ctx), _) => info_dict(py, &ctx.info),
            (None, Some(cpu)) => cpu_info_dict(py, cpu),
            (None, None) => unreachable!("a device without a Vulkan context is the CPU engine"),
        }
    }

    /// "ray_query" or "pipeline" for a Vulkan device, "cpu" for the CPU engine.
    #[getter]
    fn backend(&self) -> &'static str {
        self.ctx.as_ref().map_or("cpu", |ctx| ctx.backend.name())
    }

    #[getter]
    fn validation(&self) -> bool {
        self.ctx.as_ref().is_some_and(|ctx| ctx.validation)
    }

    #[getter]
    fn limits<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let Some(ctx) = &self.ctx else {
            // Embree's own bounds: ids of 32 bits.
            d.set_item("max_primitive_count", u32::MAX - 1)?;
            d.set_item("max_instance_count", u32::MAX - 1)?;
            d.set_item("max_geometry_count", u32::MAX - 1)?;
            d.set_item("vertex_formats", ["float32", "float16", "snorm16"])?;
            return Ok(d);
        };
        let l = &ctx.limits;
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
        d.set_item("ray_traversal_primitive_culling", l.ray_traversal_primitive_culling)?;
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
        d.set_item("store", p.store)?;
        d.set_item("order", p.order)?;
        d.set_item("host_threads", p.host_threads)?;
        d.set_item("ray_bytes", p.ray_bytes)?;
        d.set_item("gpu_columns", p.gpu_columns)?;
        Ok(d)
    }

    /// The staging this device keeps idle between queries: ``bytes``, ``kept``, ``made``, and
    /// ``pinned_bytes`` (page-locked host memory of its CUDA context).
    #[getter]
    fn idle_memory<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let memory = self.tracer.idle_memory();
        let d = PyDict::new(py);
        d.set_item("bytes", memory.bytes)?;
        d.set_item("kept", memory.items)?;
        d.set_item("made", memory.made)?;
        d.set_item("pinned_bytes", opened_cuda(&self.tracer).map_or(0, |cuda| cuda.idle_host_bytes()))?;
        Ok(d)
    }

    /// Frees the idle staging (a CUDA lease's release waits for its stream: without the GIL),
    /// and the page-locked host memory CUDA arrays crossed through.
    fn release_idle_memory(&self, py: Python<'_>) -> PyResult<()> {
        run(py, |_| {
            self.tracer.release_idle_memory();
            // Only where CUDA was opened: freeing memory starts nothing.
            match opened_cuda(&self.tracer) {
                Some(cuda) => cuda.release_idle_host_memory(),
                None => Ok(()),
            }
        })
    }

    /// CUDA's index of this device (DLPack's device id for its CUDA arrays), or None where it is
    /// not a CUDA device that shares memory with Vulkan.
    #[getter]
    fn cuda_device(&self, py: Python<'_>) -> PyResult<Option<i32>> {
        run(py, |_| Ok(cuda_of(&self.tracer)?.1.map(|cuda| cuda.ordinal)))
    }

    /// `value`, a CUDA array on this device's GPU (`name` in errors), read into host memory for
    /// a query without a GPU-resident path: (bytes, numpy dtype, shape, byte strides), which the
    /// Python layer views as an array.
    #[allow(clippy::type_complexity)]
    fn cuda_read<'py>(
        &self,
        value: &Bound<'py, PyAny>,
        name: &str,
    ) -> PyResult<(Bound<'py, PyArray1<u8>>, &'static str, Vec<usize>, Vec<usize>)> {
        let cuda = self.cuda_for(value.py(), Some((name, value)))?;
        let copy = cuda_staging::read_to_host(&cuda, value, name)?;
        Ok((copy.bytes, copy.dtype, copy.shape, copy.strides))
    }

    /// A contiguous host array's bytes (numpy `dtype`, `shape`) as a new `vkray.CudaArray` on
    /// this device's GPU: a query's answer to CUDA arrays, where it was computed through the host.
    fn cuda_write(
        &self,
        py: Python<'_>,
        bytes: PyReadonlyArray1<'_, u8>,
        dtype: &str,
        shape: Vec<usize>,
    ) -> PyResult<PyCudaArray> {
        let cuda = self.cuda_for(py, None)?;
        cuda_staging::write_from_host(&cuda, bytes, dtype, shape)
    }

    /// Makes this thread's query answers (from now until `pinned_answers(False)`) in page-locked
    /// memory of the device's GPU, from which `cuda_write` copies them by DMA alone: for a query
    /// of CUDA arrays that runs through the host (`Scene._through_host`). Arrays under 1 MiB, and
    /// any where the driver pins no more, stay numpy's.
    fn pinned_answers(&self, py: Python<'_>, on: bool) -> PyResult<()> {
        let cuda = if on { Some(self.cuda_for(py, None)?) } else { None };
        cuda_staging::set_pinned_answers(cuda);
        Ok(())
    }

    #[getter]
    fn get_chunk_rays(&self) -> usize {
        self.tracer.chunk_rays()
    }

    #[setter]
    fn set_chunk_rays(&self, rays: usize) -> PyResult<()> {
        Ok(self.tracer.set_chunk_rays(rays)?)
    }

    #[getter]
    fn get_host_threads(&self) -> Option<usize> {
        self.tracer.host_threads()
    }

    #[setter]
    fn set_host_threads(&self, threads: Option<usize>) -> PyResult<()> {
        Ok(self.tracer.set_host_threads(threads)?)
    }

    #[pyo3(signature = (vertices, faces, build="fast_trace", allow_update=false, compact=false, vertex_format="float32", opacity=None))]
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
        opacity: Option<PyReadonlyArray1<'_, f32>>,
    ) -> PyResult<PyMesh> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let vertices = Vec3Array::extract("vertices", vertices)?;
        let faces = IndexArray::extract(faces)?;
        let (vertices, faces) = (vertices.view()?, faces.view()?);
        let opacity = opacity.map(|o| o.as_array().to_vec());
        let parts = [(vertices, faces)];
        let mesh = run(py, |_| self.build_one(MeshInput { parts: &parts, opacity }, options, format))?;
        Ok(PyMesh::new(mesh))
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
        let (centers, radii) = (centers.view()?, radii.view()?);
        let mesh = run(py, |_| self.tracer.engine().build_spheres(centers, radii, options))?;
        Ok(PyMesh::new(mesh))
    }

    /// One mesh of several parts (geometries), each (vertices, faces) with transforms baked in.
    #[pyo3(signature = (parts, build="fast_trace", allow_update=false, compact=false, vertex_format="float32", opacity=None))]
    #[allow(clippy::too_many_arguments)]
    fn mesh_parts(
        &self,
        py: Python<'_>,
        parts: Vec<(Bound<'_, PyAny>, Bound<'_, PyAny>)>,
        build: &str,
        allow_update: bool,
        compact: bool,
        vertex_format: &str,
        opacity: Option<PyReadonlyArray1<'_, f32>>,
    ) -> PyResult<PyMesh> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let opacity = opacity.map(|o| o.as_array().to_vec());
        let arrays = parts
            .iter()
            .map(|(v, f)| Ok((Vec3Array::extract("vertices", v)?, IndexArray::extract(f)?)))
            .collect::<PyResult<Vec<_>>>()?;
        let views = arrays.iter().map(|(v, f)| Ok((v.view()?, f.view()?))).collect::<PyResult<Vec<_>>>()?;
        let mesh = run(py, |_| self.build_one(MeshInput { parts: &views, opacity }, options, format))?;
        Ok(PyMesh::new(mesh))
    }

    /// Many meshes in as few submissions as `budget_bytes` of build scratch allow.
    #[pyo3(signature = (items, build="fast_trace", allow_update=false, compact=false, budget_bytes=None, vertex_format="float32", progress=None))]
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
        progress: Option<Py<PyAny>>,
    ) -> PyResult<Vec<PyMesh>> {
        let options = build_options(build, allow_update, compact)?;
        let format = VertexFormat::parse(vertex_format)?;
        let arrays = items
            .iter()
            .map(|(v, f)| Ok((Vec3Array::extract("vertices", v)?, IndexArray::extract(f)?)))
            .collect::<PyResult<Vec<_>>>()?;
        let views = arrays.iter().map(|(v, f)| Ok([(v.view()?, f.view()?)])).collect::<PyResult<Vec<_>>>()?;
        let items: Vec<MeshInput> = views.iter().map(|v| MeshInput { parts: v.as_slice(), opacity: None }).collect();
        let budget = budget_bytes.unwrap_or(u64::MAX);
        let meshes = run_reporting(py, progress, |interrupt| {
            let batch = MeshBatch { items: &items, options, format, scratch_budget: budget, interrupt };
            self.tracer.engine().build_meshes(batch)
        })?;
        Ok(meshes.into_iter().map(PyMesh::new).collect())
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
                    let t = super::numpy_views::read(&format!("instance {i}: transform"), t)?;
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
        let scene = run(py, |_| self.tracer.engine().build_scene(&instances, options))?;
        Ok(PyScene { scene: RwLock::new(scene), tracer: self.tracer.clone() })
    }
}

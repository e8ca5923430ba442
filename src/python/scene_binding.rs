//! `vkray._core.Scene`: queries and refits. Queries share the scene and `update` takes it alone;
//! both wait with the GIL released, so neither can deadlock with a thread that needs the GIL.

use std::sync::RwLock;

use numpy::{
    PyArray1, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray3, PyReadwriteArrayDyn,
    PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::calls::{run, run_reporting};
use super::device_engines::{cuda_all_hits_of, cuda_of, inside_points_of, DeviceTracer};
use super::mesh_binding::stats_dict;
use super::mesh_binding::PyMesh;
use super::numpy_views::{Bound1, MaskArray, Vec3Array};
use super::{cuda_batch, dlpack};
use crate::geometry::arrays::instance_transform;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::rays::Rays;
use crate::geometry::sensor::{SensorKind, SensorRays};
use crate::gpu::memory::short_of_host_memory;
use crate::scene::Scene;
use crate::trace::hit_columns::{AskedColumn, HitColumn, HitColumns};
use crate::trace::hit_fields::{position_bytes_per_ray, FIELDS};
use crate::trace::request::spheres_on_host;
use crate::trace::vulkan::cuda_all_hits::{cuda_all_hits_refusal, CudaAllHitsOutcome};
use crate::trace::vulkan::packed_rays::device_rays_refusal;
use crate::trace::{CpuEngine, Cull, Field, HitSink, Precision, Query, Request, SignedDistance, VulkanEngine};

/// Instances under a top-level acceleration structure, ready for queries.
#[pyclass(name = "Scene", module = "vkray._core", frozen)]
pub(super) struct PyScene {
    pub(super) scene: RwLock<Scene>,
    pub(super) tracer: std::sync::Arc<DeviceTracer>,
}

/// (mesh, transform or None, custom_index, mask, flags) of one instance, as the Python layer
/// passes it; flags: 1 cull_disable, 2 flip_facing, 4 force_opaque, 8 force_no_opaque.
pub(super) type InstanceItem<'py> = (PyRef<'py, PyMesh>, Option<Bound<'py, PyAny>>, u32, u8, u8);

/// One output array: where the trace writes it, and the numpy array.
type Output<'py> = (Target, Bound<'py, PyUntypedArray>);

/// Where a trace's output array goes in its `HitSink`.
#[derive(Clone, Copy)]
enum Target {
    Field(Field),
    Position,
    Hit,
}

impl Target {
    fn attach<'a>(self, sink: &mut HitSink<'a>, bytes: &'a mut [u8]) {
        match self {
            Target::Field(field) => sink.set(field, bytes),
            Target::Position => sink.position = Some(bytes),
            Target::Hit => sink.hit = Some(bytes),
        }
    }
}

impl PyScene {
    /// Reads the scene for a moment (getters): waits for an update with the GIL released.
    fn with_scene<T: Send>(&self, py: Python<'_>, read: impl FnOnce(&Scene) -> T + Send) -> PyResult<T> {
        run(py, |_| Ok(read(&self.scene.read().unwrap_or_else(|e| e.into_inner()))))
    }

    /// Runs a query on the scene with the GIL released, reporting to `progress`; its host passes
    /// run on the device's own threads where it has them (`Device.host_threads`).
    fn query<T: Send>(
        &self,
        py: Python<'_>,
        progress: Option<Py<PyAny>>,
        work: impl FnOnce(&Scene, &dyn Interrupt) -> crate::Result<T> + Send,
    ) -> PyResult<T> {
        run_reporting(py, progress, |interrupt| {
            self.tracer.on_host_threads(|| work(&self.scene.read().unwrap_or_else(|e| e.into_inner()), interrupt))
        })
    }
}

/// The borrowed arrays of a batch of rays, as the Python layer passes them.
struct RayArrays<'py> {
    origins: Vec3Array<'py>,
    directions: Vec3Array<'py>,
    tmin: Bound1<'py>,
    tmax: Bound1<'py>,
    mask: MaskArray<'py>,
    /// A sensor's rays instead of the arrays (then empty).
    sensor: Option<SensorRays>,
}

impl<'py> RayArrays<'py> {
    fn extract(
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        mask: Option<&Bound<'py, PyAny>>,
        sensor: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Self> {
        Ok(RayArrays {
            origins: Vec3Array::extract("origins", origins)?,
            directions: Vec3Array::extract("directions", directions)?,
            tmin: Bound1::extract("tmin", tmin)?,
            tmax: Bound1::extract("tmax", tmax)?,
            mask: mask.map(MaskArray::extract).transpose()?.unwrap_or(MaskArray::All(0xFF)),
            sensor: sensor.map(sensor_rays).transpose()?,
        })
    }

    /// The core's view of the batch (no copies).
    fn rays(&self) -> PyResult<Rays<'_>> {
        Ok(Rays {
            origins: self.origins.view()?,
            directions: self.directions.view()?,
            tmin: self.tmin.view()?,
            tmax: self.tmax.view()?,
            mask: self.mask.view()?,
            sensor: self.sensor.as_ref(),
        })
    }
}

/// A sensor's rays from the parameters python/vkray/sensors.py derives (`Sensor._generator`, in
/// the layout `_api._sensor_record` gives them).
fn sensor_rays(d: &Bound<'_, PyDict>) -> PyResult<SensorRays> {
    let item = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        d.get_item(key)?.ok_or_else(|| PyValueError::new_err(format!("sensor record lacks {key:?}")))
    };
    let kind = match item("kind")?.extract::<u32>()? {
        1 => SensorKind::Pinhole,
        2 => SensorKind::Orthographic,
        3 => SensorKind::Lidar,
        other => return Err(PyValueError::new_err(format!("unknown sensor kind {other}"))),
    };
    let axes: Vec<f32> = item("axes")?.extract()?;
    let origin: Vec<f32> = item("origin")?.extract()?;
    if axes.len() != 9 || origin.len() != 3 {
        return Err(PyValueError::new_err("a sensor record needs 3 origin and 9 axis values"));
    }
    let sensor = SensorRays {
        kind,
        origin: [origin[0], origin[1], origin[2]],
        axes: [0, 1, 2].map(|r| [axes[3 * r], axes[3 * r + 1], axes[3 * r + 2]]),
        columns: item("columns")?.extract()?,
        rows: item("rows")?.extract()?,
        pixel_offset: item("pixel_offset")?.extract()?,
        tmin: item("tmin")?.extract()?,
        tmax: item("tmax")?.extract()?,
        table: item("table")?.extract()?,
    };
    sensor.check()?;
    Ok(sensor)
}

/// A new uninitialized numpy array (numpy raises MemoryError where it cannot be had); the core
/// writes every element before the caller sees it.
fn empty<'py>(py: Python<'py>, shape: &[usize], dtype: &str) -> PyResult<Bound<'py, PyUntypedArray>> {
    if let Some(pinned) = super::cuda_staging::pinned_empty(py, shape, dtype)? {
        return Ok(pinned);
    }
    let array = py.import("numpy")?.getattr("empty")?.call1((shape.to_vec(), dtype))?;
    Ok(array.downcast_into::<PyUntypedArray>()?)
}

/// A hit field's output: where the trace writes it, its shape and dtype for `n` rays in the
/// query's widths. `position` and `hit` (bool: whether the ray hit anything) are made from the
/// fields on the host.
fn output_layout(name: &str, n: usize, wide: bool) -> PyResult<(Target, Vec<usize>, &'static str)> {
    let float = if wide { "float64" } else { "float32" };
    match name {
        "position" => return Ok((Target::Position, vec![n, 3], float)),
        "hit" => return Ok((Target::Hit, vec![n], "bool")),
        _ => {}
    }
    let Some(field) = FIELDS.iter().copied().find(|f| f.name() == name) else {
        return Err(PyValueError::new_err(format!("unknown hit field {name:?}")));
    };
    Ok(match field {
        Field::T => (Target::Field(field), vec![n], float),
        Field::Uv => (Target::Field(field), vec![n, 2], float),
        Field::Normal => (Target::Field(field), vec![n, 3], "float32"),
        _ => (Target::Field(field), vec![n], "int32"),
    })
}

/// The numpy array of each field asked for, in the query's widths.
fn allocate<'py>(py: Python<'py>, fields: &[String], n: usize, wide: bool) -> PyResult<Vec<(String, Output<'py>)>> {
    let mut arrays = Vec::with_capacity(fields.len());
    for name in fields {
        let (field, shape, dtype) = output_layout(name, n, wide)?;
        arrays.push((name.clone(), (field, empty(py, &shape, dtype)?)));
    }
    Ok(arrays)
}

/// A caller's output array (`out=`), borrowed for writing for the whole call: numpy's borrow
/// tracking refuses one that is read-only or shares memory with the rays (borrowed for reading
/// first) or with another output.
enum OutArray<'py> {
    F32(PyReadwriteArrayDyn<'py, f32>),
    F64(PyReadwriteArrayDyn<'py, f64>),
    I32(PyReadwriteArrayDyn<'py, i32>),
}

impl<'py> OutArray<'py> {
    /// `array` as field `name`'s output for `n` rays (its shape and dtype exactly).
    fn borrow(name: &str, array: &Bound<'py, PyAny>, n: usize, wide: bool) -> PyResult<(Target, OutArray<'py>)> {
        let (field, shape, dtype) = output_layout(name, n, wide)?;
        let refused = |why: String| PyValueError::new_err(format!("out's {name} {why}"));
        let borrowed = match dtype {
            "float32" => array.downcast::<PyArrayDyn<f32>>().ok().map(|a| a.try_readwrite().map(OutArray::F32)),
            "float64" => array.downcast::<PyArrayDyn<f64>>().ok().map(|a| a.try_readwrite().map(OutArray::F64)),
            "int32" => array.downcast::<PyArrayDyn<i32>>().ok().map(|a| a.try_readwrite().map(OutArray::I32)),
            _ => return Err(refused("is no output of out= (intersect's out= takes hit fields)".into())),
        };
        let out = borrowed.ok_or_else(|| refused(format!("must be a numpy array of {dtype}")))?.map_err(|e| {
            refused(format!(
                "cannot be written by this call ({e}: read-only, or sharing memory with the rays or another output)"
            ))
        })?;
        let (got, contiguous) = match &out {
            OutArray::F32(a) => (a.shape().to_vec(), a.is_c_contiguous()),
            OutArray::F64(a) => (a.shape().to_vec(), a.is_c_contiguous()),
            OutArray::I32(a) => (a.shape().to_vec(), a.is_c_contiguous()),
        };
        if got != shape {
            return Err(refused(format!("has shape {got:?}, the query writes {shape:?}")));
        }
        if !contiguous {
            return Err(refused("must be C-contiguous".into()));
        }
        Ok((field, out))
    }

    /// The array's bytes (C-contiguous, checked when borrowed).
    fn bytes(&mut self) -> PyResult<&mut [u8]> {
        let not_contiguous = |e: numpy::NotContiguousError| PyValueError::new_err(e.to_string());
        Ok(match self {
            OutArray::F32(a) => bytemuck::cast_slice_mut(a.as_slice_mut().map_err(not_contiguous)?),
            OutArray::F64(a) => bytemuck::cast_slice_mut(a.as_slice_mut().map_err(not_contiguous)?),
            OutArray::I32(a) => bytemuck::cast_slice_mut(a.as_slice_mut().map_err(not_contiguous)?),
        })
    }
}

/// The bytes of a fresh numpy array this call made and nobody else holds yet.
// A mutable view from a shared handle: sound only because the array is this call's own (below).
#[allow(clippy::mut_from_ref)]
fn bytes_of<'a>(array: &'a Bound<'_, PyUntypedArray>) -> &'a mut [u8] {
    let bytes = array.len() * array.dtype().itemsize();
    // SAFETY: a C-contiguous array made by `empty` in this call and not yet returned: its data
    // is `bytes` long, and this is the only view of it until the call returns.
    unsafe { std::slice::from_raw_parts_mut((*array.as_array_ptr()).data as *mut u8, bytes) }
}

#[pymethods]
impl PyScene {
    /// Moves the instances (`transforms`, (N, 3, 4) or (N, 4, 4) float64) or changes their masks
    /// ((N,) uint8) and picks up its meshes' own updates: refits where built with
    /// allow_update, else rebuilds. Waits for running queries on this scene.
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
        run(py, |_| self.scene.write().unwrap_or_else(|e| e.into_inner()).update(transforms, masks))
    }

    #[getter]
    fn instance_count(&self, py: Python<'_>) -> PyResult<usize> {
        self.with_scene(py, |scene| scene.instance_count)
    }

    #[getter]
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let (stats, options, seconds) =
            self.with_scene(py, |scene| (scene.stats(), scene.options, scene.last_update_seconds()))?;
        let d = stats_dict(py, &stats, &options)?;
        d.set_item("update_seconds", seconds)?;
        Ok(d)
    }

    /// The grid `contains` by winding number (or parity) keeps (built by a query of 32768
    /// points or more on an engine of the host's cores), or None: its cells, the share of them
    /// undecided, its regions (each one exact answer), its build's seconds, its corner (world),
    /// cell size and cells per axis.
    fn inside_grid<'py>(&self, py: Python<'py>, winding: bool) -> PyResult<Option<Bound<'py, PyDict>>> {
        let found = self.with_scene(py, |scene| scene.inside_grid(winding).map(|grid| (grid, scene.center)))?;
        let Some((grid, center)) = found else { return Ok(None) };
        let d = PyDict::new(py);
        d.set_item("cells", grid.cell_count())?;
        d.set_item("undecided", grid.undecided)?;
        d.set_item("near_caps", grid.near_caps)?;
        d.set_item("regions", grid.regions)?;
        d.set_item("build_seconds", grid.build_seconds)?;
        let (corner, inverse_cell, dims, _) = grid.marks_layout();
        d.set_item("corner", (corner + center).to_array())?;
        d.set_item("cell", 1.0 / inverse_cell)?;
        d.set_item("dims", dims)?;
        Ok(Some(d))
    }

    /// Traces rays; returns {field name: array} for the fields asked for.
    /// `query` is "closest" or "occluded"; `precision` one of the tiers of `Precision`;
    /// `contacts` (exact tier): closed triangles (see `Request::contacts`).
    #[pyo3(signature = (origins, directions, tmin, tmax, query, fields, precision="fast", cull=None, mask=None, contacts=false, progress=None, opacity_threshold=0.5, sensor=None, out=None))]
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
        contacts: bool,
        progress: Option<Py<PyAny>>,
        opacity_threshold: f32,
        sensor: Option<&Bound<'py, PyDict>>,
        out: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let request = request(Query::parse(query)?, precision, cull, contacts, opacity_threshold)?;
        let wide = request.precision.is_f64();
        let batch = RayArrays::extract(origins, directions, tmin, tmax, mask, sensor)?;
        let rays = batch.rays()?;
        let n = rays.len();
        // The caller's arrays (`out=`), borrowed after the rays so that overlaps are refused.
        let mut given: Vec<(String, Target, OutArray<'py>, Bound<'py, PyAny>)> = Vec::new();
        for name in &fields {
            if let Some(array) = out.map(|out| out.get_item(name)).transpose()?.flatten() {
                let (field, borrowed) = OutArray::borrow(name, &array, n, wide)?;
                given.push((name.clone(), field, borrowed, array));
            }
        }
        let missing: Vec<String> = fields.iter().filter(|f| !given.iter().any(|g| &g.0 == *f)).cloned().collect();
        check_fits(&self.tracer, request, &missing, n)?;
        let arrays = allocate(py, &missing, n, wide)?;
        let mut sink = HitSink::default();
        for (_, (target, array)) in &arrays {
            target.attach(&mut sink, bytes_of(array));
        }
        for (_, target, borrowed, _) in &mut given {
            target.attach(&mut sink, borrowed.bytes()?);
        }
        self.query(py, progress, |scene, interrupt| self.tracer.trace(scene, &rays, request, &mut sink, interrupt))?;
        let result = PyDict::new(py);
        for (name, (_, array)) in arrays {
            result.set_item(name, array)?;
        }
        for (name, _, _, array) in given {
            result.set_item(name, array)?;
        }
        Ok(result)
    }

    /// Whether CUDA rays of `query` ("closest", "occluded", "count", "transmittance", "all")
    /// in `precision` are traced on the GPU where they lie (`trace_cuda`, `trace_cuda_all`: all
    /// hits of the `fields` given, which the GPU writes), for what this scene holds; else they go
    /// through the host.
    #[pyo3(signature = (query, precision="fast", fields=Vec::new()))]
    fn stays_on_gpu(&self, py: Python<'_>, query: &str, precision: &str, fields: Vec<String>) -> PyResult<bool> {
        let request = request(Query::parse(query)?, precision, None, false, 0.5)?;
        if request.query == Query::All {
            let Ok(fields) = cuda_all_fields(&fields) else { return Ok(false) };
            // The scene's lock is taken without the GIL (a writer may hold it while it waits).
            let scene = &self.scene;
            let refusal = py.detach(|| {
                cuda_all_hits_refusal(&scene.read().unwrap_or_else(|e| e.into_inner()), request, &fields).is_some()
            });
            return Ok(!refusal);
        }
        let spheres = py.detach(|| spheres_on_host(&self.scene.read().unwrap_or_else(|e| e.into_inner()), request));
        Ok(device_rays_refusal(request).is_none() && !spheres)
    }

    /// Traces rays that live in CUDA memory (DLPack arrays on this device's GPU) in `precision`
    /// ("fast" or "exact"); returns {field name: vkray.CudaArray} for the fields
    /// asked for, in CUDA memory. `query` is "closest", "occluded" or "count"; origins and
    /// directions of shape S + (3,) (one of them may be a single row); tmin and tmax numbers or
    /// CUDA arrays of shape S.
    #[pyo3(signature = (origins, directions, tmin, tmax, query, fields, cull=None, mask=255, opacity_threshold=0.5, precision="fast"))]
    #[allow(clippy::too_many_arguments)]
    fn trace_cuda<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        query: &str,
        fields: Vec<String>,
        cull: Option<&str>,
        mask: u8,
        opacity_threshold: f32,
        precision: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        let request = request(Query::parse(query)?, precision, cull, false, opacity_threshold)?;
        let wanted = cuda_fields(&fields)?;
        // Counts and occlusion write prim_id alone, transmittance t alone: no other array may
        // come back unwritten.
        let only = match request.query {
            Query::Count | Query::Occluded => Some(Field::Prim),
            Query::Transmit => Some(Field::T),
            _ => None,
        };
        if let Some(field) = only.filter(|field| wanted.iter().any(|w| w != field)) {
            return Err(PyValueError::new_err(format!("a {query} query of CUDA rays answers {} alone", field.name())));
        }
        let tracer = &self.tracer;
        let (Some(path), Some(cuda)) = cuda_of(tracer)? else {
            return Err(dlpack::unreadable(tracer.device_name(), [("origins", origins), ("directions", directions)]));
        };
        let mut lease = py.detach(|| path.cuda_lease())?; // may free idle leases, which wait
        let result = (|| -> PyResult<Bound<'py, PyDict>> {
            let borrowed =
                cuda_batch::borrow_rays(&cuda, lease.stream_handle(), origins, directions, (tmin, tmax), mask)?;
            let hits = if borrowed.rays.count == 0 {
                None
            } else {
                Some(self.query(py, None, |scene, interrupt| {
                    path.trace_cuda_rays(scene, &mut lease, &borrowed.rays, request, &wanted, interrupt)
                })?)
            };
            cuda_batch::hits_dict(py, hits, &borrowed.leading)
        })();
        py.detach(|| path.give_back_lease(lease)); // may wait for its stream
        result
    }

    /// Every hit of rays that live in CUDA memory (DLPack arrays on this device's GPU), in
    /// `precision` ("fast" or "exact"), left in CUDA memory: (the rays' shape S, {"offsets":
    /// int64 (N + 1), "ray_index": int64 (H), field: vkray.CudaArray of (H,) (+ components)} for
    /// the `fields` asked among t, uv, prim_id, instance_id and geometry_id), or None where the
    /// query must go through the host (a ray's list the GPU cannot settle: more than 32 hits, or
    /// a triangle reported twice; no rays). Arguments as `trace_cuda`'s; `max_hits` as
    /// `trace_all`'s.
    #[pyo3(signature = (origins, directions, tmin, tmax, fields, cull=None, mask=255, opacity_threshold=0.5, precision="fast", max_hits=None))]
    #[allow(clippy::too_many_arguments)]
    fn trace_cuda_all<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        fields: Vec<String>,
        cull: Option<&str>,
        mask: u8,
        opacity_threshold: f32,
        precision: &str,
        max_hits: Option<usize>,
    ) -> PyResult<Option<(Vec<usize>, Bound<'py, PyDict>)>> {
        let request = request(Query::All, precision, cull, false, opacity_threshold)?;
        if max_hits == Some(0) {
            return Err(PyValueError::new_err("max_hits must be at least 1 (or None: every hit)"));
        }
        let wanted = cuda_all_fields(&fields)?;
        let tracer = &self.tracer;
        let (path, cuda) = cuda_of(tracer)?;
        let (Some(path), Some(cuda), Some(all_hits)) = (path, cuda, cuda_all_hits_of(tracer)) else {
            return Err(dlpack::unreadable(tracer.device_name(), [("origins", origins), ("directions", directions)]));
        };
        let mut lease = py.detach(|| path.cuda_lease())?; // may free idle leases, which wait
        let result = (|| -> PyResult<Option<(Vec<usize>, Bound<'py, PyDict>)>> {
            let borrowed =
                cuda_batch::borrow_rays(&cuda, lease.stream_handle(), origins, directions, (tmin, tmax), mask)?;
            let limit = max_hits.unwrap_or(usize::MAX);
            let outcome = self.query(py, None, |scene, interrupt| {
                all_hits.trace(scene, &mut lease, &borrowed.rays, request, limit, &wanted, interrupt)
            })?;
            match outcome {
                CudaAllHitsOutcome::ThroughHost(_) => Ok(None),
                CudaAllHitsOutcome::Answered(hits) => {
                    let arrays = cuda_batch::all_hits_dict(py, hits, borrowed.rays.count)?;
                    Ok(Some((borrowed.leading.clone(), arrays)))
                }
            }
        })();
        py.detach(|| path.give_back_lease(lease)); // may wait for its stream
        result
    }

    /// A batch of CUDA rays on this device's GPU to be traced in pieces by several devices
    /// (`trace_cuda_piece` of each, then `CudaBatch.finish`): the rays borrowed, the hits of
    /// `fields` allocated here. Arguments as `trace_cuda`'s.
    #[pyo3(signature = (origins, directions, tmin, tmax, fields, mask=255))]
    #[allow(clippy::too_many_arguments)]
    fn cuda_batch(
        &self,
        origins: &Bound<'_, PyAny>,
        directions: &Bound<'_, PyAny>,
        tmin: &Bound<'_, PyAny>,
        tmax: &Bound<'_, PyAny>,
        fields: Vec<String>,
        mask: u8,
    ) -> PyResult<cuda_batch::PyCudaBatch> {
        let (_, Some(cuda)) = cuda_of(&self.tracer)? else {
            return Err(dlpack::unreadable(
                self.tracer.device_name(),
                [("origins", origins), ("directions", directions)],
            ));
        };
        cuda_batch::PyCudaBatch::new(&cuda, origins, directions, (tmin, tmax), &cuda_fields(&fields)?, mask)
    }

    /// Traces rows `start..stop` of `batch` (CUDA rays on this or another GPU) on this device in
    /// the fast tier, writing their hits into the batch's rows. `query` as in `trace_cuda`.
    #[pyo3(signature = (batch, start, stop, query, cull=None, opacity_threshold=0.5))]
    #[allow(clippy::too_many_arguments)]
    fn trace_cuda_piece(
        &self,
        py: Python<'_>,
        batch: &cuda_batch::PyCudaBatch,
        start: usize,
        stop: usize,
        query: &str,
        cull: Option<&str>,
        opacity_threshold: f32,
    ) -> PyResult<()> {
        let request = request(Query::parse(query)?, "fast", cull, false, opacity_threshold)?;
        let tracer = &self.tracer;
        let (Some(path), Some(_)) = cuda_of(tracer)? else {
            return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                "{} does not share memory with CUDA: it cannot trace a piece of CUDA rays",
                tracer.device_name()
            )));
        };
        let mut lease = py.detach(|| path.cuda_lease())?; // may free idle leases, which wait
        let traced = self.query(py, None, |scene, interrupt| {
            path.trace_cuda_piece(scene, &mut lease, batch.batch(), (start, stop), request, interrupt)
        });
        py.detach(|| path.give_back_lease(lease)); // may wait for its stream
        traced
    }

    /// Every hit of every ray: {"offsets": int64 (N+1), field: array (H, ...)}.
    #[pyo3(signature = (origins, directions, tmin, tmax, fields, precision="fast", cull=None, mask=None, max_hits=None, contacts=false, progress=None, opacity_threshold=0.5, sensor=None))]
    #[allow(clippy::too_many_arguments)]
    fn trace_all<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        fields: Vec<String>,
        precision: &str,
        cull: Option<&str>,
        mask: Option<&Bound<'py, PyAny>>,
        max_hits: Option<usize>,
        contacts: bool,
        progress: Option<Py<PyAny>>,
        opacity_threshold: f32,
        sensor: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let request = request(Query::Closest, precision, cull, contacts, opacity_threshold)?;
        if max_hits == Some(0) {
            return Err(PyValueError::new_err("max_hits must be at least 1 (or None: every hit)"));
        }
        let named = fields_named(&fields)?;
        let asked: Vec<AskedColumn> = named.iter().map(|(_, field)| *field).collect();
        let batch = RayArrays::extract(origins, directions, tmin, tmax, mask, sensor)?;
        let rays = batch.rays()?;
        let answer = self.query(py, progress, |scene, interrupt| {
            let limit = max_hits.unwrap_or(usize::MAX);
            self.tracer.all_hit_columns(scene, &rays, request, limit, &asked, interrupt)
        })?;
        let HitColumns { offsets, columns } = answer;
        // No counts and no ray indices: `AllHits` makes them from the offsets at first use
        // (`counts_of_offsets`, `ray_index_of_offsets`), 8 MB a million rays and 8 bytes a hit
        // that a caller of the hits alone does not pay.
        let result = PyDict::new(py);
        result.set_item("offsets", PyArray1::from_vec(py, offsets))?;
        for ((name, _), column) in named.into_iter().zip(columns) {
            result.set_item(name, column_array(py, column)?)?;
        }
        Ok(result)
    }

    /// The number of hits of each ray (int32, N).
    #[pyo3(signature = (origins, directions, tmin, tmax, precision="fast", cull=None, mask=None, progress=None, opacity_threshold=0.5, sensor=None))]
    #[allow(clippy::too_many_arguments)]
    fn count<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        tmin: &Bound<'py, PyAny>,
        tmax: &Bound<'py, PyAny>,
        precision: &str,
        cull: Option<&str>,
        mask: Option<&Bound<'py, PyAny>>,
        progress: Option<Py<PyAny>>,
        opacity_threshold: f32,
        sensor: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyUntypedArray>> {
        let request = request(Query::Closest, precision, cull, false, opacity_threshold)?;
        let batch = RayArrays::extract(origins, directions, tmin, tmax, mask, sensor)?;
        let rays = batch.rays()?;
        let counts = empty(py, &[rays.len()], "int32")?;
        let out: &mut [i32] = bytemuck::cast_slice_mut(bytes_of(&counts));
        self.query(py, progress, |scene, interrupt| self.tracer.count(scene, &rays, request, out, interrupt))?;
        Ok(counts)
    }

    /// The variant a query runs on this device: {"stages", "ray_query_branches", "ray_flags",
    /// "pipeline_flags", "outputs", "specialization"}; None for the host's reference tier.
    #[pyo3(signature = (kind, fields, precision="fast", cull=None, opacity_threshold=0.5, sensor=false))]
    #[allow(clippy::too_many_arguments)]
    fn explain<'py>(
        &self,
        py: Python<'py>,
        kind: &str,
        fields: Vec<String>,
        precision: &str,
        cull: Option<&str>,
        opacity_threshold: f32,
        sensor: bool,
    ) -> PyResult<Option<Bound<'py, PyDict>>> {
        let query = Query::parse(kind)?;
        let request = request(query, precision, cull, false, opacity_threshold)?;
        let mut outputs = 0;
        for (_, field) in fields_named(&fields)? {
            outputs |= match field {
                Some(field) => field.bit(),
                // Positions come from the hit triangle and its barycentrics, on the host.
                None => Field::Prim.bit() | Field::Instance.bit() | Field::Geometry.bit() | Field::Uv.bit(),
            };
        }
        if let Some(cpu) = self.tracer.engine().as_any().downcast_ref::<CpuEngine>() {
            let (stages, effects) = self.with_scene(py, |scene| cpu.explain(scene, request))?;
            let d = PyDict::new(py);
            d.set_item("stages", stages)?;
            d.set_item("filter", effects)?;
            return Ok(Some(d));
        }
        let Some(vulkan) = self.tracer.engine().as_any().downcast_ref::<VulkanEngine>() else { return Ok(None) };
        let explained = self.with_scene(py, |scene| vulkan.explain(scene, request, outputs, sensor))?;
        let Some(e) = explained else { return Ok(None) };
        let d = PyDict::new(py);
        d.set_item("stages", e.stages)?;
        d.set_item("ray_query_branches", e.branches)?;
        d.set_item("ray_flags", e.ray_flags)?;
        d.set_item("pipeline_flags", e.pipeline_skips)?;
        let written: Vec<&str> = FIELDS.iter().filter(|f| e.key.outputs & f.bit() != 0).map(|f| f.name()).collect();
        d.set_item("outputs", written)?;
        let constants = PyDict::new(py);
        constants.set_item("OUTPUTS", e.key.outputs)?;
        constants.set_item("RAY_FLAGS", e.key.ray_flags)?;
        constants.set_item("QUERY", e.key.query)?;
        constants.set_item("CLOSED_EDGES", e.key.closed_edges as u32)?;
        constants.set_item("RAY_SOURCE", e.key.ray_source)?;
        constants.set_item("OPACITY_THRESHOLD", f32::from_bits(e.key.threshold_bits))?;
        d.set_item("specialization", constants)?;
        Ok(Some(d))
    }

    /// The surface point nearest to each point ((N, 3)) within max_distance: {field: array}, with
    /// "t" the distance.
    #[pyo3(signature = (points, fields, max_distance=f64::INFINITY, precision="reference", progress=None))]
    fn closest_points<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        fields: Vec<String>,
        max_distance: f64,
        precision: &str,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let precision = Precision::parse(precision)?;
        let points = Vec3Array::extract("points", points)?;
        let points = points.view()?;
        let n = points.rows();
        let arrays = allocate(py, &fields, n, true)?;
        let mut sink = HitSink::default();
        for (_, (target, array)) in &arrays {
            target.attach(&mut sink, bytes_of(array));
        }
        self.query(py, progress, |scene, interrupt| {
            self.tracer.closest_points(scene, points, max_distance, precision, &mut sink, interrupt)
        })?;
        let result = PyDict::new(py);
        for (name, (_, array)) in arrays {
            result.set_item(name, array)?;
        }
        Ok(result)
    }

    /// The distance from each point ((N, 3)) to the nearest surface, negative inside (f64).
    #[pyo3(signature = (points, max_distance, precision, contains_precision, winding, progress=None))]
    #[allow(clippy::too_many_arguments)]
    fn signed_distance<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        max_distance: f64,
        precision: &str,
        contains_precision: &str,
        winding: bool,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<Bound<'py, PyUntypedArray>> {
        let (precision, contains_precision) = (Precision::parse(precision)?, Precision::parse(contains_precision)?);
        let points = Vec3Array::extract("points", points)?;
        let points = points.view()?;
        let signed = empty(py, &[points.rows()], "float64")?;
        let out: &mut [f64] = bytemuck::cast_slice_mut(bytes_of(&signed));
        self.query(py, progress, |scene, interrupt| {
            let query = SignedDistance { max_distance, precision, contains_precision, winding };
            self.tracer.signed_distance(scene, points, query, out, interrupt)
        })?;
        Ok(signed)
    }

    /// Whether each point ((N, 3)) is inside any instance: by parity or by winding number.
    #[pyo3(signature = (points, precision="exact", winding=false, progress=None))]
    fn contains<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        precision: &str,
        winding: bool,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<Bound<'py, PyUntypedArray>> {
        let precision = Precision::parse(precision)?;
        let points = Vec3Array::extract("points", points)?;
        let points = points.view()?;
        let inside = empty(py, &[points.rows()], "bool")?;
        let out = bytes_of(&inside);
        self.query(py, progress, |scene, interrupt| {
            self.tracer.contains(scene, points, precision, winding, out, interrupt)
        })?;
        Ok(inside)
    }

    /// `contains` at the exact tier of CUDA points (a DLPack array of shape S + (3,) on this
    /// device's GPU, float32 or float64) by parity or by winding number, answered in CUDA memory:
    /// a bool vkray.CudaArray of shape S; or None where the GPU's path through the scene's inside
    /// grid does not answer (no grid kept yet, several instances, no points, no CUDA): the caller
    /// then goes through the host. The caller checked the method against the meshes.
    #[pyo3(signature = (points, winding=false))]
    fn contains_cuda<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        winding: bool,
    ) -> PyResult<Option<Py<dlpack::PyCudaArray>>> {
        let tracer = &self.tracer;
        let (Some(path), Some(cuda)) = cuda_of(tracer)? else { return Ok(None) };
        let Some(inside_path) = inside_points_of(tracer) else { return Ok(None) };
        // Before the grid is kept (the host's path builds it) nothing is borrowed.
        if self.scene.read().unwrap_or_else(|e| e.into_inner()).inside_grid(winding).is_none() {
            return Ok(None);
        }
        let mut lease = py.detach(|| path.cuda_lease())?; // may free idle leases, which wait
        let result = (|| -> PyResult<Option<Py<dlpack::PyCudaArray>>> {
            // This GPU's context current while the producer exports (as for CUDA rays).
            let entered = cuda.enter()?;
            let mut order = dlpack::ExportOrder::new(lease.stream_handle());
            let borrowed = dlpack::borrow(points, "points", 3, &mut order, cuda.ordinal);
            drop(entered);
            // Points this path cannot read in place (leading axes that do not flatten, a dtype
            // that is not float: the host's path copies or refuses them) or one row repeated
            // (an expanded tensor: every point's own row is the host path's), and no points.
            let Ok(borrowed) = borrowed else { return Ok(None) };
            let rows: usize = borrowed.leading.iter().product();
            if rows == 0 || borrowed.array.rows != rows {
                return Ok(None);
            }
            let answered = self.query(py, None, |scene, interrupt| {
                inside_path.run_cuda(scene, path, &mut lease, &borrowed.array, winding, interrupt)
            })?;
            let Some(answer) = answered else { return Ok(None) };
            let dtype = dlpack::dtype_named("bool").expect("bool is a DLPack type");
            let array = dlpack::PyCudaArray::of_type(answer.inside, answer.ready, borrowed.leading.clone(), dtype);
            Ok(Some(Py::new(py, array)?))
        })();
        py.detach(|| path.give_back_lease(lease)); // may wait for its stream
        result
    }
}

/// The hit fields named, each one the GPU-resident path computes.
fn cuda_fields(names: &[String]) -> PyResult<Vec<Field>> {
    // A query of CUDA rays with nothing to write would wait for hits that never come.
    if names.is_empty() {
        return Err(PyValueError::new_err("outputs must name at least one field for CUDA rays"));
    }
    fields_named(names)?
        .into_iter()
        .map(|(name, field)| {
            field.ok_or_else(|| PyValueError::new_err(format!("{name} is not computed on the GPU for CUDA rays")))
        })
        .collect()
}

/// The fields of all hits of CUDA rays (none: the offsets and the hits' rays alone).
fn cuda_all_fields(names: &[String]) -> PyResult<Vec<Field>> {
    if names.is_empty() {
        return Ok(Vec::new());
    }
    cuda_fields(names)
}

/// A query's request from the option strings it was called with.
fn request(
    query: Query,
    precision: &str,
    cull: Option<&str>,
    contacts: bool,
    opacity_threshold: f32,
) -> PyResult<Request> {
    let request = Request {
        contacts,
        opacity_threshold,
        ..Request::new(query, Precision::parse(precision)?, Cull::parse(cull)?)
    };
    request.check()?;
    Ok(request)
}

/// One column of all hits as a numpy array (`(hits, k)` for fields of k numbers), without a copy.
fn column_array(py: Python<'_>, column: HitColumn) -> PyResult<Bound<'_, PyAny>> {
    fn shaped<'py, T: numpy::Element>(py: Python<'py>, v: Vec<T>, k: usize) -> PyResult<Bound<'py, PyAny>> {
        let rows = v.len() / k;
        let array = PyArray1::from_vec(py, v);
        Ok(if k == 1 { array.into_any() } else { array.reshape([rows, k])?.into_any() })
    }
    match column {
        HitColumn::F64(v, k) => shaped(py, v, k),
        HitColumn::F32(v, k) => shaped(py, v, k),
        HitColumn::I32(v) => shaped(py, v, 1),
    }
}

/// The fields named in `names` (None for `position`).
fn fields_named(names: &[String]) -> PyResult<Vec<(String, Option<Field>)>> {
    names
        .iter()
        .map(|name| match FIELDS.iter().copied().find(|f| f.name() == name) {
            Some(field) => Ok((name.clone(), Some(field))),
            None if name == "position" => Ok((name.clone(), None)),
            None => Err(PyValueError::new_err(format!("unknown hit field {name:?}"))),
        })
        .collect()
}

/// Refuses a query whose outputs and working memory exceed the host memory available, before
/// anything is allocated (rather than growing until the system's OOM killer ends the process).
fn check_fits(tracer: &DeviceTracer, request: Request, fields: &[String], n: usize) -> PyResult<()> {
    let wide = request.precision.is_f64();
    let per_ray: usize = fields
        .iter()
        .map(|name| match FIELDS.iter().find(|f| f.name() == name) {
            Some(field) => field.bytes_per_ray(wide),
            // A byte a ray, and a temporary prim_id where the host decides the hits.
            None if name == "hit" => {
                1 + if matches!(request.precision, Precision::Fast | Precision::Exact) { 0 } else { 4 }
            }
            None => position_bytes_per_ray(wide),
        })
        .sum();
    let needed = (n as u128) * (per_ray as u128) + tracer.working_bytes(request, n) as u128;
    match short_of_host_memory(needed) {
        Some(available) => Err(PyMemoryError::new_err(format!(
            "a query of {n} rays needs about {:.2} GB of host memory (its outputs and working buffers), \
             more than the {:.2} GB available: trace fewer rays at a time, or ask fewer outputs",
            needed as f64 / 1e9,
            available as f64 / 1e9
        ))),
        _ => Ok(()),
    }
}

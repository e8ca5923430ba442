//! CUDA rays as the Python layer hands them over: borrowed through DLPack as `CudaRays`, and
//! `vkray._core.CudaBatch`, one batch of them split over several devices (a `DeviceGroup`): each
//! device traces its rows (`Scene.trace_cuda_piece`), copying them from the GPU that holds them
//! and its hits back there, and `finish` hands the hits over as one set of `vkray.CudaArray`s.

use std::sync::Arc;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyCapsule, PyDict, PyTuple};

use super::dlpack::{self, Borrowed, PyCudaArray};
use crate::gpu::cuda::{Cuda, Stream};
use crate::trace::vulkan::cuda_all_hits::CudaAllHits;
use crate::trace::vulkan::cuda_rays::{CudaBatch, CudaHits, CudaRays};
use crate::trace::Field;

/// The caller's CUDA rays, borrowed (their capsules held) for as long as this lives.
pub(super) struct BorrowedRays<'py> {
    pub rays: CudaRays,
    /// The rays' shape S.
    pub leading: Vec<usize>,
    held: Vec<Borrowed<'py>>,
}

/// Borrows the rays' CUDA arrays on `cuda`'s GPU, their producers' writes ordered before
/// `stream` (a raw CUDA stream handle); tmin and tmax are numbers or CUDA arrays of shape S.
pub(super) fn borrow_rays<'py>(
    cuda: &Cuda,
    stream: usize,
    origins: &Bound<'py, PyAny>,
    directions: &Bound<'py, PyAny>,
    (tmin, tmax): (&Bound<'py, PyAny>, &Bound<'py, PyAny>),
    mask: u8,
) -> PyResult<BorrowedRays<'py>> {
    // This GPU's context current while the producers export: torch refuses to export a tensor
    // of cuda:N for a stream unless cuda:N is its current device.
    let entered = cuda.enter()?;
    let mut order = dlpack::ExportOrder::new(stream);
    let o = dlpack::borrow(origins, "origins", 3, &mut order, cuda.ordinal)?;
    let d = dlpack::borrow(directions, "directions", 3, &mut order, cuda.ordinal)?;
    let mut bounds = Vec::new();
    let lo = dlpack::bound(tmin, "tmin", &mut order, cuda.ordinal, &mut bounds)?;
    let hi = dlpack::bound(tmax, "tmax", &mut order, cuda.ordinal, &mut bounds)?;
    drop(entered);
    let leading = broadcast_rays(&o, &d, &bounds)?;
    let count = leading.iter().product();
    let rays = CudaRays { count, origins: o.array, directions: d.array, tmin: lo, tmax: hi, mask };
    let mut held = vec![o, d];
    held.extend(bounds);
    Ok(BorrowedRays { rays, leading, held })
}

/// The rays' shape S from CUDA origins and directions of shapes S + (3,) (one may be a single
/// row) and bounds of shape S.
fn broadcast_rays(o: &Borrowed, d: &Borrowed, bounds: &[Borrowed]) -> PyResult<Vec<usize>> {
    let rows = |shape: &[usize]| shape.iter().product::<usize>();
    // One row by its shape (an expanded array of shape S + (3,) has S's rows, read as one).
    let single = |b: &Borrowed| rows(&b.leading) == 1;
    let leading = if single(o) && !single(d) { d.leading.clone() } else { o.leading.clone() };
    if !single(o) && !single(d) && o.leading != d.leading {
        return Err(PyValueError::new_err(format!(
            "origins and directions must have the same shape S + (3,) (or one a single row), got {:?} and {:?}",
            o.leading, d.leading
        )));
    }
    for bound in bounds {
        if bound.leading != leading && bound.array.rows != rows(&leading) {
            return Err(PyValueError::new_err(format!(
                "tmin and tmax arrays must have the rays' shape {leading:?}, got {:?}",
                bound.leading
            )));
        }
    }
    Ok(leading)
}

/// {field name: vkray.CudaArray of shape `leading` (+ components)}; empty without hits (no rays).
pub(super) fn hits_dict<'py>(
    py: Python<'py>,
    hits: Option<CudaHits>,
    leading: &[usize],
) -> PyResult<Bound<'py, PyDict>> {
    let result = PyDict::new(py);
    if let Some(hits) = hits {
        for (field, allocation) in hits.fields {
            let array = PyCudaArray::new((field, hits.wide), allocation, hits.ready.clone(), leading);
            result.set_item(field.name(), Py::new(py, array)?)?;
        }
    }
    Ok(result)
}

/// All hits of `rays` CUDA rays as {"offsets": int64 (rays + 1), "ray_index": int64 (H), field
/// name: vkray.CudaArray of shape (H,) (+ components)}.
pub(super) fn all_hits_dict<'py>(py: Python<'py>, hits: CudaAllHits, rays: usize) -> PyResult<Bound<'py, PyDict>> {
    let result = PyDict::new(py);
    let CudaAllHits { offsets, ray_index, fields, hits, ready, wide } = hits;
    result.set_item("offsets", Py::new(py, PyCudaArray::int64(offsets, ready.clone(), vec![rays + 1]))?)?;
    result.set_item("ray_index", Py::new(py, PyCudaArray::int64(ray_index, ready.clone(), vec![hits]))?)?;
    for (field, allocation) in fields {
        let array = PyCudaArray::new((field, wide), allocation, ready.clone(), &[hits]);
        result.set_item(field.name(), Py::new(py, array)?)?;
    }
    Ok(result)
}

/// One batch of CUDA rays traced in pieces by several devices (see the module's comment). Made
/// by `Scene.cuda_batch` on the device whose GPU holds the rays.
#[pyclass(name = "CudaBatch", module = "vkray._core", frozen)]
pub(super) struct PyCudaBatch {
    batch: Arc<CudaBatch>,
    /// The rays' shape S.
    leading: Vec<usize>,
    /// The caller's arrays' capsules: their memory stays borrowed until the batch is gone.
    _capsules: Vec<Py<PyCapsule>>,
}

impl PyCudaBatch {
    pub(super) fn new(
        cuda: &Arc<Cuda>,
        origins: &Bound<'_, PyAny>,
        directions: &Bound<'_, PyAny>,
        bounds: (&Bound<'_, PyAny>, &Bound<'_, PyAny>),
        fields: &[Field],
        mask: u8,
    ) -> PyResult<PyCudaBatch> {
        let stream = Stream::new(cuda)?;
        let borrowed = borrow_rays(cuda, stream.raw as usize, origins, directions, bounds, mask)?;
        let batch = CudaBatch::new(stream, borrowed.rays, fields)?;
        let capsules = borrowed.held.into_iter().map(Borrowed::into_capsule).collect();
        Ok(PyCudaBatch { batch: Arc::new(batch), leading: borrowed.leading, _capsules: capsules })
    }

    pub(super) fn batch(&self) -> &CudaBatch {
        &self.batch
    }
}

#[pymethods]
impl PyCudaBatch {
    /// Rays in the batch.
    fn __len__(&self) -> usize {
        self.batch.rays.count
    }

    /// The rays' shape S.
    #[getter]
    fn shape<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        PyTuple::new(py, &self.leading)
    }

    /// The hits of every piece traced: {field name: vkray.CudaArray} on the batch's GPU, read by
    /// streams ordered after every piece's copies. Once only.
    fn finish<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let batch = self.batch.clone();
        let hits = py.detach(move || batch.finish())?;
        hits_dict(py, Some(hits), &self.leading)
    }
}

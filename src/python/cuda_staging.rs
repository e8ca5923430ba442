//! CUDA arrays through the host, for the queries and tiers that have no GPU-resident path (all
//! hits, the exact and refined tiers, the point queries): the caller's CUDA arrays are copied
//! into host memory on vkray's CUDA stream (ordered after the producer's writes, as DLPack
//! promises), the query runs as for numpy, and each answer is copied into a fresh CUDA
//! allocation handed back as a `vkray.CudaArray`. Two copies over the bus, one each way.

use std::sync::Arc;

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

use super::dlpack::{self, CudaTensor, PyCudaArray};
use crate::gpu::cuda::{is_pinned, Cuda, CudaAllocation, HostBlock, Stream};

/// A CUDA array's elements read into host memory: the bytes its strides span, with the numpy
/// dtype, shape and byte strides that view them.
pub(super) struct HostCopy<'py> {
    pub bytes: Bound<'py, PyArray1<u8>>,
    pub dtype: &'static str,
    pub shape: Vec<usize>,
    pub strides: Vec<usize>,
}

/// `value`, a CUDA array on `cuda`'s GPU (`name` names it in errors), read into host memory.
pub(super) fn read_to_host<'py>(cuda: &Arc<Cuda>, value: &Bound<'py, PyAny>, name: &str) -> PyResult<HostCopy<'py>> {
    let py = value.py();
    let stream = Stream::new(cuda)?;
    // The GPU's context current while the producer exports (torch's rule, as for rays).
    let entered = cuda.enter()?;
    let tensor = dlpack::export(value, name, &mut dlpack::ExportOrder::new(stream.raw as usize), cuda.ordinal)?;
    drop(entered);
    let CudaTensor { data, dtype, shape, strides, capsule } = tensor;
    let Some(dtype_name) = dlpack::dtype_name(dtype) else {
        return Err(PyTypeError::new_err(format!(
            "{name} has DLPack elements of type code {} with {} bits, which vkray does not read",
            dtype.code, dtype.bits
        )));
    };
    if shape.iter().zip(&strides).any(|(&n, &s)| n > 1 && s < 0) {
        return Err(PyValueError::new_err(format!("{name} has negative strides: pass a contiguous array")));
    }
    let element = dlpack::element_bytes(dtype);
    let plan = CopyPlan::of(&shape, &strides, element);
    let contiguous = plan.pitch.is_none_or(|pitch| pitch == plan.width || plan.rows <= 1);
    let pinned = if contiguous && plan.host_bytes() >= THROUGH_PINNED_BYTES {
        py.detach(|| -> crate::Result<Option<HostBlock>> {
            let _current = cuda.enter()?;
            let Some(block) = HostBlock::take(cuda, plan.host_bytes()) else { return Ok(None) };
            // SAFETY: `data` is the producer's CUDA memory, alive while `capsule` is (held
            // through the synchronize); the block holds the plan's bytes and is ours alone.
            if let Err(error) = unsafe { stream.copy_to_host(block.as_ptr(), data, plan.host_bytes()) }
                .and_then(|()| stream.synchronize())
            {
                std::mem::forget(block); // a copy may still write into it: kept from reuse
                return Err(error);
            }
            Ok(Some(block))
        })?
    } else {
        None
    };
    let bytes = if let Some(block) = pinned {
        lend(py, block)?
    } else {
        let bytes = PyArray1::<u8>::zeros(py, plan.host_bytes(), false);
        let host = bytes.data() as usize;
        py.detach(|| -> crate::Result<()> {
            let _current = cuda.enter()?;
            // SAFETY: `data` is the producer's CUDA memory, alive while `capsule` is (held through
            // the synchronize); the plan reads only within its strides' span; `host` is a fresh
            // array of the plan's bytes that no other code touches until this returns.
            unsafe { plan.copy(&stream, host as *mut u8, data)? };
            stream.synchronize()
        })?;
        bytes
    };
    drop(capsule);
    Ok(HostCopy { bytes, dtype: dtype_name, shape, strides: plan.host_strides })
}

/// Copies of this many bytes or more go through pinned memory (a `HostBlock` lent as the array
/// read, `Stream::write_through_pinned` for answers), at the bus's speed rather than through the
/// driver's pageable staging and fresh pages: 1M float32 rays' two arrays took about 3.4 ms
/// through pageable memory on an H200.
const THROUGH_PINNED_BYTES: usize = 1 << 20;

thread_local! {
    /// The GPU whose page-locked blocks this thread's query answers are made in, while a query of
    /// CUDA arrays runs through the host (`PyDevice.pinned_answers`): its answers then cross the
    /// bus by DMA from where they were written, with no copy into staging on the host.
    static PINNED_ANSWERS: std::cell::RefCell<Option<Arc<Cuda>>> = const { std::cell::RefCell::new(None) };
}

/// Makes this thread's answers in `cuda`'s page-locked blocks (None: in numpy's memory again).
pub(super) fn set_pinned_answers(cuda: Option<Arc<Cuda>>) {
    PINNED_ANSWERS.with(|held| *held.borrow_mut() = cuda);
}

/// An uninitialized array of `shape` and `dtype` in a page-locked block, where this thread's
/// answers are made there (`set_pinned_answers`) and the array is large enough to gain from it
/// (`THROUGH_PINNED_BYTES`); else None (numpy's `empty` then).
pub(super) fn pinned_empty<'py>(
    py: Python<'py>,
    shape: &[usize],
    dtype: &str,
) -> PyResult<Option<Bound<'py, numpy::PyUntypedArray>>> {
    let Some(cuda) = PINNED_ANSWERS.with(|held| held.borrow().clone()) else { return Ok(None) };
    let numpy = py.import("numpy")?;
    let itemsize: usize = numpy.getattr("dtype")?.call1((dtype,))?.getattr("itemsize")?.extract()?;
    let bytes = shape.iter().product::<usize>() * itemsize;
    if bytes < THROUGH_PINNED_BYTES {
        return Ok(None);
    }
    let block = py.detach(|| -> crate::Result<Option<HostBlock>> {
        let _current = cuda.enter()?;
        Ok(HostBlock::take(&cuda, bytes))
    })?;
    let Some(block) = block else { return Ok(None) };
    let array = lend(py, block)?.call_method1("view", (dtype,))?.call_method1("reshape", (shape.to_vec(),))?;
    Ok(Some(array.downcast_into::<numpy::PyUntypedArray>()?))
}

/// The Python object that owns a `HostBlock` lent as a numpy array's memory (the array's base):
/// the block goes back to the idle ones when the array is gone.
#[pyclass(name = "HostBlock", module = "vkray._core", frozen)]
struct LentBlock {
    block: HostBlock,
}

/// A numpy array of the block's bytes, which keeps the block until it is gone.
fn lend(py: Python<'_>, block: HostBlock) -> PyResult<Bound<'_, PyArray1<u8>>> {
    let owner = Bound::new(py, LentBlock { block })?;
    let (pointer, bytes) = (owner.get().block.as_ptr(), owner.get().block.bytes);
    // SAFETY: the block's `bytes` bytes are valid host memory owned by `owner`, which the array
    // holds as its base: they outlive the view, and nothing else writes them.
    let view = unsafe { numpy::ndarray::ArrayView1::from_shape_ptr(bytes, pointer as *const u8) };
    // SAFETY: as above: `owner` is the array's base and keeps the memory unmoved.
    Ok(unsafe { PyArray1::borrow_from_array(&view, owner.into_any()) })
}

/// How a CUDA array's elements reach the host: its rows packed (the last axis contiguous and
/// the others one stride: slices of wider arrays copy only their own rows), or else every byte
/// its strides span, viewed there with the same strides.
struct CopyPlan {
    /// Rows of `width` bytes, `pitch` bytes apart on the GPU; or the span (`pitch` None).
    rows: usize,
    width: usize,
    pitch: Option<usize>,
    /// Byte strides of the copy on the host.
    host_strides: Vec<usize>,
}

impl CopyPlan {
    fn of(shape: &[usize], strides: &[i64], element: usize) -> CopyPlan {
        let in_bytes = |s: &[i64]| s.iter().map(|&s| s.max(0) as usize * element).collect::<Vec<_>>();
        if shape.contains(&0) {
            return CopyPlan { rows: 0, width: 0, pitch: None, host_strides: in_bytes(strides) };
        }
        if let Some((&columns, leading)) = shape.split_last() {
            let inner = strides[shape.len() - 1];
            let packed_row = columns == 1 || inner == 1;
            // Rows apart (or all one row): not overlapping windows of one another.
            let row_stride = dlpack::collapsed_stride(leading, &strides[..leading.len()])
                .filter(|&r| r == 0 || r as usize >= columns);
            if let (true, Some(row_stride)) = (packed_row, row_stride) {
                let width = columns * element;
                let rows = if row_stride == 0 { 1 } else { leading.iter().product() };
                // Every row the same (an expanded array): one row, viewed with strides of 0.
                let mut host_strides: Vec<usize> = if row_stride == 0 {
                    vec![0; leading.len()]
                } else {
                    let mut outer = Vec::with_capacity(leading.len());
                    let mut step = width;
                    for &n in leading.iter().rev() {
                        outer.push(step);
                        step *= n;
                    }
                    outer.reverse();
                    outer
                };
                host_strides.push(element);
                let pitch = row_stride as usize * element;
                return CopyPlan { rows, width, pitch: Some(pitch), host_strides };
            }
        }
        let span =
            element + shape.iter().zip(strides).map(|(&n, &s)| (n - 1) * s.max(0) as usize * element).sum::<usize>();
        CopyPlan { rows: 1, width: span, pitch: None, host_strides: in_bytes(strides) }
    }

    fn host_bytes(&self) -> usize {
        self.rows * self.width
    }

    /// # Safety
    /// `src` must be the array's CUDA memory (of the stream's context, which must be current)
    /// and `dst` writable host memory of `host_bytes()`, both valid until the stream has run.
    unsafe fn copy(&self, stream: &Stream, dst: *mut u8, src: u64) -> crate::Result<()> {
        match self.pitch {
            // SAFETY: the caller's contract; the rows lie within the array's strides.
            Some(pitch) => unsafe { stream.copy_rows_to_host(dst, src, pitch, self.width, self.rows) },
            // SAFETY: as above; the span is the array's.
            None => unsafe { stream.copy_to_host(dst, src, self.host_bytes()) },
        }
    }
}

/// A contiguous host array's `bytes` (numpy dtype `dtype`, shape `shape`) copied into a new
/// CUDA allocation on `cuda`'s GPU, written before the returned array's readers start.
pub(super) fn write_from_host(
    cuda: &Arc<Cuda>,
    bytes: PyReadonlyArray1<'_, u8>,
    dtype: &str,
    shape: Vec<usize>,
) -> PyResult<PyCudaArray> {
    let Some(dl_type) = dlpack::dtype_named(dtype) else {
        return Err(PyTypeError::new_err(format!("vkray.CudaArray does not hold {dtype} elements")));
    };
    let elements: usize = shape.iter().product();
    if elements * dlpack::element_bytes(dl_type) != bytes.len() {
        return Err(PyValueError::new_err(format!(
            "{} bytes do not make an array of shape {shape:?} of {dtype}",
            bytes.len()
        )));
    }
    let host = bytes.as_slice()?;
    let stream = Stream::new(cuda)?;
    let (allocation, ready) = bytes.py().detach(|| -> crate::Result<_> {
        let _current = cuda.enter()?;
        let allocation = CudaAllocation::new(&stream, host.len())?;
        if is_pinned(host.as_ptr()) {
            // An answer written into a lent block (`pinned_empty`): straight across the bus.
            // SAFETY: as below.
            unsafe { stream.copy_from_host(allocation.pointer, host.as_ptr(), host.len())? };
        } else if host.len() >= THROUGH_PINNED_BYTES {
            // SAFETY: the allocation is fresh device memory of this context with room for the
            // bytes; it synchronizes the stream before returning.
            unsafe { stream.write_through_pinned(allocation.pointer, host)? };
        } else {
            // SAFETY: as above; `host` is borrowed until the synchronize, after which the copy
            // has run.
            unsafe { stream.copy_from_host(allocation.pointer, host.as_ptr(), host.len())? };
        }
        let ready = stream.record()?;
        stream.synchronize()?;
        Ok((allocation, Arc::new(ready)))
    })?;
    Ok(PyCudaArray::of_type(allocation, ready, shape, dl_type))
}

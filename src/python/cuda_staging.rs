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
use crate::gpu::cuda::{Cuda, CudaAllocation, Stream};

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
    let tensor = dlpack::export(value, name, stream.raw as usize, cuda.ordinal)?;
    drop(entered);
    let CudaTensor { data, dtype, shape, strides, capsule } = tensor;
    let Some(dtype_name) = dlpack::dtype_name(dtype) else {
        return Err(PyTypeError::new_err(format!("{name} has a DLPack element type vkray does not read ({dtype:?})")));
    };
    if strides.iter().any(|&s| s < 0) {
        return Err(PyValueError::new_err(format!("{name} has negative strides: pass a contiguous array")));
    }
    let element = dlpack::element_bytes(dtype);
    let span = if shape.contains(&0) {
        0
    } else {
        element + shape.iter().zip(&strides).map(|(&n, &s)| (n - 1) * s as usize * element).sum::<usize>()
    };
    let bytes = PyArray1::<u8>::zeros(py, span, false);
    let host = bytes.data() as usize;
    py.detach(|| -> crate::Result<()> {
        let _current = cuda.enter()?;
        // SAFETY: `data` is the producer's CUDA memory, alive while `capsule` is (held through
        // the synchronize); the strides span `span` bytes from it; `host` is a fresh array of
        // `span` bytes no other code touches until this returns.
        unsafe { stream.copy_to_host(host as *mut u8, data, span)? };
        stream.synchronize()
    })?;
    drop(capsule);
    let strides = strides.iter().map(|&s| s as usize * element).collect();
    Ok(HostCopy { bytes, dtype: dtype_name, shape, strides })
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
        // SAFETY: the allocation is fresh device memory of this context with room for the
        // bytes; `host` is borrowed until the synchronize, after which the copy has run.
        unsafe { stream.copy_from_host(allocation.pointer, host.as_ptr(), host.len())? };
        let ready = stream.record()?;
        stream.synchronize()?;
        Ok((allocation, Arc::new(ready)))
    })?;
    Ok(PyCudaArray::of_type(allocation, ready, shape, dl_type))
}

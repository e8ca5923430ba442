//! DLPack on CUDA: the caller's CUDA arrays (torch, cupy, jax: any object with `__dlpack__`) read
//! as `CudaRays`, and the hits handed back as `vkray.CudaArray`s that DLPack consumers take
//! without a copy (`torch.from_dlpack(hits.t)`), their memory owned by vkray until the last
//! consumer lets go.

use std::ffi::{c_void, CStr};
use std::sync::Arc;

use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyCapsule, PyTuple, PyType};

use crate::gpu::cuda::{CudaAllocation, Event, LEGACY_STREAM};
use crate::trace::vulkan::cuda_rays::{CudaArray, CudaBound};
use crate::trace::Field;

/// DLPack's device type of CUDA memory (dlpack.h kDLCUDA).
pub(super) const DLPACK_CUDA: i32 = 2;
const DLPACK_FLOAT: u8 = 2;
const DLPACK_INT: u8 = 0;

#[repr(C)]
#[derive(Clone, Copy)]
struct DLDevice {
    device_type: i32,
    device_id: i32,
}

#[repr(C)]
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) struct DLDataType {
    pub code: u8,
    pub bits: u8,
    lanes: u16,
}

const fn dl_type(code: u8, bits: u8) -> DLDataType {
    DLDataType { code, bits, lanes: 1 }
}

/// The element types a CUDA array may hold through vkray: numpy's name and DLPack's type
/// (dlpack.h: kDLInt 0, kDLUInt 1, kDLFloat 2, kDLBool 6).
const ELEMENT_TYPES: [(&str, DLDataType); 12] = [
    ("float32", dl_type(DLPACK_FLOAT, 32)),
    ("float64", dl_type(DLPACK_FLOAT, 64)),
    ("float16", dl_type(DLPACK_FLOAT, 16)),
    ("int32", dl_type(DLPACK_INT, 32)),
    ("int64", dl_type(DLPACK_INT, 64)),
    ("int16", dl_type(DLPACK_INT, 16)),
    ("int8", dl_type(DLPACK_INT, 8)),
    ("uint8", dl_type(1, 8)),
    ("uint16", dl_type(1, 16)),
    ("uint32", dl_type(1, 32)),
    ("uint64", dl_type(1, 64)),
    ("bool", dl_type(6, 8)),
];

/// numpy's name of a DLPack element type, if vkray reads it.
pub(super) fn dtype_name(dtype: DLDataType) -> Option<&'static str> {
    ELEMENT_TYPES.iter().find(|(_, t)| *t == dtype).map(|(name, _)| *name)
}

/// DLPack's element type of numpy's `name`, if vkray writes it.
pub(super) fn dtype_named(name: &str) -> Option<DLDataType> {
    ELEMENT_TYPES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// Bytes of one element of `dtype`.
pub(super) fn element_bytes(dtype: DLDataType) -> usize {
    (dtype.bits as usize).div_ceil(8) * dtype.lanes.max(1) as usize
}

#[repr(C)]
struct DLTensor {
    data: *mut c_void,
    device: DLDevice,
    ndim: i32,
    dtype: DLDataType,
    shape: *mut i64,
    /// Strides in elements, or null: compact row-major.
    strides: *mut i64,
    byte_offset: u64,
}

#[repr(C)]
struct DLManagedTensor {
    dl_tensor: DLTensor,
    manager_ctx: *mut c_void,
    deleter: Option<unsafe extern "C" fn(*mut DLManagedTensor)>,
}

const DLTENSOR: &CStr = c"dltensor";

/// A caller's CUDA array read through DLPack: the array, and the capsule that keeps its memory
/// alive (held until the query no longer reads it).
pub(super) struct Borrowed<'py> {
    pub array: CudaArray,
    /// The shape before the last axis (rays) or the whole shape (bounds).
    pub leading: Vec<usize>,
    _capsule: Bound<'py, PyCapsule>,
}

impl Borrowed<'_> {
    /// The capsule that keeps the array's memory alive, to hold beyond this call.
    pub fn into_capsule(self) -> Py<PyCapsule> {
        self._capsule.unbind()
    }
}

/// `value`'s (device type, device id) if it is a DLPack array, else None; a `__dlpack_device__`
/// that raises or answers no pair of ints is a TypeError naming the argument (`name`).
pub(super) fn dlpack_device(value: &Bound<'_, PyAny>, name: &str) -> PyResult<Option<(i32, i32)>> {
    if !value.hasattr("__dlpack_device__")? {
        return Ok(None);
    }
    let device = value.call_method0("__dlpack_device__").and_then(|d| {
        let (kind, id): (Bound<'_, PyAny>, Bound<'_, PyAny>) = d.extract()?;
        Ok((dlpack_number(&kind)?, dlpack_number(&id)?))
    });
    device.map(Some).map_err(|e| {
        let error = PyTypeError::new_err(format!("{name}: its __dlpack_device__() failed: {e}"));
        error.set_cause(value.py(), Some(e));
        error
    })
}

/// A device type or id as `__dlpack_device__` gives it: an int, or an enum whose `value` is one
/// (Open3D's `DLDeviceType`, which is no int).
fn dlpack_number(value: &Bound<'_, PyAny>) -> PyResult<i32> {
    match value.extract() {
        Ok(number) => Ok(number),
        Err(not_int) => match value.getattr("value") {
            Ok(inner) => inner.extract(),
            Err(_) => Err(not_int),
        },
    }
}

/// The error for CUDA arrays on a device that is not their GPU (or not one CUDA shares with):
/// a TypeError naming the first such array and where it lives.
pub(super) fn unreadable(device: &str, arrays: [(&str, &Bound<'_, PyAny>); 2]) -> PyErr {
    for (name, value) in arrays {
        if let Ok(Some((kind, id))) = dlpack_device(value, name) {
            if kind == DLPACK_CUDA {
                return PyTypeError::new_err(format!(
                    "{name} lives on cuda:{id} (DLPack device type {kind}), which vkray cannot read here: {device} \
                     does not share memory with CUDA; pass host arrays (torch: .cpu(), cupy: .get(), jax: \
                     jax.device_get)"
                ));
            }
        }
    }
    PyTypeError::new_err("the rays must be CUDA arrays (with __dlpack__)")
}

/// A caller's CUDA array as its DLPack tensor describes it: where its elements are, their type,
/// its shape and its strides in elements (compact row-major where the producer gave none).
pub(super) struct CudaTensor<'py> {
    pub data: u64,
    pub dtype: DLDataType,
    pub shape: Vec<usize>,
    pub strides: Vec<i64>,
    pub capsule: Bound<'py, PyCapsule>,
}

/// The consumer stream the arrays of one query are exported for (`__dlpack__(stream=...)`: each
/// producer orders its pending writes before it). torch and cupy order them after their *current*
/// stream, whatever the array: once one array of such a type was exported for the stream, the
/// query's other arrays of the same type need no order of their own (`stream=-1`), which spares
/// torch's export its stream and event (about 45 µs of Python a tensor on an H200's host). Other
/// producers (jax: each array's own readiness) are asked for every array.
pub(super) struct ExportOrder<'py> {
    stream: usize,
    ordered: Option<Bound<'py, PyType>>,
}

impl<'py> ExportOrder<'py> {
    pub(super) fn new(stream: usize) -> ExportOrder<'py> {
        ExportOrder { stream, ordered: None }
    }

    /// The `stream` argument of `value`'s export.
    fn stream_for(&self, value: &Bound<'py, PyAny>) -> i64 {
        match &self.ordered {
            Some(kind) if value.get_type().is(kind) => -1,
            _ => self.stream as i64,
        }
    }

    /// After `value` was exported for the stream: its type orders the rest where it orders
    /// against its framework's current stream.
    fn exported(&mut self, value: &Bound<'py, PyAny>) {
        if self.ordered.is_some() {
            return;
        }
        let kind = value.get_type();
        let module = kind.module().map(|m| m.to_string()).unwrap_or_default();
        let current_stream = ["torch", "cupy"].iter().any(|f| module == *f || module.starts_with(&format!("{f}.")));
        if current_stream {
            self.ordered = Some(kind);
        }
    }
}

/// The CUDA array `value` exported through DLPack (its producer's pending writes ordered before
/// `order`'s stream), refused with a TypeError naming it (`name`) unless it lives on CUDA device
/// `ordinal`.
pub(super) fn export<'py>(
    value: &Bound<'py, PyAny>,
    name: &str,
    order: &mut ExportOrder<'py>,
    ordinal: i32,
) -> PyResult<CudaTensor<'py>> {
    match dlpack_device(value, name)? {
        Some((DLPACK_CUDA, id)) if id == ordinal => {}
        Some((1, _)) => {
            return Err(PyTypeError::new_err(format!(
                "{name} is in host memory while other arrays of the query are CUDA arrays: pass every array on \
                 cuda:{ordinal} (or every one in host memory)"
            )));
        }
        Some((kind, id)) => {
            let place =
                if kind == DLPACK_CUDA { format!("cuda:{id}") } else { format!("DLPack device ({kind}, {id})") };
            return Err(PyTypeError::new_err(format!(
                "{name} lives on {place} (DLPack device type {kind}), not on cuda:{ordinal}, the GPU this \
                 vkray.Device is: move it there, or pass host arrays"
            )));
        }
        None => {
            return Err(PyTypeError::new_err(format!(
                "{name} must be a CUDA array (with __dlpack__) like the query's other arrays"
            )))
        }
    }
    let kwargs = [("stream", order.stream_for(value))].into_py_dict(value.py())?;
    let capsule = value.call_method("__dlpack__", (), Some(&kwargs))?.downcast_into::<PyCapsule>()?;
    order.exported(value);
    // SAFETY: a "dltensor" capsule holds a DLManagedTensor (DLPack's contract), alive while the
    // capsule is (we hold it and never rename it, so its destructor frees it after us).
    let tensor = unsafe {
        let pointer = pyo3::ffi::PyCapsule_GetPointer(capsule.as_ptr(), DLTENSOR.as_ptr());
        if pointer.is_null() {
            return Err(PyErr::fetch(value.py()));
        }
        &(*(pointer as *const DLManagedTensor)).dl_tensor
    };
    let ndim = tensor.ndim.max(0) as usize;
    // SAFETY: DLPack's shape has `ndim` entries; strides too where not null.
    let shape: Vec<usize> = (0..ndim).map(|k| unsafe { *tensor.shape.add(k) } as usize).collect();
    let strides: Vec<i64> = match tensor.strides.is_null() {
        // SAFETY: as above.
        false => (0..ndim).map(|k| unsafe { *tensor.strides.add(k) }).collect(),
        true => compact_strides(&shape),
    };
    let data = tensor.data as u64 + tensor.byte_offset;
    Ok(CudaTensor { data, dtype: tensor.dtype, shape, strides, capsule })
}

/// The CUDA array `value` (ordered before `stream` by its producer) as rows of `columns` numbers
/// (3: the last axis is xyz; 1: every element a row), on CUDA device `ordinal`.
pub(super) fn borrow<'py>(
    value: &Bound<'py, PyAny>,
    name: &str,
    columns: usize,
    order: &mut ExportOrder<'py>,
    ordinal: i32,
) -> PyResult<Borrowed<'py>> {
    let CudaTensor { data, dtype, shape, mut strides, capsule } = export(value, name, order, ordinal)?;
    let wide = match (dtype.code, dtype.bits, dtype.lanes) {
        (DLPACK_FLOAT, 32, 1) => false,
        (DLPACK_FLOAT, 64, 1) => true,
        (code, bits, _) => {
            return Err(PyTypeError::new_err(format!(
                "{name} must be float32 or float64, got DLPack dtype code {code} with {bits} bits"
            )))
        }
    };
    let ndim = shape.len();
    let element = if wide { 8 } else { 4 };
    let (leading, column_stride) = if columns == 3 {
        if shape.last() != Some(&3) {
            return Err(PyValueError::new_err(format!("{name} must have shape (..., 3), got {shape:?}")));
        }
        let stride = strides.pop().expect("a last axis");
        (shape[..ndim - 1].to_vec(), stride)
    } else {
        (shape.clone(), 1)
    };
    let row_stride = collapsed_stride(&leading, &strides).ok_or_else(|| {
        PyValueError::new_err(format!(
            "{name}'s leading axes (shape {shape:?}, strides {strides:?} elements) do not flatten into one: pass a \
             contiguous array (e.g. tensor.contiguous())"
        ))
    })?;
    if row_stride < 0 || column_stride < 0 {
        return Err(PyValueError::new_err(format!("{name} has negative strides: pass a contiguous array")));
    }
    // Every row the same element (torch's `expand`): one row, shared by every ray.
    let rows = if row_stride == 0 { 1 } else { leading.iter().product::<usize>() };
    let array = CudaArray {
        pointer: data,
        rows,
        columns,
        wide,
        row_stride: row_stride as usize * element,
        column_stride: column_stride as usize * element,
    };
    Ok(Borrowed { array, leading, _capsule: capsule })
}

/// Row-major strides (in elements) of a compact array of `shape`.
fn compact_strides(shape: &[usize]) -> Vec<i64> {
    let mut strides = vec![1i64; shape.len()];
    for k in (0..shape.len().saturating_sub(1)).rev() {
        strides[k] = strides[k + 1] * shape[k + 1] as i64;
    }
    strides
}

/// The one stride that walks every element of the leading axes in row-major order, if there is
/// one (axes of length 1 have any stride); 0 for no axes.
pub(super) fn collapsed_stride(shape: &[usize], strides: &[i64]) -> Option<i64> {
    let axes: Vec<(usize, i64)> = shape.iter().copied().zip(strides.iter().copied()).filter(|(n, _)| *n != 1).collect();
    let Some(&(_, innermost)) = axes.last() else { return Some(0) };
    for pair in axes.windows(2) {
        let ((_, outer), (inner_len, inner)) = (pair[0], pair[1]);
        if outer != inner * inner_len as i64 {
            return None;
        }
    }
    Some(innermost)
}

/// A bound as the GPU-resident path takes it: a number, or a CUDA array of one per ray.
pub(super) fn bound<'py>(
    value: &Bound<'py, PyAny>,
    name: &str,
    order: &mut ExportOrder<'py>,
    ordinal: i32,
    held: &mut Vec<Borrowed<'py>>,
) -> PyResult<CudaBound> {
    if let Ok(number) = value.extract::<f64>() {
        return Ok(CudaBound::All(number));
    }
    let borrowed = borrow(value, name, 1, order, ordinal)?;
    let array = borrowed.array;
    held.push(borrowed);
    Ok(CudaBound::Each(array))
}

/// Hits in CUDA memory owned by vkray, handed to DLPack consumers without a copy. Consumers read
/// them in stream order: `__dlpack__(stream=s)` makes stream `s` wait until they are written.
#[pyclass(name = "CudaArray", module = "vkray._core", frozen)]
pub(super) struct PyCudaArray {
    memory: Arc<HitMemory>,
    shape: Vec<usize>,
    dtype: DLDataType,
}

/// One array's CUDA allocation and the event after which it is written.
struct HitMemory {
    allocation: CudaAllocation,
    ready: Arc<Event>,
}

impl PyCudaArray {
    /// The array of `field` for rays of shape `leading` (`wide`: the exact tier's f64 t and uv).
    pub(super) fn new(
        (field, wide): (Field, bool),
        allocation: CudaAllocation,
        ready: Arc<Event>,
        leading: &[usize],
    ) -> PyCudaArray {
        let mut shape = leading.to_vec();
        if field.components() > 1 {
            shape.push(field.components());
        }
        let float = |bits| DLDataType { code: DLPACK_FLOAT, bits, lanes: 1 };
        let dtype = match field {
            Field::T | Field::Uv => float(8 * (field.bytes_per_ray(wide) / field.components()) as u8),
            Field::Normal => float(32),
            _ => DLDataType { code: DLPACK_INT, bits: 32, lanes: 1 },
        };
        PyCudaArray { memory: Arc::new(HitMemory { allocation, ready }), shape, dtype }
    }

    /// An int64 array of `shape` in `allocation`, written once `ready` is reached (all hits'
    /// offsets and rays).
    pub(super) fn int64(allocation: CudaAllocation, ready: Arc<Event>, shape: Vec<usize>) -> PyCudaArray {
        PyCudaArray::of_type(allocation, ready, shape, dl_type(DLPACK_INT, 64))
    }

    /// An array of `shape` and element type `dtype` in `allocation`, written once `ready` is
    /// reached (a query's answer copied from the host).
    pub(super) fn of_type(allocation: CudaAllocation, ready: Arc<Event>, shape: Vec<usize>, dtype: DLDataType) -> Self {
        PyCudaArray { memory: Arc::new(HitMemory { allocation, ready }), shape, dtype }
    }
}

impl Drop for HitMemory {
    fn drop(&mut self) {
        // The allocation is freed on the legacy default stream: after vkray's copy into it, and
        // after what the caller queued on blocking streams (torch's default stream among them).
        let _ = self.ready.order_before(LEGACY_STREAM);
    }
}

/// What a capsule's DLManagedTensor owns: its shape and strides, and the memory.
#[repr(C)]
struct Exported {
    tensor: DLManagedTensor,
    shape: Vec<i64>,
    memory: Arc<HitMemory>,
}

/// DLManagedTensor's deleter: frees what `__dlpack__` allocated.
unsafe extern "C" fn delete_exported(tensor: *mut DLManagedTensor) {
    if !tensor.is_null() {
        // SAFETY: `tensor` is the first field of an `Exported` boxed by `__dlpack__`, deleted once
        // (by the consumer that took it, or by the capsule's destructor if none did).
        drop(unsafe { Box::from_raw((*tensor).manager_ctx as *mut Exported) });
    }
}

/// The capsule's destructor: deletes the tensor unless a consumer took it (renamed the capsule).
unsafe extern "C" fn destroy_capsule(capsule: *mut pyo3::ffi::PyObject) {
    // SAFETY: called by Python with the capsule; a still-named capsule holds our tensor.
    unsafe {
        if pyo3::ffi::PyCapsule_IsValid(capsule, DLTENSOR.as_ptr()) == 1 {
            let tensor = pyo3::ffi::PyCapsule_GetPointer(capsule, DLTENSOR.as_ptr()) as *mut DLManagedTensor;
            delete_exported(tensor);
        }
    }
}

#[pymethods]
impl PyCudaArray {
    #[getter]
    fn shape<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        PyTuple::new(py, &self.shape)
    }

    /// numpy's name of the element type ("float32", "int32", "float64", "bool", ...).
    #[getter]
    fn dtype(&self) -> &'static str {
        dtype_name(self.dtype).unwrap_or("uint8")
    }

    fn __len__(&self) -> usize {
        self.shape.first().copied().unwrap_or(0)
    }

    fn __dlpack_device__(&self) -> (i32, i32) {
        (DLPACK_CUDA, self.memory.allocation.ordinal())
    }

    /// A DLPack capsule of the array (legacy `dltensor`). `stream`: the consumer's CUDA stream,
    /// made to wait until the hits are written (None: the legacy default stream; -1: no wait).
    #[pyo3(signature = (*, stream=None, max_version=None, dl_device=None, copy=None))]
    fn __dlpack__<'py>(
        &self,
        py: Python<'py>,
        stream: Option<i64>,
        max_version: Option<Bound<'py, PyAny>>,
        dl_device: Option<(i32, i32)>,
        copy: Option<bool>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let _ = max_version; // A legacy capsule is what every DLPack version accepts.
        if let Some(device) = dl_device {
            if device != self.__dlpack_device__() {
                return Err(PyValueError::new_err(format!("vkray.CudaArray cannot be exported to device {device:?}")));
            }
        }
        if copy == Some(true) {
            return Err(PyValueError::new_err("vkray.CudaArray is exported without a copy (copy=True unsupported)"));
        }
        match stream.unwrap_or(LEGACY_STREAM as i64) {
            -1 => {}
            s if s > 0 => self.memory.ready.order_before(s as usize)?,
            s => return Err(PyValueError::new_err(format!("stream must be -1 or a CUDA stream handle, got {s}"))),
        }
        let shape: Vec<i64> = self.shape.iter().map(|&n| n as i64).collect();
        let mut exported = Box::new(Exported {
            tensor: DLManagedTensor {
                dl_tensor: DLTensor {
                    data: self.memory.allocation.pointer as *mut c_void,
                    device: DLDevice { device_type: DLPACK_CUDA, device_id: self.memory.allocation.ordinal() },
                    ndim: shape.len() as i32,
                    dtype: self.dtype,
                    shape: std::ptr::null_mut(),
                    strides: std::ptr::null_mut(),
                    byte_offset: 0,
                },
                manager_ctx: std::ptr::null_mut(),
                deleter: Some(delete_exported),
            },
            shape,
            memory: self.memory.clone(),
        });
        exported.tensor.dl_tensor.shape = exported.shape.as_mut_ptr();
        let raw = Box::into_raw(exported);
        // SAFETY: `raw` is a live box; its first field is the tensor (repr(C)).
        unsafe { (*raw).tensor.manager_ctx = raw as *mut c_void };
        // SAFETY: the pointer is our boxed tensor; the destructor frees it unless a consumer
        // renames the capsule and takes it.
        let capsule = unsafe { pyo3::ffi::PyCapsule_New(raw as *mut c_void, DLTENSOR.as_ptr(), Some(destroy_capsule)) };
        if capsule.is_null() {
            // SAFETY: the capsule did not take the box.
            unsafe { delete_exported(raw as *mut DLManagedTensor) };
            return Err(PyErr::fetch(py));
        }
        // SAFETY: a new reference, owned from here.
        Ok(unsafe { Bound::from_owned_ptr(py, capsule) })
    }

    /// A numpy copy (waits for the hits).
    fn numpy<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let memory = self.memory.clone();
        let host = py.detach(move || -> crate::Result<Vec<u8>> {
            memory.ready.synchronize()?;
            memory.allocation.read()
        })?;
        let numpy = py.import("numpy")?;
        let array = numpy.call_method1("frombuffer", (pyo3::types::PyBytes::new(py, &host), self.dtype()))?;
        array.call_method1("reshape", (PyTuple::new(py, &self.shape)?,))?.call_method0("copy")
    }

    #[pyo3(signature = (dtype=None, copy=None))]
    fn __array__<'py>(
        &self,
        py: Python<'py>,
        dtype: Option<Bound<'py, PyAny>>,
        copy: Option<bool>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let _ = copy; // Always a copy: the memory is on the GPU.
        let array = self.numpy(py)?;
        match dtype {
            Some(dtype) => array.call_method1("astype", (dtype,)),
            None => Ok(array),
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "vkray.CudaArray(shape={:?}, dtype={}, device=cuda:{})",
            self.shape,
            self.dtype(),
            self.memory.allocation.ordinal()
        )
    }
}

use pyo3::types::IntoPyDict;

//! Array intake: borrowed views of the numpy arrays the Python layer passes (C-contiguous, with
//! an accepted dtype), read by the core without copies.

use numpy::{
    Element, PyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

use crate::geometry::arrays::{Indices, Vec3s};
use crate::geometry::rays::{Masks, PerRay};

/// `array` (the argument `name`) borrowed for reading; a ValueError, not a panic, where another
/// call is writing it meanwhile (its `out=`).
pub(super) fn read<'py, T: Element, D: numpy::ndarray::Dimension>(
    name: &str,
    array: &Bound<'py, PyArray<T, D>>,
) -> PyResult<PyReadonlyArray<'py, T, D>> {
    array.try_readonly().map_err(|e| {
        PyValueError::new_err(format!("{name} cannot be read here: another call is writing it (out=): {e}"))
    })
}

/// A borrowed (N, 3) float32/float64 C-contiguous array.
pub(super) enum Vec3Array<'py> {
    F32(PyReadonlyArray2<'py, f32>),
    F64(PyReadonlyArray2<'py, f64>),
}

impl<'py> Vec3Array<'py> {
    pub(super) fn extract(name: &str, array: &Bound<'py, PyAny>) -> PyResult<Self> {
        let wrong = || PyTypeError::new_err(format!("{name} must be a float32 or float64 array of shape (N, 3)"));
        let borrowed = if let Ok(a) = array.downcast::<PyArray2<f32>>() {
            Vec3Array::F32(read(name, a)?)
        } else if let Ok(a) = array.downcast::<PyArray2<f64>>() {
            Vec3Array::F64(read(name, a)?)
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

    pub(super) fn view(&self) -> PyResult<Vec3s<'_>> {
        Ok(match self {
            Vec3Array::F32(a) => Vec3s::F32(a.as_slice()?),
            Vec3Array::F64(a) => Vec3s::F64(a.as_slice()?),
        })
    }
}

/// A borrowed (F, 3) C-contiguous array of triangle corner indices.
pub(super) enum IndexArray<'py> {
    U16(PyReadonlyArray2<'py, u16>),
    U32(PyReadonlyArray2<'py, u32>),
    I32(PyReadonlyArray2<'py, i32>),
    I64(PyReadonlyArray2<'py, i64>),
}

impl<'py> IndexArray<'py> {
    pub(super) fn extract(array: &Bound<'py, PyAny>) -> PyResult<Self> {
        let borrowed = if let Ok(a) = array.downcast::<PyArray2<u16>>() {
            IndexArray::U16(read("faces", a)?)
        } else if let Ok(a) = array.downcast::<PyArray2<u32>>() {
            IndexArray::U32(read("faces", a)?)
        } else if let Ok(a) = array.downcast::<PyArray2<i32>>() {
            IndexArray::I32(read("faces", a)?)
        } else if let Ok(a) = array.downcast::<PyArray2<i64>>() {
            IndexArray::I64(read("faces", a)?)
        } else {
            return Err(PyTypeError::new_err("faces must be an int32, int64, uint32 or uint16 array of shape (F, 3)"));
        };
        if array.downcast::<numpy::PyUntypedArray>()?.shape()[1] != 3 {
            return Err(PyTypeError::new_err("faces must have shape (F, 3)"));
        }
        Ok(borrowed)
    }

    pub(super) fn view(&self) -> PyResult<Indices<'_>> {
        Ok(match self {
            IndexArray::U16(a) => Indices::U16(a.as_slice()?),
            IndexArray::U32(a) => Indices::U32(a.as_slice()?),
            IndexArray::I32(a) => Indices::I32(a.as_slice()?),
            IndexArray::I64(a) => Indices::I64(a.as_slice()?),
        })
    }
}

/// tmin or tmax: one float for every ray, or a borrowed (N,) float64 array.
pub(super) enum Bound1<'py> {
    All(f64),
    Each(PyReadonlyArray1<'py, f64>),
}

impl<'py> Bound1<'py> {
    pub(super) fn extract(name: &str, value: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(array) = value.downcast::<PyArray1<f64>>() {
            return Ok(Bound1::Each(read(name, array)?));
        }
        value
            .extract::<f64>()
            .map(Bound1::All)
            .map_err(|_| PyTypeError::new_err(format!("{name} must be a float or a float64 array of shape (N,)")))
    }

    pub(super) fn view(&self) -> PyResult<PerRay<'_>> {
        Ok(match self {
            Bound1::All(v) => PerRay::All(*v),
            Bound1::Each(a) => PerRay::Each(a.as_slice()?),
        })
    }
}

/// Per-ray masks: one 8-bit value or a uint8 array.
pub(super) enum MaskArray<'py> {
    All(u8),
    Each(PyReadonlyArray1<'py, u8>),
}

impl<'py> MaskArray<'py> {
    pub(super) fn extract(value: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(array) = value.downcast::<PyArray1<u8>>() {
            return Ok(MaskArray::Each(read("mask", array)?));
        }
        value
            .extract::<u8>()
            .map(MaskArray::All)
            .map_err(|_| PyValueError::new_err("mask must be an integer in [0, 255] or a uint8 array of shape (N,)"))
    }

    pub(super) fn view(&self) -> PyResult<Masks<'_>> {
        Ok(match self {
            MaskArray::All(m) => Masks::All(*m),
            MaskArray::Each(a) => Masks::Each(a.as_slice()?),
        })
    }
}

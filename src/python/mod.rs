//! The one binding module: maps the core to `vkray._core`. Arrays arrive C-contiguous with an
//! accepted dtype (the Python layer sees to that).
//!
//! Every call into the core goes through `run`: the GIL is released for the whole call (inputs
//! are borrowed slices, outputs preallocated numpy arrays), so no core lock is ever waited for by
//! a thread holding the GIL; signals are checked between chunks; panics never cross into Python.

mod calls;

mod numpy_views;

mod dlpack;

mod cuda_batch;

mod cuda_staging;

mod device_engines;

mod mesh_binding;

mod scene_binding;

mod device_binding;

use calls::{run, ForkedDeviceError, NoDeviceError, UnsupportedError, ValidationError, VkrayError, VulkanError};

use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The usable devices, best first.
#[pyfunction]
fn devices(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    let infos = run(py, |_| crate::gpu::context::list_devices())?;
    infos.iter().map(|info| device_binding::info_dict(py, info)).collect()
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

/// Host memory a new allocation can still count on (bytes), or None where unknown.
#[pyfunction]
fn host_memory_available() -> Option<u64> {
    crate::gpu::memory::host_memory_available()
}

/// Each ray's count of hits (int64, N) from CSR offsets (int64, N + 1), on all cores: numpy's
/// `diff` took a millisecond of a million rays on one.
#[pyfunction]
fn counts_of_offsets<'py>(
    py: Python<'py>,
    offsets: numpy::PyReadonlyArray1<'py, i64>,
) -> PyResult<Bound<'py, numpy::PyArray1<i64>>> {
    use rayon::prelude::*;
    let offsets = offsets.as_slice()?;
    let counts: Vec<i64> = py.detach(|| {
        crate::geometry::parallel::install(|| {
            offsets.par_windows(2).with_min_len(1 << 14).map(|w| w[1] - w[0]).collect()
        })
    });
    Ok(numpy::PyArray1::from_vec(py, counts))
}

/// Each hit's ray (int64, H) from CSR offsets (int64, N + 1; nondecreasing from 0), on all cores.
#[pyfunction]
fn ray_index_of_offsets<'py>(
    py: Python<'py>,
    offsets: numpy::PyReadonlyArray1<'py, i64>,
) -> PyResult<Bound<'py, numpy::PyArray1<i64>>> {
    use rayon::prelude::*;
    let offsets = offsets.as_slice()?;
    let rays = run(py, |_| {
        // Checked on all cores too: the blocks' split trusts them.
        let ordered =
            crate::geometry::parallel::install(|| offsets.par_windows(2).with_min_len(1 << 14).all(|w| w[0] <= w[1]));
        if offsets.first() != Some(&0) || !ordered {
            return Err(crate::error::invalid_value("offsets must start at 0 and never decrease"));
        }
        crate::trace::host_tiers::ray_indices(offsets)
    })?;
    Ok(numpy::PyArray1::from_vec(py, rays))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_function(wrap_pyfunction!(devices, m)?)?;
    m.add_function(wrap_pyfunction!(spirv_modules, m)?)?;
    m.add_function(wrap_pyfunction!(host_memory_available, m)?)?;
    m.add_function(wrap_pyfunction!(counts_of_offsets, m)?)?;
    m.add_function(wrap_pyfunction!(ray_index_of_offsets, m)?)?;
    m.add_class::<device_binding::PyDevice>()?;
    m.add_class::<mesh_binding::PyMesh>()?;
    m.add_class::<scene_binding::PyScene>()?;
    m.add_class::<dlpack::PyCudaArray>()?;
    m.add_class::<cuda_batch::PyCudaBatch>()?;
    m.add("VkrayError", py.get_type::<VkrayError>())?;
    m.add("NoDeviceError", py.get_type::<NoDeviceError>())?;
    m.add("UnsupportedError", py.get_type::<UnsupportedError>())?;
    m.add("VulkanError", py.get_type::<VulkanError>())?;
    m.add("ValidationError", py.get_type::<ValidationError>())?;
    m.add("ForkedDeviceError", py.get_type::<ForkedDeviceError>())?;
    Ok(())
}

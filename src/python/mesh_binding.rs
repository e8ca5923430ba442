//! `vkray._core.Mesh`: a BLAS and its figures; refitting.

use std::sync::Arc;

use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::calls::run;
use super::numpy_views::Vec3Array;
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::scene::{Mesh, MeshKind};

/// A triangle mesh and its bottom-level acceleration structure.
#[pyclass(name = "Mesh", module = "vkray._core", frozen)]
pub(super) struct PyMesh {
    pub(super) mesh: Arc<Mesh>,
}

impl PyMesh {
    pub(super) fn new(mesh: Mesh) -> PyMesh {
        PyMesh { mesh: Arc::new(mesh) }
    }
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
        let d = stats_dict(py, &self.mesh.stats(), &self.mesh.options)?;
        d.set_item("update_seconds", self.mesh.last_update_seconds())?;
        d.set_item("vertex_format", self.mesh.vertex_format.name())?;
        d.set_item("vertex_bytes", self.mesh.vertex_format.stride() * self.mesh.vertex_count)?;
        Ok(d)
    }

    /// Moves the vertices ((V, 3), same V) and refits the BLAS in place; waits for queries on
    /// scenes holding the mesh.
    fn update(&self, py: Python<'_>, vertices: &Bound<'_, PyAny>) -> PyResult<()> {
        let vertices = Vec3Array::extract("vertices", vertices)?;
        let vertices = vertices.view()?;
        run(py, |_| self.mesh.update(vertices))
    }
}

pub(super) fn stats_dict<'py>(
    py: Python<'py>,
    stats: &BuildStats,
    options: &BuildOptions,
) -> PyResult<Bound<'py, PyDict>> {
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

//! What users build, as every engine sees it (meshes, instances, scenes: host geometry in f64
//! and an engine's hierarchy behind a trait), the CPU engine's hierarchies (Embree scenes), and
//! the Vulkan engine's: BLAS, TLAS and the exact tier's, closest points' and winding numbers'
//! structures.

pub mod mesh;

pub mod instance;

pub mod winding_cap;

pub mod inside_grid;

pub mod top_level;

pub mod cpu_mesh;

pub mod cpu_scene;

pub mod vulkan_instance;

pub mod vulkan_mesh;

pub mod closest;

pub mod exact;

pub mod vulkan_scene;

pub use closest::{ClosestScene, WindingCap, WindingScene};
pub use cpu_mesh::{build_cpu_meshes, build_cpu_spheres, CpuMesh};
pub use cpu_scene::{build_cpu_scene, CpuScene};
pub use exact::ExactScene;
pub use inside_grid::{
    grid_caps, CellValue, GridSurfaces, InsideGrid, CAP_WINDING_LIMIT, GRID_INSIDE, GRID_OUTSIDE, GRID_UNDECIDED,
};
pub use instance::{Instance, InstanceFlags, Placement, IDENTITY};
pub use mesh::{Mesh, MeshBatch, MeshGeometry, MeshHierarchy, MeshInput, MeshKind};
pub use top_level::{Scene, SceneHierarchy};
pub use vulkan_mesh::{build_vulkan_meshes, build_vulkan_spheres, VulkanMesh};
pub use vulkan_scene::{build_vulkan_scene, VulkanScene};
pub use winding_cap::{cap_geometry, CapGeometry, MAX_CAP_EDGES, WINDING_MARGIN, WINDING_TERM_ERROR};

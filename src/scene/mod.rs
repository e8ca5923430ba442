//! What users build: meshes (BLAS), instances and scenes (TLAS), and the exact tier's view of a
//! scene.

pub mod mesh;

pub mod instance;

pub mod closest;

pub mod exact;

pub mod top_level;

pub use closest::{ClosestScene, WindingCap, WindingScene, MAX_CAP_EDGES, WINDING_MARGIN, WINDING_TERM_ERROR};
pub use exact::ExactScene;
pub use instance::{Instance, InstanceFlags, Placement, IDENTITY, MAX_CUSTOM_INDEX};
pub use mesh::{Mesh, MeshInput, MeshKind};
pub use top_level::Scene;

//! Queries: what they ask (`request`), the hit fields they write (`fields`), pipeline variants
//! and their shader binding tables (`variants`), staging slots (`staging`) and the pool of idle resources (`idle`), the chunk loop
//! (`chunks`), rays the GPU packs itself (`device_rays`), closest points on the GPU (`closest`), signed distances in one pass (`signed`), time profiles (`profile`), intersection-shader probes (`probe`), the host's f64
//! tiers (`tiers`), and the tracer that dispatches between them (`tracer`).

mod all_hits;
mod chunks;
mod closest;
pub mod cuda_rays;
pub mod device_rays;
pub mod fields;
pub mod idle;
mod probe;
pub mod profile;
pub mod request;
mod sensor;
mod signed;
mod staging;
pub mod tiers;
pub mod tracer;
mod variants;

pub use fields::{Field, HitSink};
pub use idle::IdleMemory;
pub use profile::TraceProfile;
pub use request::{Cull, Precision, Query, Request, SignedDistance};
pub use tracer::Tracer;

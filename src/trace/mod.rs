//! Queries: hit fields, pipeline variants, staging, the chunk loop, the host tiers, and the
//! tracer that dispatches between them.

pub mod request;
pub mod tiers;
pub mod tracer;

pub use request::{Cull, Precision, Query, Request};
pub use tracer::{Field, HitSink, TraceProfile, Tracer};

//! Queries. Its files, lowest first (each imports only files above it in this list): what a
//! query asks (`request`), the hit fields it writes (`hit_fields`), where its time went
//! (`profile`), the pools of idle resources (`idle`), chunks sized by time (`pacer`), the host's winding rays (`host_winding`),
//! the host's f64 tiers (`host_tiers`), all hits as columns (`hit_columns`), `contains` through a scene's inside grid (`grid_contains`), the engine seam (`engine`: what a query needs from the
//! device that runs it), the Vulkan engine (`vulkan`), the CPU engine (`cpu`), and the dispatcher
//! that picks a tier and hands the batch to an engine or the host tiers (`tracer`).

pub mod request;

pub mod hit_fields;

pub mod profile;

pub mod idle;

pub mod pacer;

pub mod host_winding;

pub mod host_tiers;

pub mod hit_columns;

pub mod grid_contains;

pub mod engine;

pub mod vulkan;

pub mod cpu;

pub mod tracer;

pub use cpu::CpuEngine;
pub use engine::{Engine, EngineLimits};
pub use hit_fields::{Field, HitSink};
pub use idle::IdleMemory;
pub use profile::TraceProfile;
pub use request::{Cull, Precision, Query, Request, SignedDistance};
pub use tracer::Tracer;
pub use vulkan::VulkanEngine;

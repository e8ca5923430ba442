//! The engine seam: what a query needs from the device that runs it. The dispatcher (`Tracer`)
//! picks a tier and a query kind and hands the batch to an `Engine`; the host tiers
//! (`host_tiers`) sit beside it, usable with any engine. Nothing here names Vulkan: the Vulkan
//! engine (`vulkan`) implements it today; a CPU engine can implement it without a device.

use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::build_options::BuildOptions;
use crate::geometry::rays::PerRay;
use crate::geometry::reference::ReferenceHit;
use std::sync::Arc;

use crate::scene::{InsideGrid, Instance, Mesh, MeshBatch, Scene};
use crate::trace::hit_columns::{AskedColumn, HitColumns};
use crate::trace::hit_fields::HitSink;
use crate::trace::host_tiers::AllHits;
use crate::trace::idle::IdleMemory;
use crate::trace::profile::TraceProfile;
use crate::trace::request::{PointBatch, Precision, RayBatch, SignedDistance};

/// What an engine can do, for the dispatcher's choice of tier.
#[derive(Clone, Copy, Debug)]
pub struct EngineLimits {
    /// Whether the engine runs the exact tier's f64 tests (and winding numbers) itself; without
    /// them the exact tier's winding numbers are the reference tier's, on the host.
    pub f64_tests: bool,
    /// Whether its queries run on the host's cores (the CPU engine, Vulkan on a CPU): `contains`
    /// then answers most points from the scene's inside grid (`grid_contains`), which a GPU's
    /// own exact test is as fast as (measured on an H100: 0.76–1.23× with the grid).
    pub on_host: bool,
}

/// A device that runs queries' batches. Every method may be called by any number of threads at
/// once; the caller has checked the request and its arrays' shapes; the engine holds the scene's
/// meshes (`Scene::hold_meshes`) where it reads them.
pub trait Engine: Send + Sync + 'static {
    /// The engine as `Any`, for what only one engine has (the Vulkan engine's CUDA rays).
    fn as_any(&self) -> &dyn std::any::Any;
    /// The device's name, for messages.
    fn name(&self) -> &str;
    /// The device's index among the usable ones (names its threads).
    fn index(&self) -> usize;
    fn limits(&self) -> EngineLimits;
    /// Fails where the device can no longer be used (lost, or opened before a fork).
    fn check_usable(&self) -> Result<()>;
    /// Fails with what the device's own checks reported during the last calls (the Vulkan
    /// validation layer's messages), if anything.
    fn check_reported(&self) -> Result<()>;

    /// Builds each item's mesh (its host copy and the engine's hierarchy), batched as the
    /// batch's `scratch_budget` allows; the error of a bad item names its position.
    fn build_meshes(&self, batch: MeshBatch) -> Result<Vec<Mesh>>;
    /// Builds a set of spheres: `centers` (N, 3), `radii` one per sphere or one for all.
    fn build_spheres(&self, centers: Vec3s, radii: PerRay, options: BuildOptions) -> Result<Mesh>;
    /// Places `instances` (of meshes this engine built) and builds the scene's hierarchy.
    fn build_scene(&self, instances: &[Instance], options: BuildOptions) -> Result<Scene>;

    /// What the engine keeps idle between queries (staging, scratch, leases).
    fn idle_memory(&self) -> IdleMemory;
    /// Frees what `idle_memory` counts.
    fn release_idle_memory(&self);
    /// Rays per chunk: what bounds a query's working memory.
    fn chunk_rays(&self) -> usize;
    fn set_chunk_rays(&self, rays: usize) -> Result<()>;
    /// Host bytes the engine's staging takes for a query of `rays` rays (`exact`: f64 rays).
    fn staging_bytes(&self, rays: usize, exact: bool) -> usize;
    /// Where the time went in the device's last query (of any thread).
    fn last_profile(&self) -> TraceProfile;
    /// Keeps `profile` as the device's last.
    fn keep_profile(&self, profile: TraceProfile);

    /// Traces the batch's rays in one of the device's tiers (`exact`: the exact tier's f64 test,
    /// else the fast tier), writing every field `sink` asks for (`hit` too).
    fn trace_rays(&self, batch: RayBatch, exact: bool, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()>;

    /// Every hit of every ray (the nearest `max_hits` of each), at `batch.request.precision`:
    /// `Exact` (f64 hits) or otherwise the fast tier's (f32 hits, which the dispatcher may refine).
    /// `host_bytes_per_hit`: what the caller will need per hit, for refusing a result that cannot
    /// fit before it is stored.
    fn all_hits(&self, batch: RayBatch, max_hits: usize, host_bytes_per_hit: usize) -> Result<AllHits>;

    /// `all_hits` written straight into the answer's `asked` columns, where the engine can for
    /// this batch and these columns (None: it cannot; the dispatcher writes them from
    /// `all_hits`'s records). Asked only in the fast and exact tiers, on scenes without spheres.
    fn all_hit_columns(
        &self,
        _batch: RayBatch,
        _max_hits: usize,
        _asked: &[AskedColumn],
    ) -> Result<Option<HitColumns>> {
        Ok(None)
    }

    /// Takes back the records of an `all_hits` answer the caller is done with, for the next
    /// query to fill (their pages already touched), where the engine keeps them.
    fn recycle_hits(&self, _hits: Vec<ReferenceHit>) {}

    /// The surface point nearest each point within distance `within`, measured at `precision`
    /// (`Exact`: f64; `Fast`: f32), its fields written into `sink`.
    fn closest_points(&self, batch: PointBatch, within: f64, precision: Precision, sink: &mut HitSink) -> Result<()>;

    /// Whether each point is inside any instance (1) or not (0), exactly: by parity (the caller
    /// checked that every mesh is closed) or by winding number. Called only where
    /// `limits().f64_tests` holds, or for parity.
    fn contains(&self, batch: PointBatch, winding: bool, out: &mut [u8]) -> Result<()>;

    /// Signed distances in one pass, where the engine has one for `query`: true, `out` written;
    /// false, nothing written (the dispatcher then asks `closest_points` and `contains`).
    fn signed_distance(&self, batch: PointBatch, query: SignedDistance, out: &mut [f64]) -> Result<bool>;

    /// `contains` at the exact tier through the scene's inside `grid`, where the engine reads the
    /// grid itself: true, `out` written; false, nothing written (the dispatcher then marks the
    /// points on the host's cores, `grid_contains`).
    fn contains_through_grid(
        &self,
        _batch: PointBatch,
        _grid: &Arc<InsideGrid>,
        _winding: bool,
        _out: &mut [u8],
    ) -> Result<bool> {
        Ok(false)
    }
}

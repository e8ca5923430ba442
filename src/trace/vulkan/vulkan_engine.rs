//! The Vulkan engine: the `Engine` seam over one Vulkan device. It makes the shared value and
//! each path once, and hands each batch to its path; the CUDA rays path and `explain` are its
//! own (no other engine has them).

use std::sync::Arc;

use super::all_hits::{gpu_column_fields, one_part_meshes, AllHitsPath, IDLE_LISTS};
use super::closest_points::{ClosestPoints, PointPipelines};
use super::containment::Containment;
use super::cuda_all_hits::CudaAllHitsPath;
use super::cuda_rays::{CudaRaysPath, CudaState};
use super::gpu_rays::GpuRays;
use super::inside_points::InsidePointsPath;
use super::packed_rays::{PackPipelines, PackedRays};
use super::probes::Probes;
use super::ray_chunks::RayChunks;
use super::shared::Shared;
use super::signed_distance::SignedDistancePath;
use super::staging::Slot;
use super::variants::{ray_flag_names, Stage, VariantKey};
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::build_options::BuildOptions;
use crate::geometry::rays::PerRay;
use crate::geometry::reference::ReferenceHit;
use crate::gpu::context::{Backend, Context};
use crate::gpu::records::{ExactHit, FastHit};
use crate::scene::{
    build_vulkan_meshes, build_vulkan_scene, build_vulkan_spheres, InsideGrid, Instance, Mesh, MeshBatch, Scene,
};
use crate::trace::engine::{Engine, EngineLimits};
use crate::trace::hit_columns::{AskedColumn, HitColumns};
use crate::trace::hit_fields::{Field, HitSink};
use crate::trace::host_tiers::AllHits;
use crate::trace::idle::{Idle, IdleMemory, IdlePool, SpareRecords};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{PointBatch, Precision, Query, RayBatch, Request, SignedDistance};

/// What `VulkanEngine::explain` tells of a variant.
pub struct Explanation {
    pub key: VariantKey,
    /// The shader stages, by role.
    pub stages: Vec<&'static str>,
    /// Ray-query backend: the candidate loop's branches the variant keeps.
    pub branches: Vec<&'static str>,
    /// The static ray flags, by name.
    pub ray_flags: Vec<&'static str>,
    /// Pipeline flags that skip a kind of primitive for the whole pipeline.
    pub pipeline_skips: Vec<&'static str>,
}

/// One Vulkan device's engine: the value its paths share and the paths.
pub struct VulkanEngine {
    shared: Arc<Shared>,
    rays: Arc<GpuRays>,
    all_hits: Arc<AllHitsPath>,
    points: Arc<ClosestPoints>,
    signed: SignedDistancePath,
    /// `contains` through the inside grid on the GPU (host points, and CUDA points).
    pub inside_points: InsidePointsPath,
    containment: Containment,
    /// The CUDA rays path (GPU-resident rays and hits).
    pub cuda: CudaRaysPath,
    /// All hits of CUDA rays, left in CUDA memory.
    pub cuda_all_hits: CudaAllHitsPath,
}

impl VulkanEngine {
    pub fn new(ctx: &Arc<Context>) -> Result<VulkanEngine> {
        let points = Arc::new(PointPipelines::new(ctx)?);
        let packing = Arc::new(PackPipelines::new(ctx)?);
        let lists = Arc::new(IdlePool::new(IDLE_LISTS.0, IDLE_LISTS.1));
        let spare_records = Arc::new(SpareRecords::default());
        let cuda = Arc::new(CudaState::default());
        let pools: Vec<Arc<dyn Idle>> =
            vec![points.clone(), packing.clone(), lists.clone(), cuda.clone(), spare_records.clone()];
        let shared = Arc::new(Shared::new(ctx, pools)?);
        let chunks = RayChunks::new(&shared);
        let probes = Arc::new(Probes::new(&shared, &chunks));
        let packed = Arc::new(PackedRays::new(&shared, &probes, &packing));
        let rays = Arc::new(GpuRays { chunks, packed: packed.clone(), probes: probes.clone() });
        let all_hits = Arc::new(AllHitsPath::new(&shared, &rays, &lists, &spare_records)?);
        let points = Arc::new(ClosestPoints::new(&shared, &points));
        Ok(VulkanEngine {
            signed: SignedDistancePath::new(&shared, &points, &probes),
            inside_points: InsidePointsPath::new(&shared, &points, &probes),
            containment: Containment::new(&shared, &rays, &all_hits, &points),
            cuda: CudaRaysPath::new(&shared, &packed, &cuda),
            cuda_all_hits: CudaAllHitsPath::new(CudaRaysPath::new(&shared, &packed, &cuda), &all_hits),
            shared,
            rays,
            all_hits,
            points,
        })
    }

    /// The variant a query of `request` on `scene` runs (writing `outputs`), as `Scene.explain`
    /// shows it: its stages (or ray-query branches), static ray flags and specialization. The
    /// host's tiers run none: `None` for the reference tier.
    pub fn explain(&self, scene: &Scene, request: Request, outputs: u32, sensor: bool) -> Option<Explanation> {
        let exact = match request.precision {
            Precision::Reference => return None,
            Precision::Exact => true,
            // Refined transmittance and all hits re-intersect the fast tier's hits on the host.
            Precision::Fast | Precision::Refined => false,
        };
        // Transmittance through opaque triangles only is an occlusion query; in the refined tier
        // the product is the host's, over the fast tier's hits (see `run_tier`).
        let (request, outputs) = match (request.query, request.precision) {
            (Query::Transmit, _) if !scene.has_opacity() => {
                (Request { query: Query::Occluded, ..request }, Field::Prim.bit())
            }
            (Query::Transmit, Precision::Refined) => {
                (Request { query: Query::All, opacity_threshold: 0.0, ..request }, Field::Prim.bit())
            }
            _ => (request, outputs),
        };
        let key = self.shared.variant_key(scene, request, exact, outputs, sensor);
        let backend = self.shared.ctx.backend;
        Some(Explanation {
            stages: key.stages(backend).into_iter().map(Stage::name).collect(),
            branches: if backend == Backend::RayQuery { key.candidate_branches() } else { Vec::new() },
            ray_flags: ray_flag_names(key.ray_flags),
            pipeline_skips: match (backend, self.shared.ctx.limits.ray_traversal_primitive_culling, exact, key.spheres)
            {
                (Backend::Pipeline, true, false, false) => vec!["SkipAABBs"],
                (Backend::Pipeline, true, true, _) => vec!["SkipTriangles"],
                _ => Vec::new(),
            },
            key,
        })
    }
}

impl Engine for VulkanEngine {
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn name(&self) -> &str {
        &self.shared.ctx.info.name
    }

    fn index(&self) -> usize {
        self.shared.ctx.info.index
    }

    fn limits(&self) -> EngineLimits {
        EngineLimits { f64_tests: self.shared.ctx.info.shader_float64, on_host: self.shared.ctx.info.is_software }
    }

    fn check_usable(&self) -> Result<()> {
        self.shared.ctx.check_usable()
    }

    fn check_reported(&self) -> Result<()> {
        self.shared.ctx.check_validation()
    }

    fn build_meshes(&self, batch: MeshBatch) -> Result<Vec<Mesh>> {
        build_vulkan_meshes(&self.shared.ctx, batch)
    }

    fn build_spheres(&self, centers: Vec3s, radii: PerRay, options: BuildOptions) -> Result<Mesh> {
        build_vulkan_spheres(&self.shared.ctx, centers, radii, options)
    }

    fn build_scene(&self, instances: &[Instance], options: BuildOptions) -> Result<Scene> {
        build_vulkan_scene(&self.shared.ctx, instances, options)
    }

    fn idle_memory(&self) -> IdleMemory {
        self.shared.idle_memory()
    }

    fn release_idle_memory(&self) {
        self.shared.release_idle_memory()
    }

    fn chunk_rays(&self) -> usize {
        self.shared.chunk_rays()
    }

    fn set_chunk_rays(&self, rays: usize) -> Result<()> {
        self.shared.set_chunk_rays(rays)
    }

    fn staging_bytes(&self, rays: usize, exact: bool) -> usize {
        2 * Slot::host_bytes(self.shared.chunk_capacity(rays), exact)
    }

    fn last_profile(&self) -> TraceProfile {
        self.shared.last_profile()
    }

    fn keep_profile(&self, profile: TraceProfile) {
        self.shared.keep_profile(profile)
    }

    fn trace_rays(&self, batch: RayBatch, exact: bool, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        self.rays.run(batch, exact, sink, profile)
    }

    fn recycle_hits(&self, hits: Vec<ReferenceHit>) {
        self.all_hits.recycle(hits);
    }

    fn all_hit_columns(&self, batch: RayBatch, max_hits: usize, asked: &[AskedColumn]) -> Result<Option<HitColumns>> {
        let Some(fields) = gpu_column_fields(asked) else { return Ok(None) };
        let path = &self.all_hits;
        Ok(match batch.request.precision {
            Precision::Exact if one_part_meshes(batch.scene) => {
                Some(path.gpu_all_hit_columns::<ExactHit>(batch, max_hits, &fields)?)
            }
            Precision::Fast => Some(path.gpu_all_hit_columns::<FastHit>(batch, max_hits, &fields)?),
            _ => None,
        })
    }

    fn all_hits(&self, batch: RayBatch, max_hits: usize, host_bytes_per_hit: usize) -> Result<AllHits> {
        if batch.request.precision == Precision::Exact {
            return self.all_hits.gpu_all_hits::<ExactHit>(batch, max_hits, host_bytes_per_hit);
        }
        self.all_hits.gpu_all_hits::<FastHit>(batch, max_hits, host_bytes_per_hit)
    }

    fn closest_points(&self, batch: PointBatch, within: f64, precision: Precision, sink: &mut HitSink) -> Result<()> {
        self.points.run(batch, within, precision, sink)
    }

    fn contains(&self, batch: PointBatch, winding: bool, out: &mut [u8]) -> Result<()> {
        self.containment.run(batch, winding, out)
    }

    fn signed_distance(&self, batch: PointBatch, query: SignedDistance, out: &mut [f64]) -> Result<bool> {
        self.signed.run(batch, query, out)
    }

    fn contains_through_grid(
        &self,
        batch: PointBatch,
        grid: &Arc<InsideGrid>,
        winding: bool,
        out: &mut [u8],
    ) -> Result<bool> {
        if !grid_marks_on_device(self.shared.ctx.info.is_software) {
            return Ok(false);
        }
        self.inside_points.run(batch, grid, winding, out)
    }
}

/// Whether `contains` of host points reads the inside grid on the device (`InsidePointsPath`)
/// rather than marking the points on the host's cores (`grid_contains`): on a hardware GPU, not
/// on a software device (whose cores are the host's). VKRAY_GRID_MARKS: "host" or "device" asks
/// for either everywhere (to measure one against the other, and for the tests).
fn grid_marks_on_device(is_software: bool) -> bool {
    match std::env::var("VKRAY_GRID_MARKS").as_deref() {
        Ok("host") => false,
        Ok("device") => true,
        _ => !is_software,
    }
}

//! The CPU engine: the `Engine` seam over Embree on the host's cores, no Vulkan involved. Its
//! fast tier is Embree's robust f32 traversal (`cpu_rays`); its exact tier is the host's f64
//! tiers, so that its exact answers are the reference tier's, bit for bit.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::cpu_rays::{all_hits_fast, trace_fast};
use super::hit_filter::QueryContext;
use crate::embree::api::{
    EmbreeApi, DEVICE_PROPERTY_FILTER_FUNCTION_SUPPORTED, DEVICE_PROPERTY_POINT_GEOMETRY_SUPPORTED,
    DEVICE_PROPERTY_RAY_MASK_SUPPORTED,
};
use crate::embree::objects::EmbreeDevice;
use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::build_options::BuildOptions;
use crate::geometry::parallel::try_vec;
use crate::geometry::rays::PerRay;
use crate::geometry::reference::{Filter, ReferenceHit};
use crate::scene::{build_cpu_meshes, build_cpu_scene, build_cpu_spheres, CpuScene, Instance, Mesh, MeshBatch, Scene};
use crate::trace::engine::{Engine, EngineLimits};
use crate::trace::hit_fields::{hits_from_prims, Field, HitSink};
use crate::trace::host_tiers::{self, AllHits};
use crate::trace::idle::{Idle, IdleMemory, SpareRecords};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{PointBatch, Precision, Query, RayBatch, Request, SignedDistance};

/// Rays a chunk of the fast tier takes by default (the interrupt is asked between chunks): tens
/// of milliseconds on two cores, a few on sixteen.
const DEFAULT_CHUNK_RAYS: usize = 1 << 20;

/// The CPU engine: Embree's device and the engine's own settings.
pub struct CpuEngine {
    device: Arc<EmbreeDevice>,
    name: String,
    chunk_rays: AtomicUsize,
    profile: Mutex<TraceProfile>,
    /// Rays a packet of the fast tier's plain closest hits and occlusion takes: Embree's widest
    /// native packet on this CPU (16 with AVX-512, 8 with AVX2; 1: one ray at a time).
    packet_width: usize,
    /// The last all-hits answer's records, for the next to fill.
    spare_records: SpareRecords,
}

impl CpuEngine {
    /// Opens Embree, loaded from the first of `places` that has it (the wheel's copy), else from
    /// the system's library path.
    pub fn new(places: &[PathBuf]) -> Result<CpuEngine> {
        let device = EmbreeDevice::new(EmbreeApi::load(places)?)?;
        for (property, what) in [
            (DEVICE_PROPERTY_RAY_MASK_SUPPORTED, "ray masks"),
            (DEVICE_PROPERTY_FILTER_FUNCTION_SUPPORTED, "filter functions"),
            (DEVICE_PROPERTY_POINT_GEOMETRY_SUPPORTED, "point geometry"),
        ] {
            if !device.has(property) {
                return Err(Error::NoDevice(format!("the Embree found was built without {what}, which vkray needs")));
            }
        }
        let v = device.version;
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let name = format!("CPU ({cores} cores, Embree {}.{}.{})", v / 10000, v / 100 % 100, v % 100);
        let packet_width = device.packet_width();
        let chunk_rays = AtomicUsize::new(DEFAULT_CHUNK_RAYS);
        let spare_records = SpareRecords::default();
        Ok(CpuEngine { device, name, chunk_rays, profile: Default::default(), packet_width, spare_records })
    }

    /// What a query of `request` on `scene` runs, as `Scene.explain` shows it: its stages, and the
    /// effects the fast tier's filter handles (none: Embree's plain traversal, no filter).
    pub fn explain(&self, scene: &Scene, request: Request) -> (Vec<&'static str>, Vec<&'static str>) {
        if matches!(request.precision, Precision::Exact | Precision::Reference) {
            return (vec!["host: f64 watertight test on all CPU cores"], Vec::new());
        }
        let every = matches!(request.query, Query::Count | Query::All | Query::Transmit);
        let threshold = if request.query == Query::Transmit { 0.0 } else { request.opacity_threshold };
        let effects = QueryContext::new(scene, request.cull, threshold, every).effects();
        let mut stages = vec!["host: Embree's robust f32 traversal on all CPU cores"];
        if request.precision == Precision::Refined {
            stages.push("host: f64 watertight test of each hit");
        }
        (stages, effects)
    }

    /// Embree's version (40400 for 4.4.0).
    pub fn embree_version(&self) -> u32 {
        self.device.version
    }

    /// Keeps the profile of a query of `items` rays or points that ran on the host since `started`.
    fn keep_host_profile(&self, items: usize, started: Instant) {
        let seconds = started.elapsed().as_secs_f64();
        let threads = rayon::current_num_threads();
        self.keep_profile(TraceProfile {
            rays: items,
            total: seconds,
            host_f64: seconds,
            host_threads: threads,
            ..Default::default()
        });
    }

    /// The exact tier: the host's f64 tiers.
    fn trace_exact(&self, batch: RayBatch, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        rays.check()?;
        let started = Instant::now();
        match request.query {
            Query::Closest | Query::Occluded => {
                let hit = sink.hit.take();
                let needs_prims = hit.is_some() && sink.field(Field::Prim).is_none();
                let mut prims =
                    if needs_prims { try_vec(4 * rays.len(), 0u8, "the hits' prim_id")? } else { Vec::new() };
                let mut work = HitSink::default();
                for (field, out) in sink.iter_mut() {
                    work.set(field, out);
                }
                if needs_prims {
                    work.set(Field::Prim, &mut prims);
                }
                let any = request.query == Query::Occluded;
                host_tiers::reference(scene, rays, request.filter(), any, &mut work, interrupt)?;
                if let Some(hit) = hit {
                    hits_from_prims(work.field(Field::Prim).expect("prims were asked for"), hit);
                }
            }
            Query::Count => {
                let out = sink.field_mut(Field::Prim).expect("a count writes prim_id");
                host_tiers::count_hits(scene, rays, request.filter(), bytemuck::cast_slice_mut(out), interrupt)?;
            }
            Query::Transmit => {
                let every = Filter { cull: request.cull, threshold: 0.0, contacts: false };
                let all = host_tiers::all_hits(scene, rays, every, usize::MAX, 0, interrupt)?;
                let out = sink.field_mut(Field::T).expect("transmittance writes t");
                host_tiers::transmittance(scene, &all, bytemuck::cast_slice_mut(out));
            }
            other => return Err(Error::Unsupported(format!("the CPU engine answers {other:?} through contains"))),
        }
        profile.host_f64 = started.elapsed().as_secs_f64();
        Ok(())
    }
}

impl Engine for CpuEngine {
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn index(&self) -> usize {
        0
    }

    fn limits(&self) -> EngineLimits {
        EngineLimits { f64_tests: true, on_host: true }
    }

    fn check_usable(&self) -> Result<()> {
        Ok(())
    }

    fn check_reported(&self) -> Result<()> {
        self.device.check("during the last query")
    }

    fn build_meshes(&self, batch: MeshBatch) -> Result<Vec<Mesh>> {
        build_cpu_meshes(&self.device, batch)
    }

    fn build_spheres(&self, centers: Vec3s, radii: PerRay, options: BuildOptions) -> Result<Mesh> {
        build_cpu_spheres(&self.device, centers, radii, options)
    }

    fn build_scene(&self, instances: &[Instance], options: BuildOptions) -> Result<Scene> {
        build_cpu_scene(&self.device, instances, options)
    }

    fn idle_memory(&self) -> IdleMemory {
        self.spare_records.memory()
    }

    fn release_idle_memory(&self) {
        self.spare_records.clear()
    }

    fn chunk_rays(&self) -> usize {
        self.chunk_rays.load(Ordering::Relaxed)
    }

    fn set_chunk_rays(&self, rays: usize) -> Result<()> {
        if rays == 0 {
            return Err(invalid_value("chunk_rays must be at least 1"));
        }
        self.chunk_rays.store(rays, Ordering::Relaxed);
        Ok(())
    }

    fn staging_bytes(&self, rays: usize, _exact: bool) -> usize {
        // A chunk's packed rays and answers.
        rays.min(self.chunk_rays()) * (32 + 48)
    }

    fn last_profile(&self) -> TraceProfile {
        *self.profile.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn keep_profile(&self, profile: TraceProfile) {
        *self.profile.lock().unwrap_or_else(|e| e.into_inner()) = profile;
    }

    fn trace_rays(&self, batch: RayBatch, exact: bool, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        profile.host_threads = rayon::current_num_threads();
        if exact {
            return self.trace_exact(batch, sink, profile);
        }
        let widths = (self.chunk_rays(), self.packet_width);
        trace_fast(batch, CpuScene::of(batch.scene)?, sink, widths, profile)
    }

    fn recycle_hits(&self, hits: Vec<ReferenceHit>) {
        self.spare_records.keep(hits);
    }

    fn all_hits(&self, batch: RayBatch, max_hits: usize, host_bytes_per_hit: usize) -> Result<AllHits> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let started = Instant::now();
        let all = if request.precision == Precision::Exact {
            rays.check()?;
            host_tiers::all_hits(scene, rays, request.filter(), max_hits, host_bytes_per_hit, interrupt)?
        } else {
            let records = self.spare_records.take();
            all_hits_fast(
                batch,
                CpuScene::of(scene)?,
                (max_hits, host_bytes_per_hit),
                (self.chunk_rays(), self.packet_width),
                records,
            )?
        };
        self.keep_host_profile(rays.len(), started);
        Ok(all)
    }

    /// Closest points in f64 on every core (the reference tier's search) in every tier: the fast
    /// tier's answers are the nearest, not an f32 search's.
    fn closest_points(&self, batch: PointBatch, within: f64, _precision: Precision, sink: &mut HitSink) -> Result<()> {
        let PointBatch { scene, points, interrupt } = batch;
        let started = Instant::now();
        let hits = host_tiers::closest_points(scene, points, within, interrupt)?;
        self.keep_host_profile(points.rows(), started);
        host_tiers::write_closest(scene, sink, |i| host_tiers::closest_hit_record(scene, &hits[i]));
        Ok(())
    }

    fn contains(&self, batch: PointBatch, winding: bool, out: &mut [u8]) -> Result<()> {
        let PointBatch { scene, points, interrupt } = batch;
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let started = Instant::now();
        host_tiers::contains(scene, points, winding, out, interrupt)?;
        self.keep_host_profile(points.rows(), started);
        Ok(())
    }

    fn signed_distance(&self, _batch: PointBatch, _query: SignedDistance, _out: &mut [f64]) -> Result<bool> {
        Ok(false)
    }
}

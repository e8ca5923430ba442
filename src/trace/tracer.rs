//! The tracer: checks a query, picks its path (GPU traversal, GPU exact test, host refinement,
//! CPU reference) and hands the rays to it. Staging, variants and the chunk loop live beside it.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use super::chunks::GpuJob;
use super::closest::{points_as_they_come, points_in_grid_order, ORDER_MIN_POINTS};
use super::fields::{hits_from_prims, position_bytes_per_ray, Field, HitSink, FIELDS};
use super::idle::IdleMemory;
use super::profile::TraceProfile;
use super::request::{Crossings, Precision, Query, Request, SignedDistance, DEFAULT_THRESHOLD};
use super::staging::SlotPool;
use super::tiers;
use super::variants::{
    ray_flag_names, ray_flags, ray_source, Stage, Variant, VariantKey, Variants, RAYS_FROM_BUFFER, RAYS_FROM_SENSOR,
};
use crate::error::{invalid_value, try_vec, Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::morton;
use crate::geometry::parallel::{self, OwnPool};
use crate::geometry::rays::{RayLayout, Rays};
use crate::gpu::context::{Backend, Context, Interrupt};
use crate::gpu::memory::Buffer;
use crate::gpu::records::{ExactHit, FastHit};
use crate::scene::{Scene, WindingCap};
use rayon::prelude::*;

/// Traces rays on one device; owns the pipeline variants and reusable staging. Any number of
/// threads may trace at once: no lock is held across a wait (each query owns its staging slots
/// and their timestamps; variants are compiled outside the cache's lock).
pub struct Tracer {
    pub(super) ctx: Arc<Context>,
    pub(super) variants: Variants,
    pub(super) slots: SlotPool,
    /// Closest points' pipelines and staging.
    pub(super) points: super::closest::PointPipelines,
    /// The pipelines that pack rays on the GPU, and their scratch.
    pub(super) packing: super::device_rays::PackPipelines,
    /// The CUDA device that is this device, and the GPU-resident path's idle leases.
    pub(super) cuda: super::cuda_rays::CudaState,
    /// Idle lists and records of the all-hits storing pass (see `all_hits`).
    pub(super) idle_lists: super::idle::IdlePool<super::chunks::ListBuffers>,
    /// Whether this driver runs the intersection shaders of each `Probe` path, once known.
    pub(super) probes: [OnceLock<bool>; 2],
    pub(super) last_profile: Mutex<TraceProfile>,
    /// Rays per chunk: bounds staging memory (two chunks in flight).
    chunk_rays: AtomicUsize,
    /// Whether queries on host arrays have the GPU pack their rays where they can
    /// (`device_rays::pack_on_gpu_by_default`).
    pub(super) pack_on_gpu: bool,
    /// Threads of this device's own for its queries' host passes (`set_host_threads`).
    host_pool: Mutex<Option<Arc<OwnPool>>>,
    /// Whether host-packed f32 rays of the common shape take the leaner layouts
    /// (`Rays::compact_layout`); `VKRAY_PACK=full` keeps the full one (for measuring).
    pack_compact: bool,
}

/// What `Tracer::explain` tells of a variant.
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

/// Default rays per chunk: CPU devices gain nothing from big chunks (and a chunk is what Ctrl-C
/// waits for); GPUs amortize each submit.
fn default_chunk_rays(ctx: &Context) -> usize {
    if ctx.unified_memory {
        1 << 20
    } else {
        1 << 22
    }
}

impl Tracer {
    pub fn new(ctx: &Arc<Context>) -> Result<Tracer> {
        Ok(Tracer {
            ctx: ctx.clone(),
            variants: Variants::new(ctx)?,
            slots: SlotPool::new(ctx),
            points: super::closest::PointPipelines::new(ctx)?,
            packing: super::device_rays::PackPipelines::new(ctx)?,
            cuda: Default::default(),
            idle_lists: super::idle::IdlePool::new(super::all_hits::IDLE_LISTS.0, super::all_hits::IDLE_LISTS.1),
            probes: [OnceLock::new(), OnceLock::new()],
            last_profile: Mutex::new(TraceProfile::default()),
            chunk_rays: AtomicUsize::new(default_chunk_rays(ctx)),
            pack_on_gpu: super::device_rays::pack_on_gpu_by_default(ctx),
            host_pool: Mutex::new(None),
            pack_compact: std::env::var("VKRAY_PACK").as_deref() != Ok("full"),
        })
    }

    /// The device's name, for messages.
    pub fn device_name(&self) -> &str {
        &self.ctx.info.name
    }

    /// Where the time went in this device's last trace (of any thread).
    pub fn last_profile(&self) -> TraceProfile {
        *self.last_profile.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps a finished trace's profile as the device's last, with the threads its host passes
    /// had.
    pub(super) fn keep_profile(&self, mut profile: TraceProfile) {
        profile.host_threads = parallel::install(rayon::current_num_threads);
        *self.last_profile.lock().unwrap_or_else(|e| e.into_inner()) = profile;
    }

    /// The staging, scratch and leases this device keeps idle between queries (as many as its
    /// queries used at once), and how many its queries had to make.
    pub fn idle_memory(&self) -> IdleMemory {
        self.slots.memory()
            + self.points.idle_memory()
            + self.packing.idle_memory()
            + self.idle_lists.memory()
            + self.idle_leases()
    }

    /// `make` (an allocation for a query), tried once more after freeing every idle pool's
    /// memory where it ran out: what the pools keep may be what it needs. No lock may be held
    /// (idle CUDA leases wait for their streams as they go).
    pub(super) fn with_memory<T>(&self, mut make: impl FnMut() -> Result<T>) -> Result<T> {
        match make() {
            Err(Error::OutOfMemory(_)) => {
                self.release_idle_memory();
                make()
            }
            made => made,
        }
    }

    /// Frees what `idle_memory` counts; later queries make what they need again.
    pub fn release_idle_memory(&self) {
        self.slots.clear();
        self.points.release_idle();
        self.packing.release_idle();
        self.idle_lists.clear();
        self.release_idle_leases();
    }

    /// Rays per chunk: staging holds two chunks of rays and hits (72 bytes a ray each).
    pub fn chunk_rays(&self) -> usize {
        self.chunk_rays.load(Ordering::Relaxed)
    }

    pub fn set_chunk_rays(&self, rays: usize) -> Result<()> {
        if rays == 0 {
            return Err(invalid_value("chunk_rays must be at least 1"));
        }
        self.chunk_rays.store(rays, Ordering::Relaxed);
        Ok(())
    }

    /// How many threads of its own this device's host passes run on; `None`: the process's
    /// shared pool, on every core.
    pub fn host_threads(&self) -> Option<usize> {
        self.host_pool.lock().unwrap_or_else(|e| e.into_inner()).as_ref().map(|own| own.threads())
    }

    /// Gives this device `threads` threads of its own for its queries' host passes (packing
    /// rays, copying hits out), or (`None`) hands them back to the shared pool. Devices that
    /// trace at once (a `DeviceGroup`'s) each on cores of their own run their passes side by
    /// side, where in one pool they queue behind each other. Queries under way keep theirs.
    pub fn set_host_threads(&self, threads: Option<usize>) -> Result<()> {
        let pool = match threads {
            Some(0) => return Err(invalid_value("host_threads must be at least 1 (or None: every core)")),
            Some(n) => {
                let name = format!("vkray-device{}", self.ctx.info.index);
                Some(Arc::new(OwnPool::new(n, &name).map_err(Error::Internal)?))
            }
            None => None,
        };
        // Started outside the lock; the old pool ends when the last query using it does.
        let old = std::mem::replace(&mut *self.host_pool.lock().unwrap_or_else(|e| e.into_inner()), pool);
        drop(old);
        Ok(())
    }

    /// Runs `work` (a query on this device) on this thread, its host passes on the device's own
    /// threads if it has them (`set_host_threads`).
    pub fn on_host_threads<R>(&self, work: impl FnOnce() -> R) -> R {
        let pool = self.host_pool.lock().unwrap_or_else(|e| e.into_inner()).clone();
        parallel::with_pool(pool.as_deref(), work)
    }

    /// Most rays one dispatch may cover on this device.
    pub(super) fn max_dispatch_rays(&self) -> usize {
        let limits = &self.ctx.limits;
        match self.ctx.backend {
            Backend::RayQuery => limits.max_compute_work_group_count[0] as usize * self.variants.local_size as usize,
            Backend::Pipeline => (limits.max_ray_dispatch_invocation_count as usize)
                .min(limits.max_compute_work_group_count[0] as usize * limits.max_compute_work_group_size[0] as usize),
        }
    }

    /// Rays per chunk for a query of `rays` rays.
    pub fn chunk_capacity(&self, rays: usize) -> usize {
        self.chunk_rays().min(self.max_dispatch_rays()).min(rays).max(1)
    }

    /// Rays per chunk of a query the host packs: `chunk_capacity`, but on a discrete GPU a batch
    /// of at least 2 × `OVERLAP_MIN_RAYS` goes in two chunks at least, so that the host's passes
    /// over one overlap the copies and the trace of the other (1M rays on an H100: 3–19% faster,
    /// docs/benchmarks.md, issue 14). Smaller batches take longer in pieces than whole.
    fn host_chunk_capacity(&self, rays: usize) -> usize {
        const OVERLAP_MIN_RAYS: usize = 1 << 18;
        let capacity = self.chunk_capacity(rays);
        if self.ctx.unified_memory || rays < 2 * OVERLAP_MIN_RAYS {
            return capacity;
        }
        capacity.min(rays.div_ceil(2))
    }

    /// Host bytes a query needs besides its inputs and outputs: staging, temporary hit fields,
    /// and the host tiers' per-ray records; for checking a query fits before it starts.
    pub fn working_bytes(&self, request: Request, rays: usize) -> usize {
        let exact = request.precision == Precision::Exact;
        let staging = 2 * super::staging::Slot::host_bytes(self.chunk_capacity(rays), exact);
        let host_tier = match request.precision {
            // Hits (40 bytes) and re-trace flags per ray, plus temporary ids and barycentrics.
            Precision::Refined => 40 + 1 + 12 + 16,
            Precision::Reference => 40,
            _ => 0,
        };
        staging + rays * host_tier
    }

    /// Traces `rays` against `scene` at `precision`, writing the fields `sink` asks for (`t` and
    /// `uv` as f64 in the f64 tiers). Each chunk's rays are checked as they are packed; an invalid
    /// ray stops the trace with an error naming it (chunks already in flight finish first, and
    /// what they wrote is not the caller's to read). `interrupt` is asked between chunks.
    ///
    /// The meshes of `scene` are held against `Mesh::update` for the whole trace.
    pub fn trace(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let started = Instant::now();
        self.ctx.check_usable()?;
        check_request(scene, rays, request, sink)?;
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        self.trace_held(scene, rays, request, sink, interrupt, started)
    }

    /// `trace` once its request is checked and the scene's meshes are held.
    pub(super) fn trace_held(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
        started: Instant,
    ) -> Result<()> {
        let mut profile = TraceProfile { rays: rays.len(), ..Default::default() };
        let position = sink.position.take();
        let mut hit = sink.hit.take();
        if rays.is_empty() || (sink.outputs() == 0 && position.is_none() && hit.is_none()) {
            return Ok(());
        }
        let wide = request.precision.is_f64();
        let refine = request.precision == Precision::Refined && request.query == Query::Closest;
        // The host needs the hit triangles (and barycentrics, or t on spheres) of rays whose
        // caller did not ask for them; `hit`, where the host decides the hits (the reference
        // tier, or refining, which may turn a hit into a miss), the final prim_id.
        let hit_from_host = request.precision == Precision::Reference || refine;
        let mut needed = Vec::new();
        if hit.is_some() && hit_from_host {
            needed.push(Field::Prim);
        }
        if refine || position.is_some() {
            needed.extend([Field::Prim, Field::Instance, Field::Geometry]);
        }
        if position.is_some() {
            needed.push(Field::Uv);
            if scene.has_spheres() {
                needed.push(Field::T);
            }
        }
        let mut temps = Vec::new();
        for field in needed.iter().filter(|f| sink.field(**f).is_none()) {
            temps.push((*field, try_vec(rays.len() * field.bytes_per_ray(wide), 0u8, "a temporary hit field")?));
        }
        let mut work = HitSink::default();
        for (field, out) in sink.iter_mut() {
            work.set(field, out);
        }
        for (field, temp) in temps.iter_mut() {
            work.set(*field, temp);
        }
        if !hit_from_host {
            // The GPU tiers' chunk loop writes it as it copies the hits out.
            work.hit = hit.take();
        }
        self.run_tier(scene, rays, request, &mut work, interrupt, &mut profile)?;
        if let Some(out) = hit {
            hits_from_prims(work.field(Field::Prim).unwrap_or_default(), out);
        }
        if let Some(out) = position {
            let hits = tiers::HitTriangles {
                prim: work.field(Field::Prim).unwrap_or_default(),
                instance: work.field(Field::Instance).unwrap_or_default(),
                geometry: work.field(Field::Geometry).unwrap_or_default(),
                t: work.field(Field::T).unwrap_or_default(),
                uv: work.field(Field::Uv).unwrap_or_default(),
                wide,
            };
            tiers::positions(scene, rays, &hits, out);
        }
        profile.total = started.elapsed().as_secs_f64();
        self.keep_profile(profile);
        self.ctx.check_validation()
    }

    /// Runs the query in its tier, writing every field `work` asks for.
    fn run_tier(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        work: &mut HitSink,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let refine = request.precision == Precision::Refined && request.query == Query::Closest;
        if request.query == Query::Transmit && !scene.has_opacity() {
            // Where every triangle is opaque, light is kept (1) or not (0): an occlusion query.
            return self.transmit_by_occlusion(scene, rays, request, work, interrupt, profile);
        }
        if request.query == Query::Transmit && !matches!(request.precision, Precision::Fast | Precision::Exact) {
            // The host's tiers multiply over the f64 hits of every crossing.
            let every = Request { query: Query::All, opacity_threshold: 0.0, ..request };
            let started = Instant::now();
            let all = self.trace_all(scene, rays, every, usize::MAX, 0, interrupt)?;
            let out: &mut [f64] = bytemuck::cast_slice_mut(work.field_mut(Field::T).expect("transmittance writes t"));
            tiers::transmittance(scene, &all, out);
            if request.precision == Precision::Refined {
                // The GPU's all-hits passes left their times in the last profile.
                *profile = TraceProfile { rays: rays.len(), ..self.last_profile() };
            }
            let gpu = profile.gpu_upload.unwrap_or(0.0) + profile.gpu_trace.unwrap_or(0.0);
            profile.host_f64 = (started.elapsed().as_secs_f64() - gpu).max(0.0);
            return Ok(());
        }
        match request.precision {
            Precision::Exact => {
                self.check_paths(scene, true)?;
                self.run_gpu(scene, rays, request, true, work, interrupt, profile)
            }
            Precision::Refined if refine => {
                // The GPU finds which triangle; the host recomputes where, in f64.
                let mut host_fields = HitSink::default();
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = work.take(field) {
                        host_fields.set(field, out);
                    }
                }
                self.check_paths(scene, false)?;
                self.run_gpu(scene, rays, request, false, work, interrupt, profile)?;
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = host_fields.take(field) {
                        work.set(field, out);
                    }
                }
                let host = Instant::now();
                tiers::refine(scene, rays, request.filter(), work, interrupt)?;
                profile.host_f64 = host.elapsed().as_secs_f64();
                Ok(())
            }
            Precision::Fast | Precision::Refined => {
                self.check_paths(scene, false)?;
                self.run_gpu(scene, rays, request, false, work, interrupt, profile)
            }
            Precision::Reference => {
                rays.check()?;
                let host = Instant::now();
                tiers::reference(scene, rays, request.filter(), request.query == Query::Occluded, work, interrupt)?;
                profile.host_f64 = host.elapsed().as_secs_f64();
                Ok(())
            }
        }
    }

    /// Transmittance in a scene without opacity: 1 where a ray is not occluded, else 0.
    fn transmit_by_occlusion(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        work: &mut HitSink,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let mut blocked = try_vec(rays.len(), 0i32, "the rays' occlusion")?;
        let mut sink = HitSink::default();
        sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut blocked));
        self.run_tier(scene, rays, Request { query: Query::Occluded, ..request }, &mut sink, interrupt, profile)?;
        let out = work.field_mut(Field::T).expect("transmittance writes t");
        let left = |b: &i32| if *b >= 0 { 0.0 } else { 1.0 };
        parallel::install(|| {
            if request.precision.is_f64() {
                let out: &mut [f64] = bytemuck::cast_slice_mut(out);
                out.par_iter_mut().zip(&blocked).with_min_len(4096).for_each(|(t, b)| *t = left(b));
            } else {
                let out: &mut [f32] = bytemuck::cast_slice_mut(out);
                out.par_iter_mut().zip(&blocked).with_min_len(4096).for_each(|(t, b)| *t = left(b) as f32);
            }
        });
        Ok(())
    }

    /// Fails where this driver does not run the intersection shaders a GPU query on `scene`
    /// needs (`exact`: the f64 test through per-triangle boxes; spheres).
    pub(super) fn check_paths(&self, scene: &Scene, exact: bool) -> Result<()> {
        if exact {
            self.check_intersection_shaders(super::probe::Probe::Exact)?;
        }
        if scene.has_spheres() {
            self.check_intersection_shaders(super::probe::Probe::Spheres)?;
        }
        Ok(())
    }

    /// The GPU's part of a query: traversal in f32 (`exact`: through the scene's per-triangle
    /// boxes, each candidate decided by the f64 test).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run_gpu(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        exact: bool,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        // The GPU packing path writes fields into the caller's arrays itself: not `hit`.
        let packs_on_gpu = !exact && sink.hit.is_none();
        if packs_on_gpu && self.trace_arrays_packed_on_gpu(scene, rays, request, sink, interrupt, profile)?.is_some() {
            return Ok(());
        }
        let outputs = sink.outputs();
        // Before any exact variant: this fails on devices without shaderFloat64 (no exact modules).
        let exact_scene = if exact { Some(scene.exact()?) } else { None };
        let all_hits = request.query.counts_hits();
        let (variant, sensor) = self.gpu_variant(scene, rays, request, exact, outputs)?;
        let capacity = self.host_chunk_capacity(rays.len());
        let frame = scene.frame();
        let sensor = sensor.as_ref();
        let cap = match request.query {
            Query::Winding => Some(scene.winding_cap()?.ok_or_else(|| {
                invalid_value("a winding query needs a scene of one instance whose mesh has a cap (WindingCap)")
            })?),
            _ => None,
        };
        let (exact, cap) = (exact_scene.as_deref(), cap.as_deref());
        let compact_variant =
            self.compact_variant(scene, rays, request, outputs, exact_scene.is_some() || sensor.is_some())?;
        let compact = compact_variant.as_ref().map(|(layout, variant)| (*layout, &**variant));
        let compact_refused = Default::default();
        // Taken last: nothing fails between here and their return.
        let mut slots = self.with_memory(|| self.slots.take(capacity, exact.is_some()))?;
        let job = GpuJob {
            scene,
            exact,
            rays,
            variant: &variant,
            compact,
            compact_refused,
            outputs,
            frame,
            all_hits,
            sensor,
            cap,
        };
        let result = self.trace_chunks(&job, sink, &mut slots, capacity, interrupt, profile);
        self.slots.give_back(slots);
        result
    }
}

impl Tracer {
    /// The leaner layout a GPU query's host-packed f32 rays take, if any (rays of the common
    /// shape; not the exact tier's f64 rays, nor rays a sensor generates on the GPU), and the
    /// variant of `request` that reads it.
    pub(super) fn compact_variant(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        outputs: u32,
        exact_or_sensor: bool,
    ) -> Result<Option<(RayLayout, Arc<Variant>)>> {
        if exact_or_sensor || !self.pack_compact {
            return Ok(None);
        }
        let Some(layout) = rays.compact_layout(&scene.frame()) else { return Ok(None) };
        let key = self.variant_key(scene, request, false, outputs, false);
        Ok(Some((layout, self.variants.get(VariantKey { ray_source: ray_source(layout), ..key })?)))
    }

    /// The variant a GPU query runs (see `VariantKey`), and the sensor record its shaders
    /// generate the rays from where they can (rays of a sensor none of whose rays the host would
    /// advance).
    pub(super) fn gpu_variant(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        exact: bool,
        outputs: u32,
    ) -> Result<(Arc<Variant>, Option<Buffer>)> {
        let frame = scene.frame();
        let sensor = rays.generated_on_gpu(&frame);
        let variant = self.variants.get(self.variant_key(scene, request, exact, outputs, sensor.is_some()))?;
        let sensor = sensor.map(|s| super::sensor::upload(&self.ctx, s, &frame, exact)).transpose()?;
        Ok((variant, sensor))
    }

    /// What the variant of a GPU query on `scene` is specialized to: a function of what the
    /// scene holds (opacity, spheres, non-opaque instances) and what the query asks.
    pub fn variant_key(&self, scene: &Scene, request: Request, exact: bool, outputs: u32, sensor: bool) -> VariantKey {
        let spheres = scene.has_spheres();
        let query = request.query;
        VariantKey {
            outputs,
            ray_flags: ray_flags(query, request.cull, self.ctx.backend, exact, scene.all_opaque(), spheres),
            exact,
            spheres,
            query: query.shader_query(),
            closed_edges: request.contacts,
            opacity: scene.has_opacity() && !exact,
            threshold_bits: if scene.has_opacity() { request.opacity_threshold } else { DEFAULT_THRESHOLD }.to_bits(),
            ray_source: if sensor { RAYS_FROM_SENSOR } else { RAYS_FROM_BUFFER },
        }
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
        let key = self.variant_key(scene, request, exact, outputs, sensor);
        let backend = self.ctx.backend;
        Some(Explanation {
            stages: key.stages(backend).into_iter().map(Stage::name).collect(),
            branches: if backend == Backend::RayQuery { key.candidate_branches() } else { Vec::new() },
            ray_flags: ray_flag_names(key.ray_flags),
            pipeline_skips: match (backend, self.ctx.limits.ray_traversal_primitive_culling, exact, key.spheres) {
                (Backend::Pipeline, true, false, false) => vec!["SkipAABBs"],
                (Backend::Pipeline, true, true, _) => vec!["SkipTriangles"],
                _ => Vec::new(),
            },
            key,
        })
    }

    /// Every hit of every ray (the nearest `max_hits` of each), for `write_all`: on the GPU in the
    /// fast and exact tiers (the refined tier re-intersects the fast tier's hits in f64), on the
    /// CPU in the reference tier. `host_bytes_per_hit`: what the caller will need per hit, for
    /// refusing a result that cannot fit before it is stored.
    pub fn trace_all(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        max_hits: usize,
        host_bytes_per_hit: usize,
        interrupt: &dyn Interrupt,
    ) -> Result<tiers::AllHits> {
        self.check_every_hit_query(scene, "intersect_all")?;
        check_contacts(request)?;
        match request.precision {
            Precision::Exact => {
                self.check_paths(scene, true)?;
                let stored =
                    self.gpu_all_hits::<ExactHit>(scene, rays, request, max_hits, host_bytes_per_hit, interrupt)?;
                Ok(stored.into_all_hits())
            }
            Precision::Fast | Precision::Refined => {
                let stored =
                    self.gpu_all_hits::<FastHit>(scene, rays, request, max_hits, host_bytes_per_hit, interrupt)?;
                let fast = stored.into_all_hits(scene)?;
                if request.precision == Precision::Fast {
                    return Ok(fast);
                }
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                tiers::refine_all(scene, rays, request.filter(), max_hits, &fast, interrupt)
            }
            Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                rays.check()?;
                tiers::all_hits(scene, rays, request.filter(), max_hits, host_bytes_per_hit, interrupt)
            }
        }
    }

    /// Writes the fields `sink` asks for, one entry per hit of `trace_all` (on the same scene).
    pub fn write_all(&self, scene: &Scene, all: &tiers::AllHits, sink: &mut HitSink) {
        tiers::write_all_hits(scene, all, sink);
    }

    /// The number of hits of each ray, into `out`: as `trace_all` finds them, without storing
    /// them (but in the refined tier, whose hits must be re-intersected on the host).
    pub fn count(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        out: &mut [i32],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if out.len() != rays.len() {
            return Err(invalid_value(format!("count's output has {} entries for {} rays", out.len(), rays.len())));
        }
        self.check_every_hit_query(scene, "count")?;
        match request.precision {
            Precision::Fast | Precision::Exact => {
                let mut sink = HitSink::default();
                sink.set(Field::Prim, bytemuck::cast_slice_mut(out));
                self.trace(scene, rays, Request { query: Query::Count, ..request }, &mut sink, interrupt)
            }
            Precision::Refined => {
                let all = self.trace_all(scene, rays, request, usize::MAX, 0, interrupt)?;
                for (count, pair) in out.iter_mut().zip(all.offsets.windows(2)) {
                    *count = (pair[1] - pair[0]) as i32;
                }
                Ok(())
            }
            Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                rays.check()?;
                tiers::count_hits(scene, rays, request.filter(), out, interrupt)
            }
        }
    }

    /// The surface point nearest to each of `points` within `max_distance`, its fields written
    /// into `sink` (`t`: the distance; f64 in the f64 tiers). Tiers: `reference` (the CPU, f64).
    pub fn closest_points(
        &self,
        scene: &Scene,
        points: Vec3s,
        max_distance: f64,
        precision: Precision,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        self.check_point_query(scene, points, max_distance, "closest_points")?;
        if sink.hit.is_some() {
            return Err(invalid_value("hit (whether a ray hit anything) is not an output of closest_points"));
        }
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let hits =
            match precision {
                Precision::Reference => tiers::closest_points(scene, points, max_distance, interrupt)?,
                Precision::Exact | Precision::Fast => {
                    return self.gpu_closest_points(scene, points, max_distance, precision, sink, interrupt);
                }
                Precision::Refined => return Err(Error::Unsupported(
                    "closest points are answered at precision='fast' (f32 on the GPU), 'exact' (f64 on the GPU) or \
                     'reference' (f64 on the CPU): 'refined' would be 'exact'"
                        .into(),
                )),
            };
        tiers::write_closest(scene, sink, |i| tiers::closest_hit_record(scene, &hits[i]));
        Ok(())
    }

    /// The checks every query of distances makes: the scene's, `max_distance`, finite points.
    fn check_point_query(&self, scene: &Scene, points: Vec3s, max_distance: f64, query: &str) -> Result<()> {
        self.check_every_hit_query(scene, query)?;
        if max_distance.is_nan() || max_distance < 0.0 {
            return Err(invalid_value(format!("max_distance must be >= 0 (or inf), got {max_distance}")));
        }
        crate::geometry::arrays::check_points("points", points)
    }

    /// The distance from each point to the nearest surface within `max_distance` (`closest_points`
    /// at `precision`), negative where `contains` (at `contains_precision`, by winding number or
    /// parity) puts the point inside, into `out` (f64 a point).
    pub fn signed_distance(
        &self,
        scene: &Scene,
        points: Vec3s,
        query: SignedDistance,
        out: &mut [f64],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let SignedDistance { max_distance, precision, contains_precision, winding } = query;
        if out.len() != points.rows() {
            return Err(invalid_value(format!(
                "signed_distance's output has {} entries for {} points",
                out.len(),
                points.rows()
            )));
        }
        self.check_point_query(scene, points, max_distance, "signed_distance")?;
        if self.signed_distance_in_one_pass(scene, points, query, out, interrupt)? {
            return Ok(());
        }
        let mut sink = HitSink::default();
        sink.set(Field::T, bytemuck::cast_slice_mut(out));
        self.closest_points(scene, points, max_distance, precision, &mut sink, interrupt)?;
        let mut inside = try_vec(points.rows(), 0u8, "the points inside")?;
        self.contains(scene, points, contains_precision, winding, &mut inside, interrupt)?;
        parallel::install(|| {
            out.par_iter_mut().zip(&inside).with_min_len(4096).filter(|(_, &inside)| inside != 0).for_each(|(d, _)| {
                *d = -*d;
            })
        });
        Ok(())
    }

    /// Whether each point is inside any instance (1) or not (0), into `out`: by parity (the
    /// caller checked that every mesh is closed) or by winding number.
    pub fn contains(
        &self,
        scene: &Scene,
        points: Vec3s,
        precision: Precision,
        winding: bool,
        out: &mut [u8],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if out.len() != points.rows() {
            return Err(invalid_value(format!(
                "contains' output has {} entries for {} points",
                out.len(),
                points.rows()
            )));
        }
        if let Some(i) = (0..points.rows()).find(|&i| !points.row_f64(i).iter().all(|c| c.is_finite())) {
            return Err(invalid_value(format!("points row {i} is not finite: {:?}", points.row_f64(i))));
        }
        self.check_every_hit_query(scene, "contains")?;
        if out.is_empty() {
            return Ok(());
        }
        // A point beyond f32's range (which rays cannot start from) outside the scene is outside.
        let moved = crate::geometry::rays::far_points_moved_in(points, scene.bounds(), scene.center)?;
        let points = moved.as_deref().map_or(points, Vec3s::F64);
        match precision {
            Precision::Exact if !winding => self.contains_by_gpu_rays(scene, points, None, out, interrupt),
            Precision::Exact if self.ctx.info.shader_float64 => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                match scene.winding_cap()? {
                    Some(cap) => self.contains_by_gpu_rays(scene, points, Some(&cap), out, interrupt),
                    None => self.gpu_contains_by_winding(scene, points, out, interrupt),
                }
            }
            // Without f64 shaders, the exact tier's winding numbers are the reference tier's.
            Precision::Exact | Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                tiers::contains(scene, points, winding, out, interrupt)
            }
            Precision::Fast | Precision::Refined => Err(Error::Unsupported(
                "contains answers at precision='exact' (the f64 test on the GPU: each crossing counted once) or \
                 'reference' (on the CPU); the f32 tiers could count a crossing at an edge twice or not at all"
                    .into(),
            )),
        }
    }

    /// `contains_by_gpu_crossings` with the rays of 4,096 points or more cast in grid order on a
    /// software device (`morton::point_order`: neighbouring invocations then cross the same
    /// nodes; lavapipe, 1M points: 140 -> 95 ms), each answer written to its point's own row. Not
    /// on a hardware GPU: there the sort, the gather and the scatter on the host (7–10 ms for 1M
    /// points on an H100's 16 cores) cost more than the trace gains (2–7 ms). VKRAY_POINT_ORDER:
    /// `input` casts them as they come everywhere, `grid` orders them everywhere.
    fn contains_by_gpu_rays(
        &self,
        scene: &Scene,
        points: Vec3s,
        cap: Option<&WindingCap>,
        out: &mut [u8],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let n = points.rows();
        let bounds = scene.bounds();
        let worth_it = self.ctx.info.is_software || points_in_grid_order();
        let ordered = n >= ORDER_MIN_POINTS && worth_it && !points_as_they_come();
        if !(ordered && bounds.min.is_finite() && bounds.max.is_finite()) {
            return self.contains_by_gpu_crossings(scene, points, cap, out, interrupt);
        }
        let started = Instant::now();
        let order = morton::point_order(points, bounds.min + scene.center, bounds.max + scene.center);
        let mut sorted = try_vec(3 * n, 0.0f64, "the points in grid order")?;
        let mut inside = try_vec(n, 0u8, "contains in grid order")?;
        parallel::install(|| {
            sorted.par_chunks_exact_mut(3).zip(order.as_slice()).with_min_len(4096).for_each(|(row, &i)| {
                row.copy_from_slice(&points.row_f64(i as usize));
            })
        });
        let sorting = started.elapsed();
        self.contains_by_gpu_crossings(scene, Vec3s::F64(&sorted), cap, &mut inside, interrupt)?;
        let scattering = Instant::now();
        order.scatter(&inside, out);
        let mut profile = self.last_profile.lock().unwrap_or_else(|e| e.into_inner());
        profile.order = (sorting + scattering.elapsed()).as_secs_f64();
        Ok(())
    }

    /// `contains` from one ray a point on the GPU, its crossings counted exactly: by parity
    /// (`cap` None: the caller checked that every mesh is closed), or by the winding number of
    /// the scene's one mesh through its `cap` (its signed crossings plus the cap's winding number).
    /// With one instance the GPU also tests whether the point lies on a surface (a ray cannot
    /// tell: its t there rounds to either side of 0). With several (parity only), the crossings
    /// are found with their instances (a parity each) and the CPU tells points on a surface.
    fn contains_by_gpu_crossings(
        &self,
        scene: &Scene,
        points: Vec3s,
        cap: Option<&WindingCap>,
        out: &mut [u8],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let direction = tiers::PARITY_DIRECTION.to_array();
        let rays = Rays {
            origins: points,
            directions: Vec3s::F64(&direction),
            tmin: crate::geometry::rays::PerRay::All(0.0),
            tmax: crate::geometry::rays::PerRay::All(f64::INFINITY),
            mask: crate::geometry::rays::Masks::All(0xFF),
            sensor: None,
        };
        // Every triangle counts, whatever its opacity: inside is a question of the surface.
        let request = Request {
            opacity_threshold: 0.0,
            ..Request::new(Query::Count, Precision::Exact, crate::trace::Cull::None)
        };
        self.check_paths(scene, true)?;
        let mut odd = try_vec(points.rows(), 0i32, "the crossings of contains")?;
        if let Some(cap) = cap {
            let mut cap_winding = try_vec(points.rows(), 0.0f64, "the cap's winding numbers")?;
            let mut sink = HitSink::default();
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut odd));
            sink.set(Field::T, bytemuck::cast_slice_mut(&mut cap_winding));
            self.trace(scene, &rays, Request { query: Query::Winding, ..request }, &mut sink, interrupt)?;
            return tiers::inside_by_crossings(scene, points, &odd, &cap_winding, cap.band(), out, interrupt);
        }
        if scene.placements.len() == 1 {
            let mut sink = HitSink::default();
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut odd));
            self.trace(scene, &rays, Request { query: Query::Parity, ..request }, &mut sink, interrupt)?;
            parallel::install(|| {
                out.par_iter_mut().zip(&odd).with_min_len(4096).for_each(|(inside, &count)| {
                    *inside = u8::from(tiers::inside_by_parity(Crossings(count)));
                })
            });
            return Ok(());
        }
        let all = self.gpu_all_hits::<ExactHit>(scene, &rays, request, usize::MAX, 0, interrupt)?.into_all_hits();
        for (odd, pair) in odd.iter_mut().zip(all.offsets.windows(2)) {
            *odd =
                i32::from(tiers::odd_crossings(&all.hits[pair[0] as usize..pair[1] as usize], scene.placements.len()));
        }
        let _in_use = scene.hold_meshes();
        tiers::inside_by_counts(scene, points, &odd, out, interrupt)
    }

    /// The queries that meet every hit (all hits, counts, contains) are for triangle meshes.
    fn check_every_hit_query(&self, scene: &Scene, query: &str) -> Result<()> {
        self.ctx.check_usable()?;
        if scene.has_spheres() {
            return Err(Error::Unsupported(format!("{query} is for triangle meshes: this scene holds spheres")));
        }
        Ok(())
    }
}

/// Contacts (closed triangles) are the exact tier's alone.
fn check_contacts(request: Request) -> Result<()> {
    if request.contacts && request.precision != Precision::Exact {
        return Err(Error::Unsupported("contacts are answered at precision='exact'".into()));
    }
    Ok(())
}

/// Checks what a query asks before any work: array sizes, fields the query can write, tiers the
/// scene can be traced in.
fn check_request(scene: &Scene, rays: &Rays, request: Request, sink: &HitSink) -> Result<()> {
    rays.check_shapes()?;
    check_contacts(request)?;
    let n = rays.len();
    let wide = request.precision.is_f64();
    for field in FIELDS {
        if let Some(out) = sink.field(field) {
            if out.len() != n * field.bytes_per_ray(wide) {
                return Err(invalid_value(format!("output for {} has {} bytes for {n} rays", field.name(), out.len())));
            }
        }
    }
    if let Some(out) = &sink.position {
        if out.len() != n * position_bytes_per_ray(wide) {
            return Err(invalid_value(format!("output for position has {} bytes for {n} rays", out.len())));
        }
    }
    if let Some(out) = &sink.hit {
        if out.len() != n {
            return Err(invalid_value(format!("output for hit has {} bytes for {n} rays", out.len())));
        }
        if !matches!(request.query, Query::Closest | Query::Occluded) {
            return Err(invalid_value("hit (whether a ray hit anything) is an output of closest and occluded queries"));
        }
    }
    // Occlusion stops at any hit, so it knows only whether there was one; a count writes the
    // number alone (in prim_id's place).
    let answerable = sink.outputs() & !Field::Prim.bit() == 0 && sink.position.is_none();
    if request.query == Query::Occluded && !answerable {
        return Err(invalid_value("an occlusion query writes prim_id alone (>= 0 where the ray is blocked)"));
    }
    let gpu_tier = matches!(request.precision, Precision::Fast | Precision::Exact);
    if request.query == Query::Count && (!answerable || !gpu_tier) {
        return Err(Error::Unsupported(
            "a count on the GPU is answered at precision='fast' or 'exact', into one int32 a ray".into(),
        ));
    }
    if request.query == Query::All {
        return Err(invalid_value("all hits are traced by Tracer::trace_all"));
    }
    if request.query == Query::Transmit {
        if sink.outputs() != Field::T.bit() || sink.position.is_some() {
            return Err(invalid_value("a transmittance query writes t alone (the light each ray keeps)"));
        }
        if scene.has_spheres() {
            return Err(Error::Unsupported("transmittance is for triangle meshes: this scene holds spheres".into()));
        }
    }
    if request.query == Query::Parity && (!answerable || request.precision != Precision::Exact) {
        return Err(invalid_value("a parity query is answered at precision='exact', into one int32 a ray"));
    }
    let crossings_and_t = sink.outputs() == Field::Prim.bit() | Field::T.bit() && sink.position.is_none();
    if request.query == Query::Winding && (!crossings_and_t || request.precision != Precision::Exact) {
        return Err(invalid_value(
            "a winding query is answered at precision='exact', into one int32 (prim_id) and one f64 (t) a ray",
        ));
    }
    if scene.has_spheres() && request.precision != Precision::Fast {
        return Err(Error::Unsupported(
            "scenes with spheres trace at precision='fast' (the f64 tiers are for triangle meshes)".into(),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::variants::*;
    use crate::gpu::context::Backend;
    use crate::gpu::records::Params;
    use crate::trace::request::{Cull, Query};

    #[test]
    fn params_fit_every_device_push_constants() {
        // Vulkan guarantees 128 bytes of push constants.
        assert!(std::mem::size_of::<Params>() <= 128);
    }

    #[test]
    fn occlusion_flags_terminate_on_first_hit() {
        for backend in [Backend::RayQuery, Backend::Pipeline] {
            for exact in [false, true] {
                let flags = |query| ray_flags(query, Cull::None, backend, exact, true, false);
                assert_ne!(flags(Query::Occluded) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
                assert_eq!(flags(Query::Closest) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
                // The exact tier's structures are all AABBs.
                assert_eq!(ray_flags(Query::Closest, Cull::None, backend, true, true, false) & RAY_FLAG_SKIP_AABBS, 0);
                // Spheres are boxes too.
                assert_eq!(ray_flags(Query::Closest, Cull::None, backend, false, true, true) & RAY_FLAG_SKIP_AABBS, 0);
            }
        }
        let pipeline = |query, cull, all_opaque| ray_flags(query, cull, Backend::Pipeline, false, all_opaque, false);
        assert_ne!(
            ray_flags(Query::Closest, Cull::None, Backend::RayQuery, false, true, false) & RAY_FLAG_SKIP_AABBS,
            0
        );
        assert_ne!(pipeline(Query::Occluded, Cull::None, true) & RAY_FLAG_SKIP_CLOSEST_HIT_SHADER, 0);
        assert_eq!(pipeline(Query::Closest, Cull::None, true) & RAY_FLAG_SKIP_AABBS, 0);
        // Non-opaque instances must not be culled; culling follows the query.
        assert_eq!(pipeline(Query::Closest, Cull::None, false) & RAY_FLAG_CULL_NO_OPAQUE, 0);
        assert_ne!(pipeline(Query::Closest, Cull::Back, true) & RAY_FLAG_CULL_BACK_FACING_TRIANGLES, 0);
        assert_ne!(pipeline(Query::Closest, Cull::Front, true) & RAY_FLAG_CULL_FRONT_FACING_TRIANGLES, 0);
    }
}

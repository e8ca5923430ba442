//! What the Vulkan engine's paths share, borrowed by each: the device, the pipeline variants,
//! the staging slots, the registry of every path's idle pool (for the memory retry), chunk sizing
//! and the device's last profile. No path state lives here.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use ash::vk;

use super::cap_winding::CapWinding;
use super::sensor_upload;
use super::staging::SlotPool;
use super::variants::{ray_flags, ray_source, Variant, VariantKey, Variants, RAYS_FROM_BUFFER, RAYS_FROM_SENSOR};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::parallel;
use crate::geometry::rays::{RayLayout, Rays};
use crate::gpu::context::{Backend, Context};
use crate::gpu::memory::Buffer;
use crate::gpu::records::Params;
use crate::scene::Scene;
use crate::trace::idle::{Idle, IdleMemory};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Request, DEFAULT_THRESHOLD};

/// The one value every path of the Vulkan engine borrows. Any number of threads may trace at
/// once: no lock is held across a wait (each query owns its staging slots and their timestamps;
/// variants are compiled outside the cache's lock).
pub struct Shared {
    pub ctx: Arc<Context>,
    pub variants: Variants,
    /// cap_winding.comp: the caps' solid angles of winding queries' rays.
    pub cap_winding: CapWinding,
    pub slots: SlotPool,
    /// Every path's idle pool, in the order the paths were made (summed and freed together).
    pools: Vec<Arc<dyn Idle>>,
    last_profile: Mutex<TraceProfile>,
    /// Rays per chunk: bounds staging memory (two chunks in flight).
    chunk_rays: AtomicUsize,
    /// Whether host-packed f32 rays of the common shape take the leaner layouts
    /// (`Rays::compact_layout`); `VKRAY_PACK=full` keeps the full one (for measuring).
    pack_compact: bool,
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

impl Shared {
    /// The shared value of a device whose paths keep their idle resources in `pools`.
    pub fn new(ctx: &Arc<Context>, pools: Vec<Arc<dyn Idle>>) -> Result<Shared> {
        Ok(Shared {
            ctx: ctx.clone(),
            variants: Variants::new(ctx)?,
            cap_winding: CapWinding::new(ctx)?,
            slots: SlotPool::new(ctx),
            pools,
            last_profile: Mutex::new(TraceProfile::default()),
            chunk_rays: AtomicUsize::new(default_chunk_rays(ctx)),
            pack_compact: std::env::var("VKRAY_PACK").as_deref() != Ok("full"),
        })
    }

    /// Where the time went in this device's last trace (of any thread).
    pub fn last_profile(&self) -> TraceProfile {
        *self.profile_mut()
    }

    /// The last profile, to amend (a query's passes after its trace).
    pub fn profile_mut(&self) -> std::sync::MutexGuard<'_, TraceProfile> {
        self.last_profile.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps a finished trace's profile as the device's last, with the threads its host passes
    /// had.
    pub fn keep_profile(&self, mut profile: TraceProfile) {
        profile.host_threads = parallel::install(rayon::current_num_threads);
        *self.profile_mut() = profile;
    }

    /// Runs `trace` (a query's GPU part) with a fresh profile of `rays` rays, keeps that profile
    /// (timed from `started`) as the device's last, then fails with what the validation layer
    /// reported, if anything.
    pub fn profiled(
        &self,
        rays: usize,
        started: Instant,
        trace: impl FnOnce(&mut TraceProfile) -> Result<()>,
    ) -> Result<()> {
        let mut profile = TraceProfile { rays, ..Default::default() };
        trace(&mut profile)?;
        profile.total = started.elapsed().as_secs_f64();
        self.keep_profile(profile);
        self.ctx.check_validation()
    }

    /// The staging, scratch and leases this device keeps idle between queries.
    pub fn idle_memory(&self) -> IdleMemory {
        self.pools.iter().fold(self.slots.memory(), |sum, pool| sum + pool.memory())
    }

    /// `make` (an allocation for a query), tried once more after freeing every idle pool's
    /// memory where it ran out: what the pools keep may be what it needs. No lock may be held
    /// (idle CUDA leases wait for their streams as they go).
    pub fn with_memory<T>(&self, mut make: impl FnMut() -> Result<T>) -> Result<T> {
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
        for pool in &self.pools {
            pool.clear();
        }
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

    /// Most rays one dispatch may cover on this device.
    pub fn max_dispatch_rays(&self) -> usize {
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
    pub fn host_chunk_capacity(&self, rays: usize) -> usize {
        const OVERLAP_MIN_RAYS: usize = 1 << 18;
        let capacity = self.chunk_capacity(rays);
        if self.ctx.unified_memory || rays < 2 * OVERLAP_MIN_RAYS {
            return capacity;
        }
        capacity.min(rays.div_ceil(2))
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

    /// The variant a GPU query runs (see `VariantKey`), and the sensor record its shaders
    /// generate the rays from where they can (rays of a sensor none of whose rays the host would
    /// advance).
    pub fn gpu_variant(
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
        let sensor = sensor.map(|s| sensor_upload::upload(&self.ctx, s, &frame, exact)).transpose()?;
        Ok((variant, sensor))
    }

    /// The leaner layout a GPU query's host-packed rays take, if any (rays of the common shape,
    /// f32 or, in the exact tier, f32 rays moved into the scene's frame in f64 by the shaders;
    /// not rays a sensor generates on the GPU), and the variant of `request` that reads it.
    pub fn compact_variant(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        outputs: u32,
        exact: bool,
        sensor: bool,
    ) -> Result<Option<(RayLayout, Arc<Variant>)>> {
        if sensor || !self.pack_compact {
            return Ok(None);
        }
        let layout = if exact { rays.exact_layout() } else { rays.compact_layout(&scene.frame()) };
        let Some(layout) = layout else { return Ok(None) };
        let key = self.variant_key(scene, request, exact, outputs, false);
        Ok(Some((layout, self.variants.get(VariantKey { ray_source: ray_source(layout), ..key })?)))
    }

    /// Records the trace of `len` rays (within the device's dispatch limits) by `variant`.
    pub fn record_trace(&self, cmd: vk::CommandBuffer, variant: &Variant, params: &Params, len: usize) {
        self.variants.record_trace(cmd, variant, params, len)
    }
}

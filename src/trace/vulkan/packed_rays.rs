//! Rays the GPU packs itself: the caller's arrays, wherever the device reaches them by address
//! (host memory imported in place, memory shared with CUDA), are read in their own layout by
//! shaders/pack_rays.comp, traced, and their far rays' distances finished, all in one submission:
//! no host pass over the rays or the hits. The fast tier's closest-hit and occlusion queries.

use std::sync::Arc;
use std::time::Instant;

use ash::vk;

use super::probes::Probes;
use super::shared::Shared;
use super::timestamps::{start_stamps, Stamp, Stamps};
use super::variants::Variant;
use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::geometry::rays::{Masks, PerRay, RAY_FLOATS};
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::{Backend, Commands, Context, Timeline};
use crate::gpu::external::HostImport;
use crate::gpu::memory::{memory_barrier, Buffer, MemoryLocation};
use crate::gpu::records::{
    ExactBest, PackFrame, PackParams, Params, PACK_DIRECTIONS_F64, PACK_ORIGINS_F64, PACK_TMAX_F64, PACK_TMIN_F64,
};
use crate::gpu::shaders;
use crate::scene::{ExactScene, Scene, VulkanScene};
use crate::trace::hit_fields::{Field, HitSink, FIELDS, FIELD_COUNT};
use crate::trace::idle::{Held, Idle, IdleMemory, IdlePool};
use crate::trace::pacer::ChunkPacer;
use crate::trace::profile::TraceProfile;
use crate::trace::request::{spheres_on_host, Precision, Query, RayBatch, Request};

/// One array of the caller's rays on the device: rows of 3 (origins, directions) or 1 (bounds)
/// numbers, f32 or f64 (`wide`), `stride` bytes apart (0: row 0 for every ray).
#[derive(Clone, Copy, Debug)]
pub struct DeviceArray {
    pub address: u64,
    pub stride: u32,
    pub wide: bool,
}

impl DeviceArray {
    /// The array from row `row` on.
    fn at_row(self, row: usize) -> u64 {
        self.address + row as u64 * self.stride as u64
    }
}

/// A bound of the rays' intervals: one for every ray, or one per ray.
#[derive(Clone, Copy, Debug)]
pub enum DeviceBound {
    All(f64),
    Each(DeviceArray),
}

/// The caller's rays, on the device.
#[derive(Clone, Copy, Debug)]
pub struct DeviceRays {
    pub count: usize,
    pub origins: DeviceArray,
    pub directions: DeviceArray,
    pub tmin: DeviceBound,
    pub tmax: DeviceBound,
    /// The cull mask of every ray.
    pub mask: u8,
}

/// Where each requested hit field goes: the device address of the whole query's array (0: not
/// requested), `t` and `uv` in f32.
pub type DeviceOutputs = [u64; FIELD_COUNT];

/// Idle packing scratch kept: as many as queries used at once, at least one, at most eight.
const IDLE_SCRATCH: (usize, usize) = (1, 8);

/// The packing shader's pipelines (compiled on first use) and idle scratch.
pub struct PackPipelines {
    ctx: Arc<Context>,
    /// pack_rays.comp (it packs in f64: loaded only with shaderFloat64).
    kernel: ComputeKernel,
    idle: IdlePool<PackScratch>,
}

impl Idle for PackPipelines {
    fn memory(&self) -> IdleMemory {
        self.idle.memory()
    }

    fn clear(&self) {
        self.idle.clear();
    }
}

/// Device memory for one chunk of packed rays and their advances.
struct PackScratch {
    packed: Buffer,
    advances: Buffer,
    /// The exact tier's best hit of each ray so far (`ExactBest`), for its closest hits and
    /// occlusion on the pipeline backend; None for the fast tier's scratch.
    best: Option<Buffer>,
    capacity: usize,
}

impl Held for PackScratch {
    fn bytes(&self) -> u64 {
        self.packed.size() + self.advances.size() + self.best.as_ref().map_or(0, Buffer::size)
    }
}

impl PackPipelines {
    pub fn new(ctx: &Arc<Context>) -> Result<PackPipelines> {
        let kernel = ComputeKernel::new(
            ctx,
            shaders::PACK_RAYS,
            std::mem::size_of::<PackParams>(),
            Some("packing rays on the GPU needs"),
        )?;
        Ok(PackPipelines { ctx: ctx.clone(), kernel, idle: IdlePool::new(IDLE_SCRATCH.0, IDLE_SCRATCH.1) })
    }

    /// Most rays one packing dispatch may cover on this device.
    fn max_rays(&self) -> usize {
        self.kernel.max_invocations()
    }

    /// Whether this device packs rays itself (it needs shaderFloat64).
    pub fn available(&self) -> bool {
        self.kernel.available()
    }

    /// The pipeline of pack_rays.comp's `mode`.
    fn pipeline(&self, mode: PackMode) -> Result<vk::Pipeline> {
        self.kernel.pipeline(&[mode as u32])
    }

    /// Scratch for `capacity` rays: an idle one where it fits, a new one (allocated outside the
    /// lock) otherwise.
    fn take_scratch(&self, capacity: usize, exact: bool) -> Result<PackScratch> {
        // The exact tier's rays are f64 (`Rays::pack_f64`), the others' f32.
        let ray_bytes = (capacity * RAY_FLOATS * if exact { 8 } else { 4 }) as u64;
        let fits =
            |s: &PackScratch| s.capacity >= capacity && s.packed.size() >= ray_bytes && (s.best.is_some() || !exact);
        if let Some(scratch) = self.idle.take(1, fits, |_| true).pop() {
            return Ok(scratch);
        }
        use vk::BufferUsageFlags as U;
        let usage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let made = (|| {
            Ok(PackScratch {
                packed: Buffer::new(&self.ctx, ray_bytes, usage, MemoryLocation::GpuOnly, "packed rays")?,
                advances: Buffer::new(&self.ctx, 8 * capacity as u64, usage, MemoryLocation::GpuOnly, "ray advances")?,
                best: if exact {
                    let bytes = (capacity * size_of::<ExactBest>()) as u64;
                    Some(Buffer::new(&self.ctx, bytes, usage, MemoryLocation::GpuOnly, "exact best hits")?)
                } else {
                    None
                },
                capacity,
            })
        })();
        made.inspect_err(|_| self.idle.give_back(1, []))
    }

    /// Keeps the scratch for a later query (as many as were in use at once).
    fn give_back(&self, scratch: PackScratch) {
        self.idle.give_back(1, [scratch]);
    }

    /// Records the packing (or finishing) of one chunk.
    fn record(&self, cmd: vk::CommandBuffer, pipeline: vk::Pipeline, params: &PackParams) {
        let device = &self.ctx.device;
        // SAFETY: `cmd` is recording; pipeline and layout are live; the push constants cover the
        // layout's range; the group count is within limits (count < 2^32, local_size >= 1, and
        // chunks fit `max_rays`).
        unsafe {
            device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, pipeline);
            device.cmd_push_constants(
                cmd,
                self.kernel.layout(),
                vk::ShaderStageFlags::COMPUTE,
                0,
                bytemuck::bytes_of(params),
            );
            device.cmd_dispatch(cmd, params.count.div_ceil(self.kernel.local_size), 1, 1);
        }
    }
}

/// What pack_rays.comp does (its specialization constant FINISH).
#[derive(Clone, Copy)]
enum PackMode {
    /// Packs the fast tier's f32 rays, far ones advanced.
    Pack = 0,
    /// Adds each far ray's advance back to its hit distance.
    Finish = 1,
    /// Packs the exact tier's f64 rays.
    PackExact = 2,
    /// Adds each hit's ray's advance back to its distance (all hits' columns).
    FinishHits = 3,
}

/// Why a query cannot take the device-rays path, if it cannot: closest hits, occlusion, counts
/// and transmittance in the fast and exact tiers.
pub fn device_rays_refusal(request: Request) -> Option<&'static str> {
    match (request.precision, request.query) {
        (Precision::Fast | Precision::Exact, Query::Closest | Query::Occluded | Query::Count | Query::Transmit) => None,
        (Precision::Fast | Precision::Exact, _) => {
            Some("only closest hits, occlusion, counts and transmittance trace rays the GPU packs itself")
        }
        _ => Some("only precision='fast' and 'exact' (counts) trace rays the GPU packs itself"),
    }
}

/// The GPU-packed rays path: the caller's arrays read where they lie, packed, traced and finished
/// on the device. Owns the packing pipelines and their idle scratch.
pub struct PackedRays {
    shared: Arc<Shared>,
    probes: Arc<Probes>,
    packing: Arc<PackPipelines>,
    /// Whether queries on host arrays have the GPU pack their rays where they can
    /// (`pack_on_gpu_by_default`).
    pack_on_gpu: bool,
}

impl PackedRays {
    pub fn new(shared: &Arc<Shared>, probes: &Arc<Probes>, packing: &Arc<PackPipelines>) -> PackedRays {
        let pack_on_gpu = pack_on_gpu_by_default(&shared.ctx);
        PackedRays { shared: shared.clone(), probes: probes.clone(), packing: packing.clone(), pack_on_gpu }
    }

    /// Whether queries on this device may have the GPU pack their rays.
    pub fn packs_rays(&self) -> bool {
        self.packing.available()
    }

    /// Traces `rays` (on the device) against `scene` in the fast tier, writing the fields
    /// `outputs` points at: packing, tracing and finishing on the device, a submission a chunk,
    /// ordered against another API's work by `order` where given. Returns the first invalid ray's row, if any (its
    /// outputs, and perhaps others', are then not the caller's to read).
    ///
    /// The caller makes sure the arrays stay valid until this returns.
    pub fn trace_device_rays(
        &self,
        query: DeviceQuery,
        order: Option<Ordering>,
        interrupt: &dyn Interrupt,
    ) -> Result<Option<usize>> {
        let DeviceQuery { scene, rays, request, .. } = query;
        if let Some(why) = device_rays_refusal(request) {
            return Err(invalid_value(why));
        }
        if spheres_on_host(scene, request) {
            // The caller asks `stays_on_gpu` first: this query of this scene is the host's.
            return Err(Error::Unsupported("the GPU does not trace this query of a scene with spheres".into()));
        }
        // Here, not in `trace_packed`: `trace` holds the meshes already (holding them twice on
        // one thread would deadlock behind a waiting update), and the intersection-shader probes
        // trace through `run_gpu`.
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        self.probes.check_paths(scene, request.precision == Precision::Exact)?;
        let mut profile = TraceProfile { rays: rays.count, ..Default::default() };
        let started = Instant::now();
        let invalid = self.trace_packed(query, order, interrupt, &mut profile)?;
        profile.total = started.elapsed().as_secs_f64();
        self.shared.keep_profile(profile);
        Ok(invalid)
    }

    /// Rays per chunk (a submission) of a query on `count` device rays.
    pub fn device_chunk_capacity(&self, count: usize) -> usize {
        self.shared.chunk_capacity(count).min(self.packing.max_rays())
    }

    /// `trace_device_rays` for any tier whose GPU part traverses in f32 (the refined tier's too),
    /// its device times added to `profile`.
    fn trace_packed(
        &self,
        query: DeviceQuery,
        order: Option<Ordering>,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<Option<usize>> {
        let DeviceQuery { scene, rays, request, outputs } = query;
        if rays.count >= u32::MAX as usize {
            return Err(invalid_value("at most 2^32 - 2 rays a query when the GPU packs them"));
        }
        self.shared.ctx.check_usable()?;
        let bits = FIELDS.iter().filter(|f| outputs[**f as usize] != 0).fold(0, |b, f| b | f.bit());
        let exact = request.precision == Precision::Exact;
        // Before the exact variant: this fails on devices without shaderFloat64 (no exact modules).
        let exact_scene = if exact { Some(VulkanScene::of(scene)?.exact(scene)?) } else { None };
        let variant = self.shared.variants.get(self.shared.variant_key(scene, request, exact, bits, false))?;
        let frame_buffer = self.pack_frame(scene, rays)?;
        // Chunks as the host path's (`Device.chunk_rays`): the interrupt is asked between them.
        let capacity = match order.as_ref().and_then(|o| o.chunk_rays) {
            Some(rays) => rays.clamp(1, self.packing.max_rays()),
            None => self.device_chunk_capacity(rays.count),
        };
        let scratch = self.shared.with_memory(|| self.packing.take_scratch(capacity, exact))?;
        let job = PackedJob {
            hierarchy: VulkanScene::of(scene)?,
            exact: exact_scene.as_deref(),
            t_is_distance: request.query != Query::Transmit,
            counts: request.query.counts_hits(),
            rays,
            outputs,
            variant: &variant,
            scratch: &scratch,
            frame: frame_buffer.address(),
        };
        let traced = self.trace_packed_chunks(&job, capacity, order, interrupt, profile);
        self.packing.give_back(scratch);
        traced?;
        self.shared.ctx.check_validation()?;
        let frame: PackFrame =
            *bytemuck::from_bytes(&frame_buffer.mapped().expect("the frame is host-visible")[..size_of::<PackFrame>()]);
        Ok((frame.first_invalid != u32::MAX).then_some(frame.first_invalid as usize))
    }

    /// Packs, traces and finishes `job`'s rays, one submission a chunk of `capacity` rays (each
    /// waiting for `order`'s timeline value; the last one signals it and then calls its
    /// `after_submit`); the interrupt is asked between chunks.
    fn trace_packed_chunks(
        &self,
        job: &PackedJob,
        capacity: usize,
        mut order: Option<Ordering>,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let exact = job.exact.is_some();
        let pack = self.packing.pipeline(if exact { PackMode::PackExact } else { PackMode::Pack })?;
        // The exact tier advances no ray, transmittance's t is no distance: nothing to finish.
        let finish = if exact || !job.t_is_distance { None } else { Some(self.packing.pipeline(PackMode::Finish)?) };
        let stamps = Stamps::new(&self.shared.ctx)?;
        let mut commands = Commands::new(&self.shared.ctx)?;
        let count = job.rays.count;
        let mut pacer = ChunkPacer::on_device(capacity, self.shared.ctx.info.is_software);
        let mut start = 0;
        while start < count {
            interrupt.check()?;
            let len = pacer.next_len(count - start);
            commands.begin()?;
            let cmd = commands.buffer;
            let stamp = start_stamps(stamps.as_ref(), cmd);
            let mut pack_params = pack_params(job.rays, start, len, job.scratch, job.frame);
            self.packing.record(cmd, pack, &pack_params);
            self.barrier(cmd, vk::PipelineStageFlags::COMPUTE_SHADER, self.trace_stage());
            stamp(Stamp::Uploaded);
            let params = job.trace_params(start, len);
            self.shared.record_trace(cmd, job.variant, &params, len);
            stamp(Stamp::Traced);
            if let (Some(finish), true) = (finish, params.outputs[Field::T as usize] != 0) {
                self.barrier(cmd, self.trace_stage(), vk::PipelineStageFlags::COMPUTE_SHADER);
                pack_params.t = params.outputs[Field::T as usize];
                self.packing.record(cmd, finish, &pack_params);
            }
            let host = (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ);
            let all = (vk::PipelineStageFlags::ALL_COMMANDS, vk::AccessFlags::MEMORY_WRITE);
            memory_barrier(&self.shared.ctx, cmd, all, host);
            stamp(Stamp::ReadBack);
            let last = start + len == count;
            // Arriving chunk by chunk: this one's rays are in place once the chunk holding its
            // last ray is.
            let arrived = |o: &Ordering| o.chunk_rays.map_or(0, |rays| ((start + len - 1) / rays.max(1)) as u64);
            let timeline = order.as_ref().map(|o| Timeline {
                wait: o.timeline.wait + arrived(o),
                signal: last.then_some(o.timeline.signal).flatten(),
                ..o.timeline
            });
            commands.submit_ordered(timeline)?;
            if last {
                if let Some(order) = order.as_mut() {
                    (order.after_submit)()?;
                }
            }
            pacer.started();
            commands.wait()?;
            pacer.finished(len);
            profile.chunks += 1;
            if let Some(stamps) = &stamps {
                stamps.add_to(profile)?;
            }
            interrupt.progress(start + len, count);
            start += len;
        }
        Ok(())
    }

    /// The shader stage tracing runs in on this device.
    fn trace_stage(&self) -> vk::PipelineStageFlags {
        match self.shared.ctx.backend {
            Backend::RayQuery => vk::PipelineStageFlags::COMPUTE_SHADER,
            Backend::Pipeline => vk::PipelineStageFlags::RAY_TRACING_SHADER_KHR,
        }
    }

    /// A barrier from shader writes in `src` to shader reads and writes in `dst`.
    fn barrier(&self, cmd: vk::CommandBuffer, src: vk::PipelineStageFlags, dst: vk::PipelineStageFlags) {
        use vk::AccessFlags as A;
        memory_barrier(
            &self.shared.ctx,
            cmd,
            (src, A::SHADER_WRITE | A::SHADER_READ),
            (dst, A::SHADER_READ | A::SHADER_WRITE),
        );
    }

    /// The query's `PackFrame`, host-visible (the shader reports the first invalid ray in it).
    fn pack_frame(&self, scene: &Scene, rays: &DeviceRays) -> Result<Buffer> {
        let frame = scene.frame();
        let bound = |b: DeviceBound| match b {
            DeviceBound::All(value) => value,
            DeviceBound::Each(_) => 0.0,
        };
        let record = PackFrame {
            shift: frame.shift.to_array(),
            bounds_center: frame.bounds_center.to_array(),
            radius: frame.radius,
            far_squared: frame.far_squared(),
            tmin: bound(rays.tmin),
            tmax: bound(rays.tmax),
            first_invalid: u32::MAX,
            unused: 0,
        };
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS;
        let size = size_of::<PackFrame>() as u64;
        let mut buffer = Buffer::new(&self.shared.ctx, size, usage, MemoryLocation::CpuToGpu, "pack frame")?;
        buffer.mapped_mut().expect("CpuToGpu memory is host-visible")[..size as usize]
            .copy_from_slice(bytemuck::bytes_of(&record));
        Ok(buffer)
    }
}

/// How a query on device rays is ordered against another API's work on them: a timeline
/// semaphore every submission waits for (the rays are in place), the last one signalling when
/// the hits are; `after_submit` runs right after that last submission (the other API queues its
/// wait for the hits), before the host waits.
pub struct Ordering<'a> {
    pub timeline: Timeline,
    pub after_submit: &'a mut dyn FnMut() -> Result<()>,
    /// Rays arriving chunk by chunk: chunks of this many rays, chunk k waiting for
    /// `timeline.wait + k` (so that tracing one chunk overlaps the copy of the next). None: every
    /// chunk waits for `timeline.wait`, in chunks of `chunk_capacity`.
    pub chunk_rays: Option<usize>,
}

/// A query on rays on the device: the scene, the rays, what is asked, and the device addresses
/// of its outputs (per field; 0: not written).
#[derive(Clone, Copy)]
pub struct DeviceQuery<'a> {
    pub scene: &'a Scene,
    pub rays: &'a DeviceRays,
    pub request: Request,
    pub outputs: &'a DeviceOutputs,
}

/// What every chunk of a query on device rays shares.
struct PackedJob<'a> {
    /// The Vulkan engine's hierarchy of the scene traced.
    hierarchy: &'a VulkanScene,
    /// The exact tier's structures, for exact queries.
    exact: Option<&'a ExactScene>,
    /// `t` is a distance along the ray, to which a far ray's advance is added back; not the
    /// light a transmittance query keeps.
    t_is_distance: bool,
    /// The query counts hits (QUERY_ALL's counting pass).
    counts: bool,
    rays: &'a DeviceRays,
    outputs: &'a DeviceOutputs,
    variant: &'a Variant,
    scratch: &'a PackScratch,
    /// The `PackFrame`'s address.
    frame: u64,
}

impl PackedJob<'_> {
    /// The trace's push constants for the packed rays `start..start + len`.
    fn trace_params(&self, start: usize, len: usize) -> Params {
        let mut params = Params {
            rays: self.scratch.packed.address(),
            count: len as u32,
            ray_mask: self.rays.mask as u32,
            instances: self.hierarchy.instance_geometries_address(),
            tlas: self.hierarchy.tlas_address(),
            ..Default::default()
        };
        if let Some(exact) = self.exact {
            (params.instances, params.tlas, params.bounds) =
                (exact.instances_address(), exact.tlas_address(), exact.bounds_f32());
            // Each ray's best hit so far (closest hits and occlusion on the pipeline backend; a
            // count, QUERY_ALL's counting pass, reads none).
            if !self.counts {
                params.scratch = self.scratch.best.as_ref().map_or(0, Buffer::address);
            }
        }
        for field in FIELDS {
            let address = self.outputs[field as usize];
            if address != 0 {
                params.outputs[field as usize] = address + (start * field.bytes_per_ray(self.exact.is_some())) as u64;
            }
        }
        params
    }
}

/// A query's device rays packed chunk by chunk for another path (all hits of CUDA rays, whose
/// passes read the packed rays twice): the query's frame, one chunk's scratch, and the pipelines.
/// The scratch goes back to the idle pool when it is dropped.
pub struct DevicePacking<'a> {
    packing: &'a PackPipelines,
    rays: &'a DeviceRays,
    scratch: Option<PackScratch>,
    frame: Buffer,
    pack: vk::Pipeline,
    /// The fast tier's: far rays' advances added back to their hits' t.
    finish_hits: Option<vk::Pipeline>,
}

impl DevicePacking<'_> {
    fn scratch(&self) -> &PackScratch {
        self.scratch.as_ref().expect("kept until dropped")
    }

    /// Where a chunk's packed rays lie (as `Rays::pack` or, exact, `Rays::pack_f64` lays them).
    pub fn rays_address(&self) -> u64 {
        self.scratch().packed.address()
    }

    /// Records the packing of rays `start..start + len`, made visible to `trace_stage`.
    pub fn record_pack(&self, cmd: vk::CommandBuffer, start: usize, len: usize, trace_stage: vk::PipelineStageFlags) {
        let params = pack_params(self.rays, start, len, self.scratch(), self.frame.address());
        self.packing.record(cmd, self.pack, &params);
        use vk::AccessFlags as A;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(&self.packing.ctx, cmd, (compute, A::SHADER_WRITE), (trace_stage, A::SHADER_READ));
    }

    /// Records, after `writer`'s writes of a chunk's `hits` columns (rays from `start`), the
    /// addition of each far ray's advance back to its hits' t (f32, at `t`; each hit's ray at
    /// `ray_index`); nothing in the exact tier, which advances no ray.
    pub fn record_finish_hits(&self, cmd: vk::CommandBuffer, start: usize, hits: usize, (t, ray_index): (u64, u64)) {
        let Some(pipeline) = self.finish_hits.filter(|_| hits > 0 && t != 0) else { return };
        use vk::AccessFlags as A;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(&self.packing.ctx, cmd, (compute, A::SHADER_WRITE), (compute, A::SHADER_READ | A::SHADER_WRITE));
        // A dispatch covers at most `max_rays` invocations: more hits go in several.
        let most = self.packing.max_rays().max(1);
        for first in (0..hits).step_by(most) {
            let params = PackParams {
                advances: self.scratch().advances.address(),
                t: t + 4 * first as u64,
                ray_index: ray_index + 8 * first as u64,
                count: (hits - first).min(most) as u32,
                first_row: start as u32,
                ..Default::default()
            };
            self.packing.record(cmd, pipeline, &params);
        }
    }

    /// The first invalid ray's row, once every chunk was packed and waited for.
    pub fn first_invalid(&self) -> Option<usize> {
        let frame: PackFrame =
            *bytemuck::from_bytes(&self.frame.mapped().expect("the frame is host-visible")[..size_of::<PackFrame>()]);
        (frame.first_invalid != u32::MAX).then_some(frame.first_invalid as usize)
    }
}

impl Drop for DevicePacking<'_> {
    fn drop(&mut self) {
        if let Some(scratch) = self.scratch.take() {
            self.packing.give_back(scratch);
        }
    }
}

impl PackedRays {
    /// Packing for `rays` (on the device, fewer than 2^32) traced against `scene` in chunks of at
    /// most `capacity` (`max_pack_rays` at most), f64 rays where `exact`.
    pub fn device_packing<'a>(
        &'a self,
        scene: &Scene,
        rays: &'a DeviceRays,
        exact: bool,
        capacity: usize,
    ) -> Result<DevicePacking<'a>> {
        if rays.count >= u32::MAX as usize {
            return Err(invalid_value("at most 2^32 - 2 rays a query when the GPU packs them"));
        }
        let pack = self.packing.pipeline(if exact { PackMode::PackExact } else { PackMode::Pack })?;
        let finish_hits = if exact { None } else { Some(self.packing.pipeline(PackMode::FinishHits)?) };
        let frame = self.pack_frame(scene, rays)?;
        let scratch = self.shared.with_memory(|| self.packing.take_scratch(capacity, exact))?;
        Ok(DevicePacking { packing: &self.packing, rays, scratch: Some(scratch), frame, pack, finish_hits })
    }

    /// Most rays one chunk of `device_packing` may hold.
    pub fn max_pack_rays(&self) -> usize {
        self.packing.max_rays()
    }
}

/// The packing shader's push constants for rays `start..start + len`.
fn pack_params(rays: &DeviceRays, start: usize, len: usize, scratch: &PackScratch, frame: u64) -> PackParams {
    let mut params = PackParams {
        origins: rays.origins.at_row(start),
        directions: rays.directions.at_row(start),
        packed: scratch.packed.address(),
        advances: scratch.advances.address(),
        frame,
        origin_stride: rays.origins.stride,
        direction_stride: rays.directions.stride,
        count: len as u32,
        first_row: start as u32,
        formats: if rays.origins.wide { PACK_ORIGINS_F64 } else { 0 }
            | if rays.directions.wide { PACK_DIRECTIONS_F64 } else { 0 },
        ..Default::default()
    };
    if let DeviceBound::Each(array) = rays.tmin {
        (params.tmin, params.tmin_stride) = (array.at_row(start), array.stride);
        params.formats |= if array.wide { PACK_TMIN_F64 } else { 0 };
    }
    if let DeviceBound::Each(array) = rays.tmax {
        (params.tmax, params.tmax_stride) = (array.at_row(start), array.stride);
        params.formats |= if array.wide { PACK_TMAX_F64 } else { 0 };
    }
    params
}

/// When queries on host arrays have the GPU pack their rays (`VKRAY_PACK`): "gpu" wherever it
/// can; otherwise (the default, or "host") the host packs them. Measured on an H100 (docs/
/// benchmarks.md, issue 14): importing 16M rays' host memory pins it at about 13 GB/s, which
/// costs more than the host's packing pass it saves, so the GPU packs only rays already on it
/// (CUDA arrays) unless asked.
fn pack_on_gpu_by_default(_ctx: &Context) -> bool {
    matches!(std::env::var("VKRAY_PACK").as_deref(), Ok("gpu" | "staged"))
}

/// VKRAY_PACK=staged: the GPU packs, from copies of the caller's arrays in vkray's own staging
/// rather than imported (to measure what a raw copy costs against the host's packing pass).
fn copy_rather_than_import() -> bool {
    matches!(std::env::var("VKRAY_PACK").as_deref(), Ok("staged"))
}

/// Host memory the device reads or writes for one query: the caller's bytes imported in place,
/// or a buffer of its own the bytes are copied into (inputs) or out of (outputs).
enum HostMemory {
    Imported(HostImport),
    Copied(Buffer),
}

impl HostMemory {
    /// The device's view of `bytes`, to read.
    fn input(ctx: &Arc<Context>, bytes: &[u8], name: &str) -> Result<HostMemory> {
        if !copy_rather_than_import() {
            // SAFETY: `bytes` is borrowed for the whole query, which waits for the device before the
            // import is dropped; nothing writes it meanwhile (a shared borrow).
            if let Some(import) = unsafe { HostImport::new(ctx, bytes.as_ptr(), bytes.len()) }? {
                return Ok(HostMemory::Imported(import));
            }
        }
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS;
        let mut buffer = Buffer::new(ctx, bytes.len() as u64, usage, MemoryLocation::CpuToGpu, name)?;
        let staging = buffer.mapped_mut().expect("CpuToGpu memory is host-visible");
        parallel::copy(&mut staging[..bytes.len()], bytes);
        Ok(HostMemory::Copied(buffer))
    }

    /// The device's view of `bytes`, to write (`finish` copies what it wrote into them).
    fn output(ctx: &Arc<Context>, bytes: &mut [u8], name: &str) -> Result<HostMemory> {
        if !copy_rather_than_import() {
            // SAFETY: `bytes` is borrowed mutably for the whole query, which waits for the device
            // before the import is dropped; the host does not touch it meanwhile.
            if let Some(import) = unsafe { HostImport::new(ctx, bytes.as_ptr(), bytes.len()) }? {
                return Ok(HostMemory::Imported(import));
            }
        }
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS;
        Ok(HostMemory::Copied(Buffer::new(ctx, bytes.len() as u64, usage, MemoryLocation::GpuToCpu, name)?))
    }

    fn address(&self) -> u64 {
        match self {
            HostMemory::Imported(import) => import.address(),
            HostMemory::Copied(buffer) => buffer.address(),
        }
    }

    /// After the device wrote an output: its bytes into the caller's array, unless in place.
    fn finish(&self, out: &mut [u8]) {
        if let HostMemory::Copied(buffer) = self {
            let written = buffer.mapped().expect("GpuToCpu memory is host-visible");
            parallel::copy(out, &written[..out.len()]);
        }
    }
}

fn vec3_bytes<'a>(v: &Vec3s<'a>) -> (&'a [u8], bool) {
    match *v {
        Vec3s::F32(values) => (bytemuck::cast_slice(values), false),
        Vec3s::F64(values) => (bytemuck::cast_slice(values), true),
    }
}

impl PackedRays {
    /// The GPU part of a query on host arrays with the rays packed by the GPU: the arrays are
    /// imported in place where the device can (else copied once), and the hits written straight
    /// into the caller's arrays (else copied out once). `None` where this query cannot go this
    /// way (rays of a sensor, per-ray masks, lists of hits, the exact tier, a policy of packing on
    /// the host): the caller packs on the host instead.
    pub fn trace_arrays_packed_on_gpu(
        &self,
        batch: RayBatch,
        sink: &mut HitSink,
        profile: &mut TraceProfile,
    ) -> Result<Option<()>> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let Masks::All(mask) = rays.mask else { return Ok(None) };
        let eligible = self.pack_on_gpu
            && self.packing.available()
            && rays.sensor.is_none()
            // The exact tier packs host rays on the host (its leaner layouts).
            && request.precision == Precision::Fast
            && device_rays_refusal(request).is_none()
            && rays.len() < u32::MAX as usize;
        if !eligible {
            return Ok(None);
        }
        let ctx = &self.shared.ctx;
        let clock = Instant::now();
        let mut inputs = Vec::new();
        let mut array = |v: &Vec3s, name: &str| -> Result<DeviceArray> {
            let (bytes, wide) = vec3_bytes(v);
            let shared = self.shared.with_memory(|| HostMemory::input(ctx, bytes, name))?;
            let stride = if v.rows() == 1 { 0 } else { 3 * if wide { 8 } else { 4 } };
            let array = DeviceArray { address: shared.address(), stride, wide };
            inputs.push(shared);
            Ok(array)
        };
        let origins = array(&rays.origins, "origins")?;
        let directions = array(&rays.directions, "directions")?;
        let mut bound = |b: PerRay, name: &str| -> Result<DeviceBound> {
            Ok(match b {
                PerRay::All(value) => DeviceBound::All(value),
                PerRay::Each(values) => {
                    let shared =
                        self.shared.with_memory(|| HostMemory::input(ctx, bytemuck::cast_slice(values), name))?;
                    let array = DeviceArray { address: shared.address(), stride: 8, wide: true };
                    inputs.push(shared);
                    DeviceBound::Each(array)
                }
            })
        };
        let (tmin, tmax) = (bound(rays.tmin, "tmin")?, bound(rays.tmax, "tmax")?);
        let device_rays = DeviceRays { count: rays.len(), origins, directions, tmin, tmax, mask };
        let mut outputs: DeviceOutputs = [0; FIELD_COUNT];
        let mut shared_outputs = Vec::new();
        for (field, out) in sink.iter_mut() {
            let shared = self.shared.with_memory(|| HostMemory::output(ctx, out, field.name()))?;
            outputs[field as usize] = shared.address();
            shared_outputs.push((field, shared));
        }
        profile.pack += clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let query = DeviceQuery { scene, rays: &device_rays, request, outputs: &outputs };
        let invalid = self.trace_packed(query, None, interrupt, profile)?;
        profile.wait += clock.elapsed().as_secs_f64();
        if let Some(row) = invalid {
            return Err(rays.invalid_ray(row));
        }
        let clock = Instant::now();
        for (field, shared) in &shared_outputs {
            shared.finish(sink.field_mut(*field).expect("a requested field"));
        }
        profile.unpack += clock.elapsed().as_secs_f64();
        drop(inputs);
        Ok(Some(()))
    }
}

//! The closest-hit path (`RayChunks`): every GPU ray query whose rays the host packs goes through
//! the chunk loop: rays go through in chunks that fit the device's dispatch limits and the
//! staging slots, each sized to last a fraction of a second (`ChunkPacer`), two chunks in flight so that packing the next overlaps tracing the current one.
//! Between chunks the caller may interrupt (Ctrl-C); chunks in flight finish first.

use std::time::Instant;

use ash::vk;
use glam::DVec3;
use rayon::prelude::*;

use super::cap_winding::{CapChunk, CapPass};
use super::hit_lists::ListBuffers;
use super::shared::Shared;
use super::staging::{HitReadback, RayStaging, Slot};
use super::timestamps::{start_stamps, Stamp};
use super::variants::Variant;
use crate::error::{invalid_value, Result};
use crate::geometry::parallel;
use crate::geometry::rays::{Advance, Frame, Masks, RayLayout, Rays, RAY_FLOATS};
use crate::trace::hit_fields::{hits_from_prims, Field, HitSink, FIELDS};
use crate::trace::pacer::ChunkPacer;
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Query, RayBatch};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::geometry::interrupt::Interrupt;
use crate::gpu::context::{Backend, Commands, Context};
use crate::gpu::memory::{memory_barrier, Buffer};
use crate::gpu::records::Params;
use crate::scene::{ExactScene, VulkanScene};

/// What every chunk of one query shares.
pub(super) struct GpuJob<'a> {
    /// The Vulkan engine's hierarchy of the scene traced.
    pub hierarchy: &'a VulkanScene,
    /// The exact tier's structures, for exact queries.
    pub exact: Option<&'a ExactScene>,
    pub rays: &'a Rays<'a>,
    pub variant: &'a Variant,
    /// A leaner layout the rays pack in, and the variant that reads it (`Rays::compact_layout`);
    /// a chunk it cannot hold (a far ray) takes the full layout and `variant`, and so do the
    /// chunks after it (`compact_refused`): rays far from the scene tend to come together.
    pub compact: Option<(RayLayout, &'a Variant)>,
    /// A chunk of this job had a far ray: the rest pack in the full layout at once, rather than
    /// each packing twice.
    pub compact_refused: AtomicBool,
    pub outputs: u32,
    pub frame: Frame,
    /// The variant meets every hit (QUERY_ALL: counts and all hits).
    pub all_hits: bool,
    /// The sensor record the shaders generate the rays from, when they do (nothing uploaded).
    pub sensor: Option<&'a Buffer>,
    /// The cap a winding query's rays take away (`Query::Winding`), and the pass that sums its
    /// solid angles after each chunk's trace.
    pub cap: Option<CapPass<'a>>,
    /// `t` is a distance along the ray, to which a far ray's advance is added back; not the
    /// light a transmittance query keeps.
    pub t_is_distance: bool,
    /// Where the GPU packed the chunk's rays itself (all hits of CUDA rays: `DevicePacking`),
    /// read there rather than from the slot; `rays` then holds only their mask.
    pub packed_on_device: Option<u64>,
}

/// Where a chunk's all hits go (QUERY_ALL), in `scratch` and `out_t`.
#[derive(Clone, Copy)]
pub(super) enum ChunkLists<'a> {
    /// Counted only.
    Counted,
    /// The counting pass, keeping each ray's nearest `hits` in fixed lists from `records`.
    Nearest { records: u64, hits: usize },
    /// The storing pass: into the buffers' lists.
    Lists(&'a ListBuffers),
}

/// A chunk submitted and not yet unpacked: its first ray, its length, and how far its far rays
/// were advanced.
struct InFlight {
    start: usize,
    len: usize,
    advances: Vec<Advance>,
}

/// The closest-hit path: rays the host packs into staging, traced two chunks in flight. It owns
/// nothing of its own: staging and variants are the shared value's.
#[derive(Clone)]
pub struct RayChunks {
    shared: Arc<Shared>,
}

impl RayChunks {
    pub fn new(shared: &Arc<Shared>) -> RayChunks {
        RayChunks { shared: shared.clone() }
    }

    /// The GPU's part of a query on rays the host packs: traversal in f32 (`exact`: through the
    /// scene's per-triangle boxes, each candidate decided by the f64 test).
    pub fn run(&self, batch: RayBatch, exact: bool, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let shared = &*self.shared;
        let outputs = sink.outputs();
        // Before any exact variant: this fails on devices without shaderFloat64 (no exact modules).
        let exact_scene = if exact { Some(VulkanScene::of(scene)?.exact(scene)?) } else { None };
        let all_hits = request.query.counts_hits();
        let (variant, sensor) = shared.gpu_variant(scene, rays, request, exact, outputs)?;
        let capacity = shared.host_chunk_capacity(rays.len());
        let frame = scene.frame();
        let sensor = sensor.as_ref();
        let cap = match request.query {
            Query::Winding => Some(VulkanScene::of(scene)?.winding_cap(scene)?.ok_or_else(|| {
                invalid_value("a winding query needs a scene of one instance whose mesh has a cap (WindingCap)")
            })?),
            _ => None,
        };
        let (exact, cap) = (exact_scene.as_deref(), cap.as_deref());
        let cap = cap.map(|cap| shared.cap_winding.pass(cap)).transpose()?;
        let compact_variant =
            shared.compact_variant(scene, rays, request, outputs, exact_scene.is_some(), sensor.is_some())?;
        let compact = compact_variant.as_ref().map(|(layout, variant)| (*layout, &**variant));
        let compact_refused = Default::default();
        // Taken last: nothing fails between here and their return.
        let mut slots = shared.with_memory(|| shared.slots.take(capacity, exact.is_some()))?;
        let job = GpuJob {
            hierarchy: VulkanScene::of(scene)?,
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
            t_is_distance: request.query != Query::Transmit,
            packed_on_device: None,
        };
        let result = self.trace_chunks(&job, sink, &mut slots, capacity, interrupt, profile);
        shared.slots.give_back(slots);
        result
    }

    /// Traces every ray of `job` through the two `slots` of `capacity` rays each, unpacking each
    /// finished chunk into `sink`.
    fn trace_chunks(
        &self,
        job: &GpuJob,
        sink: &mut HitSink,
        slots: &mut [Slot; 2],
        capacity: usize,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let n = job.rays.len();
        let mut clock = Instant::now();
        let mut lap = |into: &mut f64| {
            let now = Instant::now();
            *into += (now - clock).as_secs_f64();
            clock = now;
        };
        // Dropping these on an error waits for the chunks in flight before their memory goes.
        let mut commands = [Commands::new(&self.shared.ctx)?, Commands::new(&self.shared.ctx)?];
        let mut in_flight: [Option<InFlight>; 2] = [None, None];
        // Rays whose chunk finished, for `Interrupt::progress` (chunks finish out of order at the end).
        let mut finished = 0;
        let mut pacer = ChunkPacer::on_device(capacity, self.shared.ctx.info.is_software);
        let (mut chunk, mut start) = (0, 0);
        while start < n {
            interrupt.check()?;
            let s = chunk % 2;
            lap(&mut profile.submit);
            commands[s].wait()?;
            lap(&mut profile.wait);
            let done = in_flight[s].take();
            if let Some(done) = &done {
                pacer.finished(done.len);
            }
            let len = pacer.next_len(n - start);
            let (finished_chunk, packed) = {
                // The slot's last chunk's hits are copied out while this chunk's rays are packed
                // into its ray staging: the one pass reads host memory, the other writes the
                // GPU's over the bus, and side by side they take less than one after the other.
                let (staging, readback) = slots[s].split();
                let outputs = job.outputs;
                let unpack = || {
                    let started = Instant::now();
                    let finished = done
                        .as_ref()
                        .map_or(Ok(0), |done| finish_chunk(&readback, done, outputs, sink, profile).map(|()| done.len));
                    (finished, started.elapsed().as_secs_f64())
                };
                let pack = || {
                    let started = Instant::now();
                    (pack_chunk(job, staging, start, len), started.elapsed().as_secs_f64())
                };
                parallel::install(|| rayon::join(unpack, pack))
            };
            let ((finished_rays, unpack_seconds), (advances, pack_seconds)) = (finished_chunk, packed);
            // Each side's own time: side by side, they add up to more than the phase's.
            lap(&mut 0.0);
            (profile.unpack, profile.pack) = (profile.unpack + unpack_seconds, profile.pack + pack_seconds);
            let finished_rays = finished_rays?;
            if finished_rays > 0 {
                finished += finished_rays;
                interrupt.progress(finished, n);
            }
            // A far ray's advance corrects distances, not the light transmittance keeps.
            let advances = if job.t_is_distance { advances? } else { advances.map(|_| Vec::new())? };
            if job.sensor.is_none() {
                profile.ray_bytes += slots[s].packed_bytes(len);
            }
            profile.chunks += 1;
            commands[s].begin()?;
            self.record_chunk(commands[s].buffer, job, &slots[s], start, len);
            commands[s].submit()?;
            pacer.started();
            in_flight[s] = Some(InFlight { start, len, advances });
            (chunk, start) = (chunk + 1, start + len);
        }
        lap(&mut profile.submit);
        for s in 0..2 {
            commands[s].wait()?;
            lap(&mut profile.wait);
            if let Some(done) = in_flight[s].take() {
                finish_chunk(&slots[s].split().1, &done, job.outputs, sink, profile)?;
                finished += done.len;
                interrupt.progress(finished, n);
            }
            lap(&mut profile.unpack);
        }
        Ok(())
    }

    /// Records one chunk (`len` rays from `start`): its upload (discrete GPUs), the trace, and its
    /// readback.
    pub(super) fn record_chunk(&self, cmd: vk::CommandBuffer, job: &GpuJob, slot: &Slot, start: usize, len: usize) {
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        self.record_upload(cmd, job, slot, len);
        stamp(Stamp::Uploaded);
        self.record_trace(cmd, job, slot, start, len, ChunkLists::Counted);
        stamp(Stamp::Traced);
        record_readback(&self.shared.ctx, cmd, slot, job.outputs, len, None);
        stamp(Stamp::ReadBack);
    }

    /// Records the upload of a chunk's `len` rays from the slot's staging (discrete GPUs; rays a
    /// sensor generates need none), made visible to the trace.
    pub(super) fn record_upload(&self, cmd: vk::CommandBuffer, job: &GpuJob, slot: &Slot, len: usize) {
        let ctx = &self.shared.ctx;
        let Some((rays_device, _)) = &slot.device else { return };
        if job.sensor.is_none() {
            let masks_at = slot.masks_offset() as u64;
            let rays_region = vk::BufferCopy::default().size(slot.packed_bytes(len) as u64);
            let masks_region = vk::BufferCopy::default().src_offset(masks_at).dst_offset(masks_at).size(4 * len as u64);
            let regions = match job.rays.mask {
                Masks::Each(_) => vec![rays_region, masks_region],
                Masks::All(_) => vec![rays_region],
            };
            // SAFETY: `cmd` is recording; both buffers hold `capacity` rays and masks.
            unsafe { ctx.device.cmd_copy_buffer(cmd, slot.rays_host.raw(), rays_device.raw(), &regions) };
        }
        memory_barrier(
            ctx,
            cmd,
            (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
            (trace_stage(ctx), vk::AccessFlags::SHADER_READ),
        );
    }

    /// Records the trace of a chunk's `len` rays (from `start`) already on the device (all hits:
    /// where `lists` says).
    pub(super) fn record_trace(
        &self,
        cmd: vk::CommandBuffer,
        job: &GpuJob,
        slot: &Slot,
        start: usize,
        len: usize,
        lists: ChunkLists,
    ) {
        let mut params = chunk_params(job, slot, start, len);
        if job.all_hits {
            // QUERY_ALL reads `scratch` as the rays' lists (hit_lists.glsl), `out_t` as their records.
            let (scratch, records) = match lists {
                ChunkLists::Counted => (0, 0),
                ChunkLists::Nearest { records, hits } => (((hits as u64) << 1) | 1, records),
                ChunkLists::Lists(buffers) => (buffers.lists_address(), buffers.records_address()),
            };
            params.scratch = scratch;
            if records != 0 {
                params.outputs[Field::T as usize] = records;
            }
        }
        if let Some(cap) = job.cap {
            // QUERY_WINDING reads `scratch` as the cap, and leaves the origins of the rays whose
            // caps' solid angles the cap pass sums at `out_uv`: the slot's exact scratch, which it
            // has no other use for.
            params.outputs[Field::Uv as usize] = slot.hits_address() + slot.scratch_offset() as u64;
            params.scratch = cap.cap.address();
        }
        let variant = match job.compact {
            Some((layout, compact)) if slot.layout == layout => compact,
            _ => job.variant,
        };
        self.shared.record_trace(cmd, variant, &params, len);
        if let Some(cap) = job.cap {
            let chunk = CapChunk {
                origins: params.outputs[Field::Uv as usize],
                shift: DVec3::ZERO,
                counts: params.outputs[Field::Prim as usize],
                winding: params.outputs[Field::T as usize],
                len,
            };
            cap.record(&self.shared.ctx, cmd, &chunk, trace_stage(&self.shared.ctx));
        }
    }
}

/// The shader stage tracing runs in on this device.
pub(super) fn trace_stage(ctx: &Context) -> vk::PipelineStageFlags {
    match ctx.backend {
        Backend::RayQuery => vk::PipelineStageFlags::COMPUTE_SHADER,
        Backend::Pipeline => vk::PipelineStageFlags::RAY_TRACING_SHADER_KHR,
    }
}

/// The push constants of the chunk of `len` rays from `start`.
fn chunk_params(job: &GpuJob, slot: &Slot, start: usize, len: usize) -> Params {
    let rays = job.packed_on_device.unwrap_or_else(|| slot.rays_address());
    let mut params = Params { rays, count: len as u32, ..Default::default() };
    match job.rays.mask {
        Masks::All(m) => params.ray_mask = m as u32,
        Masks::Each(_) => params.masks = slot.rays_address() + slot.masks_offset() as u64,
    }
    if let Some(sensor) = job.sensor {
        params.rays = sensor.address();
        params.masks = start as u64;
    }
    match job.exact {
        Some(exact) => {
            params.instances = exact.instances_address();
            params.tlas = exact.tlas_address();
            params.scratch = slot.hits_address() + slot.scratch_offset() as u64;
            params.bounds = exact.bounds_f32();
        }
        None => {
            params.instances = job.hierarchy.instance_geometries_address();
            params.tlas = job.hierarchy.tlas_address();
        }
    }
    for field in FIELDS {
        if job.outputs & field.bit() != 0 {
            params.outputs[field as usize] = slot.hits_address() + slot.field_offset(field) as u64;
        }
    }
    params
}

/// Makes the hits (and the storing pass's records) visible to the host: copied to readback
/// memory on discrete GPUs.
pub(super) fn record_readback(
    ctx: &Context,
    cmd: vk::CommandBuffer,
    slot: &Slot,
    outputs: u32,
    len: usize,
    records: Option<(&ListBuffers, usize)>,
) {
    // The trace's writes, and a winding query's cap pass's.
    let shader_stage = trace_stage(ctx) | vk::PipelineStageFlags::COMPUTE_SHADER;
    let Some((_, hits_device)) = &slot.device else {
        let host = (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ);
        memory_barrier(ctx, cmd, (shader_stage, vk::AccessFlags::SHADER_WRITE), host);
        return;
    };
    memory_barrier(
        ctx,
        cmd,
        (shader_stage, vk::AccessFlags::SHADER_WRITE),
        (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_READ),
    );
    let regions: Vec<vk::BufferCopy> = FIELDS
        .iter()
        .filter(|f| outputs & f.bit() != 0)
        .map(|f| {
            let offset = slot.field_offset(*f) as u64;
            vk::BufferCopy::default()
                .src_offset(offset)
                .dst_offset(offset)
                .size((len * f.bytes_per_ray(slot.exact)) as u64)
        })
        .collect();
    // SAFETY: `cmd` is recording; each region lies within both buffers (same layout).
    unsafe { ctx.device.cmd_copy_buffer(cmd, hits_device.raw(), slot.hits_host.raw(), &regions) };
    if let Some((ListBuffers { records_host, records_device: Some(records_device), .. }, bytes)) = records {
        if bytes > 0 {
            let region = [vk::BufferCopy::default().size(bytes as u64)];
            // SAFETY: `cmd` is recording; both buffers hold at least `bytes` of records.
            unsafe { ctx.device.cmd_copy_buffer(cmd, records_device.raw(), records_host.raw(), &region) };
        }
    }
    memory_barrier(
        ctx,
        cmd,
        (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
        (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ),
    );
}

/// Checks and packs rays `start..start + len` (and their masks) into the slot's staging; rays the
/// shaders generate need nothing.
pub(super) fn pack_chunk(job: &GpuJob, slot: RayStaging, start: usize, len: usize) -> Result<Vec<Advance>> {
    if job.sensor.is_some() {
        return Ok(Vec::new());
    }
    let RayStaging { rays, layout: slot_layout, masks_at, exact } = slot;
    *slot_layout = RayLayout::Full;
    let packed = rays.mapped_mut().expect("ray staging is host-visible");
    let (rays_bytes, masks_bytes) = packed.split_at_mut(masks_at);
    if exact {
        // Plain rays in a leaner layout, which the shaders move into the scene's frame in f64.
        if let Some((layout, _)) = job.compact.filter(|(layout, _)| layout.exact_bytes(len) < len * RAY_FLOATS * 8) {
            let out: &mut [f32] = bytemuck::cast_slice_mut(&mut rays_bytes[..layout.exact_bytes(len)]);
            job.rays.pack_exact_compact(layout, start, out, job.frame.shift)?;
            *slot_layout = layout;
        } else {
            let out: &mut [f64] = bytemuck::cast_slice_mut(&mut rays_bytes[..len * RAY_FLOATS * 8]);
            job.rays.pack_f64(start, out, job.frame.shift)?;
        }
        pack_masks(job, masks_bytes, start, len);
        return Ok(Vec::new());
    }
    let refused = job.compact_refused.load(Ordering::Relaxed);
    let compact = job.compact.filter(|(layout, _)| !refused && layout.bytes(len) <= len * RAY_FLOATS * 4);
    let mut packed_compact = false;
    if let Some((layout, _)) = compact {
        let out: &mut [f32] = bytemuck::cast_slice_mut(&mut rays_bytes[..layout.bytes(len)]);
        packed_compact = job.rays.pack_compact(layout, start, out, &job.frame)?.is_some();
        job.compact_refused.store(!packed_compact, Ordering::Relaxed);
    }
    let advances = if packed_compact {
        Vec::new()
    } else {
        let out: &mut [f32] = bytemuck::cast_slice_mut(&mut rays_bytes[..len * RAY_FLOATS * 4]);
        job.rays.pack(start, out, &job.frame)?
    };
    pack_masks(job, masks_bytes, start, len);
    if let (true, Some((layout, _))) = (packed_compact, compact) {
        *slot_layout = layout;
    }
    Ok(advances)
}

/// The per-ray masks of rays `start..start + len`, one word each, where the rays have them.
fn pack_masks(job: &GpuJob, masks_bytes: &mut [u8], start: usize, len: usize) {
    if let Masks::Each(masks) = job.rays.mask {
        let words: &mut [u32] = bytemuck::cast_slice_mut(&mut masks_bytes[..4 * len]);
        parallel::install(|| {
            words.par_iter_mut().zip(&masks[start..start + len]).for_each(|(dst, m)| *dst = *m as u32)
        });
    }
}

/// A finished chunk: its timestamps into the profile, its hits into the caller's arrays.
fn finish_chunk(
    slot: &HitReadback,
    done: &InFlight,
    outputs: u32,
    sink: &mut HitSink,
    profile: &mut TraceProfile,
) -> Result<()> {
    if let Some(stamps) = slot.stamps {
        stamps.add_to(profile)?;
    }
    unpack(slot, done, outputs, sink);
    Ok(())
}

/// Copies a finished chunk's requested fields into the caller's arrays, on all cores, and adds
/// back to `t` how far each far ray was advanced before tracing.
fn unpack(slot: &HitReadback, done: &InFlight, outputs: u32, sink: &mut HitSink) {
    let InFlight { start, len, advances } = done;
    let (start, len) = (*start, *len);
    let hits = slot.hits.mapped().expect("hit readback is host-visible");
    for (field, out) in sink.iter_mut() {
        if outputs & field.bit() == 0 {
            continue;
        }
        let width = field.bytes_per_ray(slot.exact);
        let from = slot.field_offset(field);
        let out = &mut out[start * width..(start + len) * width];
        let src = &hits[from..from + len * width];
        parallel::copy(out, src);
        if field == Field::T && !slot.exact {
            let t: &mut [f32] = bytemuck::cast_slice_mut(out);
            for advance in advances {
                let hit = &mut t[advance.ray];
                if hit.is_finite() {
                    *hit = (*hit as f64 + advance.t) as f32;
                }
            }
        }
    }
    if let Some(hit) = sink.hit.as_deref_mut() {
        let from = slot.field_offset(Field::Prim);
        hits_from_prims(&hits[from..from + 4 * len], &mut hit[start..start + len]);
    }
}

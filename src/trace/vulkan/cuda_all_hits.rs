//! All hits of CUDA rays without the host: the caller's rays are copied device to device into
//! memory Vulkan shares with CUDA (as `cuda_rays.rs` copies them), packed chunk by chunk by
//! pack_rays.comp, and put through all_hits.rs's two passes; hit_columns.comp then writes each
//! chunk's columns, and each ray's offset among the query's hits, into the shared memory, from
//! which CUDA copies them into the caller's allocations. The host reads back two numbers a chunk
//! (its hits, and whether every list is settled) and waits for Vulkan only.
//!
//! A chunk whose lists the shaders cannot settle (a ray of more than 32 hits, whose list the host
//! sorts; a triangle traversal reported twice; a ray whose hits alone exceed a chunk's records) is
//! not answered here: the caller takes the query through the host instead
//! (`CudaAllHitsOutcome`). A chunk whose hits exceed its records stores the rays whose lists fit,
//! and the next chunk starts after them.

use std::mem::size_of;
use std::sync::Arc;
use std::time::Instant;

use ash::vk;

use super::all_hits::{one_part_meshes, rays_that_fit, record_budget, AllHitsPath, Counting, HitRecord};
use super::cuda_rays::{invalid_ray, CudaLease, CudaPlaces, CudaRays, CudaRaysPath};
use super::hit_lists::{ListBuffers, Placed};
use super::list_columns::{ChunkRays, ColumnTargets, GPU_COLUMN_FIELDS};
use super::packed_rays::{DevicePacking, DeviceRays};
use super::ray_chunks::{trace_stage, ChunkLists, GpuJob};
use super::shared::Shared;
use super::staging::Slot;
use super::timestamps::{start_stamps, Stamp};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::align::align_up;
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::gpu::context::{Commands, Timeline};
use crate::gpu::cuda::{Cuda, CudaAllocation, Event, LEGACY_STREAM};
use crate::gpu::memory::{memory_barrier, Buffer, MemoryLocation};
use crate::gpu::records::{ExactHit, FastHit};
use crate::scene::{Scene, VulkanScene};
use crate::trace::hit_fields::Field;
use crate::trace::pacer::ChunkPacer;
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Precision, Query, Request};

/// All hits of CUDA rays in CUDA memory: each ray's first hit among the query's (i64, one more
/// than the rays, the last the total), each hit's ray (i64) and the asked fields' columns
/// (f64 `t` and `uv` where `wide`), written once `ready` is reached.
pub struct CudaAllHits {
    pub offsets: CudaAllocation,
    pub ray_index: CudaAllocation,
    pub fields: Vec<(Field, CudaAllocation)>,
    pub hits: usize,
    pub ready: Arc<Event>,
    pub wide: bool,
}

/// What the GPU-resident all-hits path made of a query.
pub enum CudaAllHitsOutcome {
    Answered(CudaAllHits),
    /// A list the host must settle, more hits than a chunk's records hold, or no rays: the query
    /// goes through the host (why).
    ThroughHost(&'static str),
}

/// Why a query of CUDA rays cannot take the GPU-resident all-hits path, if it cannot: the fast
/// and exact tiers (exact: scenes of one-part meshes) of scenes without spheres, fields among
/// those hit_columns.comp writes, each once.
pub fn cuda_all_hits_refusal(scene: &Scene, request: Request, fields: &[Field]) -> Option<&'static str> {
    if fields.iter().any(|f| !GPU_COLUMN_FIELDS.contains(f))
        || fields.iter().enumerate().any(|(k, f)| fields[..k].contains(f))
    {
        return Some("all hits of CUDA rays write t, uv, prim_id, instance_id and geometry_id on the GPU, each once");
    }
    if scene.has_spheres() {
        return Some("the GPU does not store the hits of spheres");
    }
    match request.precision {
        Precision::Fast => None,
        Precision::Exact if one_part_meshes(scene) => None,
        Precision::Exact => Some("the exact tier's hits name their geometry on the GPU only in one-part meshes"),
        _ => Some("only precision='fast' and 'exact' store all hits on the GPU"),
    }
}

/// The GPU-resident all-hits path: the CUDA rays path's leases and copies, the all-hits path's
/// lists and kernels.
pub struct CudaAllHitsPath {
    cuda: CudaRaysPath,
    all_hits: Arc<AllHitsPath>,
}

impl CudaAllHitsPath {
    pub fn new(cuda: CudaRaysPath, all_hits: &Arc<AllHitsPath>) -> CudaAllHitsPath {
        CudaAllHitsPath { cuda, all_hits: all_hits.clone() }
    }

    /// Every hit of `rays` (CUDA memory, ordered before `lease`'s stream by the caller's
    /// producer) against `scene` in the fast or exact tier (the nearest `max_hits` of each ray),
    /// the `fields` asked written into new CUDA allocations. Errors name the first invalid ray
    /// as the numpy path does.
    #[allow(clippy::too_many_arguments)]
    pub fn trace(
        &self,
        scene: &Scene,
        lease: &mut CudaLease,
        rays: &CudaRays,
        request: Request,
        max_hits: usize,
        fields: &[Field],
        interrupt: &dyn Interrupt,
    ) -> Result<CudaAllHitsOutcome> {
        if let Some(why) = cuda_all_hits_refusal(scene, request, fields) {
            return Err(invalid_value(why));
        }
        if rays.count == 0 {
            return Ok(CudaAllHitsOutcome::ThroughHost("no rays"));
        }
        let cuda = self.cuda.cuda()?.expect("a lease implies CUDA");
        let places = CudaPlaces { home: &cuda, after: None, into: None };
        // Every ray at once (one signal): each chunk's packing reads its own rows.
        let (device_rays, wait) = self.cuda.copy_rays_in(&cuda, lease, rays, &places, rays.count)?;
        let placed = PlacedRays { cuda: &cuda, rays, device: &device_rays, ready: wait };
        let outcome = self.trace_placed(
            scene,
            lease,
            placed,
            Request { query: Query::All, ..request },
            max_hits,
            fields,
            interrupt,
        );
        if !matches!(outcome, Ok(CudaAllHitsOutcome::Answered(_))) {
            // Copies into allocations now dropped may be queued: they finish first.
            let _ = lease.stream.synchronize();
        }
        outcome
    }

    /// `trace` of rays copied into the lease's shared input.
    #[allow(clippy::too_many_arguments)]
    fn trace_placed(
        &self,
        scene: &Scene,
        lease: &mut CudaLease,
        placed: PlacedRays,
        request: Request,
        max_hits: usize,
        fields: &[Field],
        interrupt: &dyn Interrupt,
    ) -> Result<CudaAllHitsOutcome> {
        let shared = &*self.all_hits.shared;
        let _current = placed.cuda.enter()?;
        let offsets = shared.with_memory(|| CudaAllocation::new(&lease.stream, 8 * (placed.rays.count + 1)))?;
        let mut out = CudaColumns {
            shared,
            cuda: placed.cuda,
            lease,
            fields,
            wide: request.precision.is_f64(),
            offsets: Some(offsets),
            chunks: Vec::new(),
            free_at: placed.ready,
            hits: 0,
        };
        let outcome = self.trace_into(scene, &mut out, placed, (request, max_hits), interrupt);
        if !matches!(outcome, Ok(CudaAllHitsOutcome::Answered(_))) {
            // The copies queued into the query's allocations finish before they are freed (on
            // the legacy default stream, which does not wait for vkray's).
            let _ = out.lease.stream.synchronize();
        }
        outcome
    }

    /// Both passes over every chunk of the placed rays, written into `out`.
    fn trace_into(
        &self,
        scene: &Scene,
        out: &mut CudaColumns,
        placed: PlacedRays,
        (request, max_hits): (Request, usize),
        interrupt: &dyn Interrupt,
    ) -> Result<CudaAllHitsOutcome> {
        let started = Instant::now();
        let PlacedRays { cuda, rays, device, ready } = placed;
        let path = &*self.all_hits;
        let shared = &*path.shared;
        let exact = request.precision == Precision::Exact;
        let capacity = shared.chunk_capacity(rays.count).min(path.rays.packed.max_pack_rays());
        let packing = path.rays.packed.device_packing(scene, device, exact, capacity)?;
        let passes = DevicePasses {
            scene,
            request,
            max_hits,
            packing: &packing,
            rays: rays.count,
            mask: rays.mask,
            capacity,
            rays_ready: ready,
            interrupt,
        };
        let mut profile = TraceProfile { rays: rays.count, ..Default::default() };
        let traced = if exact {
            trace_on_device::<ExactHit>(path, &passes, out, &mut profile)
        } else {
            trace_on_device::<FastHit>(path, &passes, out, &mut profile)
        };
        profile.total = started.elapsed().as_secs_f64();
        shared.keep_profile(profile);
        let through_host = traced?;
        // (An invalid ray packed before a chunk that needs the host is named here all the same.)
        if let Some(row) = packing.first_invalid() {
            return Err(invalid_ray(cuda, rays, row));
        }
        if let Some(why) = through_host {
            return Ok(CudaAllHitsOutcome::ThroughHost(why));
        }
        shared.ctx.check_validation()?;
        out.finish().map(CudaAllHitsOutcome::Answered)
    }
}

/// A query's CUDA rays, copied into the lease's shared input: the CUDA device, the caller's
/// rays, where the GPU reads them, and the semaphore's value once they are there.
struct PlacedRays<'a> {
    cuda: &'a Arc<Cuda>,
    rays: &'a CudaRays,
    device: &'a DeviceRays,
    ready: u64,
}

/// What every chunk of a GPU-resident all-hits query shares.
struct DevicePasses<'a> {
    scene: &'a Scene,
    request: Request,
    max_hits: usize,
    packing: &'a DevicePacking<'a>,
    rays: usize,
    mask: u8,
    capacity: usize,
    /// The semaphore's value once the rays are in place.
    rays_ready: u64,
    interrupt: &'a dyn Interrupt,
}

/// Both passes over every chunk of `passes`' rays, each chunk's columns into `out`; Some(why)
/// where a chunk needs the host.
fn trace_on_device<R: HitRecord>(
    path: &AllHitsPath,
    passes: &DevicePasses,
    out: &mut CudaColumns,
    profile: &mut TraceProfile,
) -> Result<Option<&'static str>> {
    let shared = &*path.shared;
    let ctx = &shared.ctx;
    let scene = passes.scene;
    let exact = passes.request.precision == Precision::Exact;
    ctx.check_usable()?;
    // Held across both passes, so that the lists the first sizes are the second's.
    let _in_use = scene.hold_meshes();
    scene.check_current()?;
    path.rays.probes.check_paths(scene, exact)?;
    let exact_scene = if exact { Some(VulkanScene::of(scene)?.exact(scene)?) } else { None };
    let outputs = Field::Prim.bit();
    let count = Request { query: Query::Count, ..passes.request };
    let counting_variant = shared.variants.get(shared.variant_key(scene, count, exact, outputs, false))?;
    let storing_variant = shared.variants.get(shared.variant_key(scene, passes.request, exact, outputs, false))?;
    // The rays' mask: the rays themselves are packed on the device (`packed_on_device`).
    let mask = Rays {
        origins: Vec3s::F32(&[]),
        directions: Vec3s::F32(&[]),
        tmin: PerRay::All(0.0),
        tmax: PerRay::All(0.0),
        mask: Masks::All(passes.mask),
        sensor: None,
    };
    let hierarchy = VulkanScene::of(scene)?;
    let job = |variant| GpuJob {
        hierarchy,
        exact: exact_scene.as_deref(),
        rays: &mask,
        variant,
        compact: None,
        compact_refused: Default::default(),
        outputs,
        frame: scene.frame(),
        all_hits: true,
        sensor: None,
        cap: None,
        t_is_distance: true,
        packed_on_device: Some(passes.packing.rays_address()),
    };
    let jobs = (job(&counting_variant), job(&storing_variant));
    let record_bytes = (record_budget(ctx.unified_memory) / size_of::<R>()).max(1) * size_of::<R>();
    let usage = vk::BufferUsageFlags::STORAGE_BUFFER
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS
        | vk::BufferUsageFlags::TRANSFER_DST;
    let check = Buffer::new(ctx, 16, usage, MemoryLocation::GpuToCpu, "hit columns' check")?;
    let pipeline = path.columns.pipeline(R::WIDE)?;
    let slots = shared.with_memory(|| shared.slots.take(passes.capacity, exact))?;
    let lists = match shared.with_memory(|| path.take_lists(passes.capacity, record_bytes)) {
        Ok(lists) => lists,
        Err(error) => {
            shared.slots.give_back(slots);
            return Err(error);
        }
    };
    let chunks = DeviceChunks {
        path,
        passes,
        jobs: (&jobs.0, &jobs.1),
        slot: &slots[0],
        lists: &lists,
        room: record_bytes / size_of::<R>(),
        check: &check,
        pipeline,
    };
    // (The commands wait for their work in flight, after an error, before the memory goes.)
    let result = Commands::new(ctx).and_then(|mut commands| chunks.run(&mut commands, out, profile));
    shared.slots.give_back(slots);
    path.give_back_lists(vec![lists]);
    result
}

/// The chunk loop of `trace_on_device`: what its chunks share.
struct DeviceChunks<'a> {
    path: &'a AllHitsPath,
    passes: &'a DevicePasses<'a>,
    /// The counting pass's job and the storing pass's.
    jobs: (&'a GpuJob<'a>, &'a GpuJob<'a>),
    slot: &'a Slot,
    lists: &'a ListBuffers,
    /// Records the lists hold.
    room: usize,
    /// Host-visible: hit_columns.comp's check (a list not settled).
    check: &'a Buffer,
    pipeline: vk::Pipeline,
}

impl DeviceChunks<'_> {
    /// Chunk after chunk, each sized by the time the last took: counted, then stored and written
    /// into `out`; Some(why) where a chunk needs the host.
    fn run(
        &self,
        commands: &mut Commands,
        out: &mut CudaColumns,
        profile: &mut TraceProfile,
    ) -> Result<Option<&'static str>> {
        let passes = self.passes;
        let ctx = &self.path.shared.ctx;
        let n = passes.rays;
        let mut pacer = ChunkPacer::on_device(passes.capacity, ctx.info.is_software);
        let mut start = 0;
        while start < n {
            passes.interrupt.check()?;
            let len = pacer.next_len(n - start);
            pacer.started();
            let Placed { mut total, storing } = self.count(commands, out, (start, len), profile)?;
            let mut stored = len;
            if total > self.room as u64 {
                // Only the rays whose lists fit in the records (as the numpy path cuts a chunk).
                let firsts = self.read_offsets(commands, len, profile)?;
                stored = rays_that_fit(firsts, self.room as u64);
                if stored == 0 {
                    return Ok(Some("a ray's hits exceed a chunk's records"));
                }
                total = firsts[stored];
            }
            self.store(commands, out, (start, stored, len), (total as usize, storing), profile)?;
            pacer.finished(stored);
            profile.chunks += 1;
            let check: &[u32] = bytemuck::cast_slice(&self.check.mapped().expect("host-visible")[..4]);
            if check[0] != 0 {
                return Ok(Some("a list the shaders did not settle"));
            }
            profile.gpu_columns += 1;
            start += stored;
            passes.interrupt.progress(start, n);
        }
        Ok(None)
    }

    /// Packs and counts rays `start..start + len` and places their lists (list_offsets.comp);
    /// returns what the host reads back: the chunk's hits, and whether any ray needs the storing
    /// pass.
    fn count(
        &self,
        commands: &mut Commands,
        out: &CudaColumns,
        (start, len): (usize, usize),
        profile: &mut TraceProfile,
    ) -> Result<Placed> {
        let submitting = Instant::now();
        let ctx = &self.path.shared.ctx;
        let (slot, lists) = (self.slot, self.lists);
        commands.begin()?;
        let cmd = commands.buffer;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        self.passes.packing.record_pack(cmd, start, len, trace_stage(ctx));
        stamp(Stamp::Uploaded);
        let counting = Counting { job: self.jobs.0, slot, lists, max_hits: self.passes.max_hits, room: self.room };
        self.path.record_counting(cmd, &counting, (start, len), &stamp)?;
        let timeline = Timeline { semaphore: out.lease.vulkan_semaphore(), wait: self.passes.rays_ready, signal: None };
        commands.submit_ordered(Some(timeline))?;
        let waiting = Instant::now();
        profile.submit += (waiting - submitting).as_secs_f64();
        commands.wait()?;
        profile.wait += waiting.elapsed().as_secs_f64();
        if let Some(stamps) = &slot.stamps {
            stamps.add_to(profile)?;
        }
        Ok(lists.read_placed())
    }

    /// The first `len` rays' lists' first records among the chunk's, back on the host.
    fn read_offsets(&self, commands: &mut Commands, len: usize, profile: &mut TraceProfile) -> Result<&[u64]> {
        commands.begin()?;
        self.path.offsets.record_offsets(commands.buffer, self.lists, len);
        commands.submit()?;
        let waiting = Instant::now();
        commands.wait()?;
        profile.wait += waiting.elapsed().as_secs_f64();
        Ok(self.lists.read_offsets(len))
    }

    /// Stores the hits of the first `len` of the `counted` rays from `start` (`total`; the
    /// storing pass where `storing`) and writes them into `out` as columns, with each ray's
    /// offset among the query's hits and far rays' advances added back; CUDA's copies out are
    /// queued behind the submission.
    fn store(
        &self,
        commands: &mut Commands,
        out: &mut CudaColumns,
        (start, len, counted): (usize, usize, usize),
        (total, storing): (usize, bool),
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let storing_started = Instant::now();
        let ctx = &self.path.shared.ctx;
        let (slot, lists) = (self.slot, self.lists);
        let targets = out.room(len, total)?;
        commands.begin()?;
        let cmd = commands.buffer;
        if storing {
            self.path.rays.chunks.record_trace(cmd, self.jobs.1, slot, start, len, ChunkLists::Lists(lists));
        }
        let seen = slot.hits_address() + slot.field_offset(Field::Prim) as u64;
        let rays = ChunkRays { first: start, len, counted, seen, max_hits: self.passes.max_hits };
        self.path.columns.record_into(cmd, self.pipeline, lists, &targets, (self.check, 0), rays, trace_stage(ctx));
        self.passes.packing.record_finish_hits(cmd, start, total, (targets.t, targets.ray_index));
        let compute = (vk::PipelineStageFlags::COMPUTE_SHADER, vk::AccessFlags::SHADER_WRITE);
        memory_barrier(ctx, cmd, compute, (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ));
        let timeline = out.store_timeline();
        commands.submit_ordered(Some(timeline))?;
        out.queue_copies(start, len, total, timeline.signal.expect("a signal"))?;
        let waiting = Instant::now();
        commands.wait()?;
        profile.wait += waiting.elapsed().as_secs_f64();
        profile.store += storing_started.elapsed().as_secs_f64();
        Ok(())
    }
}

/// A chunk's columns in the lease's shared output: each ray's offset (and the end), each hit's
/// ray, then each asked field's column, each aligned.
struct OutputLayout {
    ray_index: u64,
    fields: Vec<u64>,
    bytes: u64,
}

impl OutputLayout {
    fn new(fields: &[Field], wide: bool, len: usize, hits: usize) -> OutputLayout {
        let ray_index = align_up(8 * (len as u64 + 1), SHARED_ALIGN);
        let mut at = align_up(ray_index + 8 * hits as u64, SHARED_ALIGN);
        let fields = fields
            .iter()
            .map(|f| {
                let placed = at;
                at = align_up(at + (hits * f.bytes_per_ray(wide)) as u64, SHARED_ALIGN);
                placed
            })
            .collect();
        OutputLayout { ray_index, fields, bytes: at.max(1) }
    }
}

/// Alignment of each column within the shared output.
const SHARED_ALIGN: u64 = 256;

/// One chunk's hits in CUDA memory: their rays, and their columns in the order asked.
struct ChunkColumns {
    ray_index: CudaAllocation,
    columns: Vec<CudaAllocation>,
}

/// Where a GPU-resident all-hits query's columns go: chunk by chunk through the lease's shared
/// output, copied by its stream into CUDA allocations (the offsets into one of the query's).
struct CudaColumns<'a> {
    shared: &'a Shared,
    cuda: &'a Arc<Cuda>,
    lease: &'a mut CudaLease,
    fields: &'a [Field],
    wide: bool,
    /// i64 per ray and one more (taken by `finish`).
    offsets: Option<CudaAllocation>,
    /// Each chunk's hits.
    chunks: Vec<ChunkColumns>,
    /// The semaphore's value once the shared output is free (the last chunk's copies out of it
    /// done; at first, the rays copied in).
    free_at: u64,
    /// Hits of the chunks so far.
    hits: usize,
}

impl CudaColumns<'_> {
    /// The addresses hit_columns.comp writes a chunk of `len` rays and `hits` hits to.
    fn room(&mut self, len: usize, hits: usize) -> Result<ColumnTargets> {
        let layout = OutputLayout::new(self.fields, self.wide, len, hits);
        self.lease.grow_output(self.shared, self.cuda, layout.bytes)?;
        let base = self.lease.output().vulkan.address();
        let field = |wanted: Field| {
            self.fields.iter().zip(&layout.fields).find(|(f, _)| **f == wanted).map_or(0, |(_, at)| base + at)
        };
        Ok(ColumnTargets {
            ray_index: base + layout.ray_index,
            t: field(Field::T),
            uv: field(Field::Uv),
            prim: field(Field::Prim),
            instance: field(Field::Instance),
            geometry: field(Field::Geometry),
            offsets_out: base,
            base: self.hits as u64,
        })
    }

    /// What a chunk's storing submission waits for (the shared output free) and signals (its
    /// columns written).
    fn store_timeline(&mut self) -> Timeline {
        let signal = self.lease.next_value();
        Timeline { semaphore: self.lease.vulkan_semaphore(), wait: self.free_at, signal: Some(signal) }
    }

    /// Queues, once the semaphore reaches `written`, the copies of a chunk's columns (rays
    /// `start..start + len`, `hits` hits) out of the shared output: its offsets into the query's,
    /// its hits' rays and columns into new allocations; then signals the output free.
    fn queue_copies(&mut self, start: usize, len: usize, hits: usize, written: u64) -> Result<()> {
        let layout = OutputLayout::new(self.fields, self.wide, len, hits);
        let lease = &*self.lease;
        let (stream, output) = (&lease.stream, lease.output().pointer);
        lease.wait_on_stream(written)?;
        let copy = |dst: u64, src: u64, bytes: usize| -> Result<()> {
            if bytes == 0 {
                return Ok(());
            }
            // SAFETY: both are device memory of this context with room for `bytes` (the output
            // laid out as `layout`, the destinations made for these bytes), live until the copy
            // runs: the allocations are the query's, the output stays in the lease, whose later
            // users queue on the same stream.
            unsafe { stream.copy_2d(dst, bytes, src, bytes, bytes, 1) }
        };
        let offsets = self.offsets.as_ref().expect("taken by finish only");
        copy(offsets.pointer + 8 * start as u64, output, 8 * (len + 1))?;
        let shared = self.shared;
        let allocate = |bytes: usize| shared.with_memory(|| CudaAllocation::new(stream, bytes));
        let ray_index = allocate(8 * hits)?;
        copy(ray_index.pointer, output + layout.ray_index, 8 * hits)?;
        let mut columns = Vec::new();
        for (field, at) in self.fields.iter().zip(&layout.fields) {
            let bytes = hits * field.bytes_per_ray(self.wide);
            let column = allocate(bytes)?;
            copy(column.pointer, output + at, bytes)?;
            columns.push(column);
        }
        self.chunks.push(ChunkColumns { ray_index, columns });
        self.hits += hits;
        let free = self.lease.next_value();
        self.lease.signal_on_stream(free)?;
        self.free_at = free;
        Ok(())
    }

    /// The query's answer: each column joined from its chunks' (in the stream's order; the
    /// chunks' own freed after the copies, on the legacy default stream made to wait for them).
    fn finish(&mut self) -> Result<CudaAllHits> {
        let mut chunks = std::mem::take(&mut self.chunks);
        let (shared, stream, hits, wide) = (self.shared, &self.lease.stream, self.hits, self.wide);
        let (ray_index, columns) = if chunks.len() == 1 {
            let only = chunks.pop().expect("one chunk");
            (only.ray_index, only.columns)
        } else {
            // Column k's (None: the hits' rays).
            let join = |bytes_per_hit: usize, column: Option<usize>| {
                let joined = shared.with_memory(|| CudaAllocation::new(stream, hits * bytes_per_hit))?;
                let mut at = joined.pointer;
                for chunk in &chunks {
                    let piece = column.map_or(&chunk.ray_index, |k| &chunk.columns[k]);
                    if piece.bytes > 0 {
                        // SAFETY: both are device memory of this context, the joined array with
                        // room for every chunk's piece; the pieces are freed only after the
                        // stream's copies (below, or the caller's synchronize on failure).
                        unsafe { stream.copy_2d(at, piece.bytes, piece.pointer, piece.bytes, piece.bytes, 1)? };
                    }
                    at += piece.bytes as u64;
                }
                Ok::<_, Error>(joined)
            };
            let joined = join(8, None).and_then(|ray_index| {
                let columns = (0..self.fields.len())
                    .map(|k| join(self.fields[k].bytes_per_ray(wide), Some(k)))
                    .collect::<Result<Vec<_>>>()?;
                Ok((ray_index, columns))
            });
            match joined {
                Ok(joined) => joined,
                Err(error) => {
                    // The pieces go with this frame: the copies reading them finish first.
                    let _ = stream.synchronize();
                    return Err(error);
                }
            }
        };
        let ready = Arc::new(stream.record()?);
        if !chunks.is_empty() {
            // The pieces are freed on the legacy default stream: after the copies out of them.
            ready.order_before(LEGACY_STREAM)?;
        }
        let offsets = self.offsets.take().expect("finished once");
        let fields = self.fields.iter().copied().zip(columns).collect();
        Ok(CudaAllHits { offsets, ray_index, fields, hits, ready, wide })
    }
}

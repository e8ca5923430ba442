//! All hits of each ray on the GPU (fast and exact tiers), chunk by chunk. Each chunk's rays are
//! packed once. A counting pass (the all-hits shaders with fixed lists of a few records a ray)
//! finds how many hits each ray meets and keeps its nearest few; list_offsets.comp turns the
//! counts into each ray's list among the chunk's records and copies into place the hits of rays
//! the counting pass kept whole, all in one submission; the host reads back only the chunk's
//! total (and the offsets, where the records have no room for every ray's). A storing pass then
//! keeps the hits (the nearest `max_hits`) of the other rays, sorted, in their lists, if there
//! are any. Then either the records come back with their offsets, straight after the chunks
//! before (`gpu_all_hits`), or hit_columns.comp writes them out as the answer's columns, which
//! come back instead and are copied once (`gpu_all_hit_columns`); there the offsets come back
//! only where a list is not settled (hit_columns.comp checks each), the host placing them from
//! each ray's hits otherwise. Memory is bounded by the chunks
//! (a chunk whose records do not fit stores only the rays whose lists do) and nothing is
//! truncated.

use std::cmp::Ordering;
use std::mem::size_of;
use std::time::Instant;

use ash::vk;
use bytemuck::Pod;
use rayon::prelude::*;

use super::gpu_rays::GpuRays;
use super::hit_lists::{appends, ListBuffers, ListOffsets, Placed};
use super::list_columns::{ChunkRays, ColumnLayout, ListColumns, GPU_COLUMN_FIELDS};
use super::ray_chunks::{pack_chunk, record_readback, trace_stage, ChunkLists, GpuJob};
use super::shared::Shared;
use super::staging::Slot;
use super::timestamps::{start_stamps, Stamp};
use crate::error::{Error, Result};
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::geometry::parallel::try_zeroed;
use crate::geometry::rays::Advance;
use crate::geometry::reference::ReferenceHit;
use crate::gpu::context::Commands;
use crate::gpu::memory::memory_barrier;
use crate::gpu::records::{ExactHit, FastHit};
use crate::scene::{Scene, VulkanScene};
use crate::trace::hit_columns::{AskedColumn, HitColumn, HitColumns};
use crate::trace::hit_fields::Field;
use crate::trace::host_tiers::{check_hits_fit, AllHits};
use crate::trace::idle::{IdlePool, SpareRecords};
use crate::trace::pacer::{in_paced_blocks, ChunkPacer, FIRST_ON_CPU};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Precision, Query, RayBatch, Request};
use std::sync::Arc;

/// What the storing pass found: ray i's hits are `records[offsets[i]..offsets[i + 1]]` (the CPU
/// tracer's records, each turned into one as it came back), of which the first `seen[i]` are
/// written where `seen[i]` is smaller (a primitive traversal reported twice, kept once);
/// `advances` holds (ray, t) for far rays packed from nearer origins (fast tier), whose records'
/// `t` is short by `t`.
struct StoredHits {
    offsets: Vec<i64>,
    records: Vec<ReferenceHit>,
    seen: Vec<i32>,
    advances: Vec<(usize, f64)>,
    /// Some list needs the host: appended (sorted by the host), or written short.
    unsettled: bool,
    /// The first ray that met more hits storing than counting (a driver's fault), if any.
    overflowed: Option<usize>,
    /// The columns' way (`gpu_all_hit_columns`): each chunk's hits go straight into the answer's
    /// columns, and `records` stays empty.
    columns: Option<ColumnWay>,
}

/// The answer's columns, chunk by chunk: each stored chunk's hits (their rays and columns) a
/// segment of its own, copied from the columns hit_columns.comp wrote where every list of the
/// chunk is settled, else written from its records once the host settled them. The segments are
/// joined once at the end (on all cores): growing one array chunk by chunk copied it again each
/// time it grew (16M camera rays on an H200: 50 of 82 ms).
struct ColumnWay {
    asked: Vec<Field>,
    wide: bool,
    /// The columns, a segment at a time.
    segments: Vec<Segment>,
    /// Hits stored so far.
    hits: usize,
}

/// Some chunks' hits: their columns in the order asked, with room for `room` hits.
struct Segment {
    hits: usize,
    room: usize,
    columns: Vec<HitColumn>,
}

impl ColumnWay {
    /// No columns yet of the `asked` fields (f64 t and uv where `wide`).
    fn new(asked: &[Field], wide: bool) -> ColumnWay {
        ColumnWay { asked: asked.to_vec(), wide, segments: Vec::new(), hits: 0 }
    }

    /// A chunk's `total` hits as hit_columns.comp wrote them (`written`, laid out as
    /// `layout`; `offsets`, its rays' among the query's, and where the last ray's end), each
    /// column copied once on all cores into the last segment where it has room,
    /// else into a new one with room for `room` hits (the query's rate of hits so far, for the
    /// rays left); with the advances of far rays (chunk's ray, t) added back to their hits' t, as
    /// `StoredHits::settled` does.
    fn append_written(
        &mut self,
        written: &[u8],
        layout: &ColumnLayout,
        offsets: &[i64],
        (total, room): (usize, usize),
        advances: &[(usize, f64)],
    ) -> Result<()> {
        let fits = self.segments.last().is_some_and(|s| s.room - s.hits >= total);
        if !fits {
            let room = room.max(total);
            let columns = self.asked.iter().map(|&f| HitColumn::with_room(Some(f), room, self.wide));
            self.segments.push(Segment { hits: 0, room, columns: columns.collect::<Result<_>>()? });
        }
        let segment = self.segments.last_mut().expect("a segment with room");
        let before = segment.hits;
        segment.hits += total;
        let columns = &mut segment.columns;
        for (column, &(_, at, bytes)) in columns.iter_mut().zip(&layout.fields) {
            column.extend_from_bytes(&written[at..at + bytes]);
        }
        if let Some(k) = self.asked.iter().position(|&f| f == Field::T) {
            // (The chunk's offsets start at its first hit's among the query's.)
            let first = |ray: usize| before + (offsets[ray] - offsets[0]) as usize;
            for &(ray, t) in advances {
                let hits = first(ray)..first(ray + 1);
                match &mut columns[k] {
                    HitColumn::F32(v, _) => v[hits].iter_mut().for_each(|h| *h = (*h as f64 + t) as f32),
                    HitColumn::F64(v, _) => v[hits].iter_mut().for_each(|h| *h = (*h + t) as f32 as f64),
                    HitColumn::I32(_) => unreachable!("t is a float column"),
                }
            }
        }
        self.hits += total;
        Ok(())
    }

    /// The asked fields as the host's writer names them.
    fn asked_columns(&self) -> Vec<AskedColumn> {
        self.asked.iter().map(|&f| Some(f)).collect()
    }

    /// Room for the hits of `rays` more rays at `rate` hits a ray, and a tenth more.
    fn hits_left(&self, rate: f64, rays: usize) -> usize {
        (rate * rays as f64 * 1.1) as usize
    }

    /// The segments joined: the asked columns.
    fn joined(self) -> Result<Vec<HitColumn>> {
        let ColumnWay { asked, wide, mut segments, .. } = self;
        if segments.len() == 1 {
            return Ok(segments.pop().expect("one segment").columns);
        }
        let mut columns: Vec<Vec<HitColumn>> = asked.iter().map(|_| Vec::with_capacity(segments.len())).collect();
        for segment in segments {
            for (parts, column) in columns.iter_mut().zip(segment.columns) {
                parts.push(column);
            }
        }
        asked.iter().zip(columns).map(|(&field, parts)| HitColumn::joined(Some(field), parts, wide)).collect()
    }
}

/// Bytes of hit records a chunk may hold: CPU devices share the host's memory. `VKRAY_HIT_RECORD_BYTES`
/// sets another (the tests' way to chunks that store part of their rays).
pub(super) fn record_budget(unified_memory: bool) -> usize {
    let set = std::env::var("VKRAY_HIT_RECORD_BYTES").ok().and_then(|v| v.parse().ok());
    set.unwrap_or(if unified_memory { 64 << 20 } else { 256 << 20 })
}

/// Idle lists kept between queries: as many as were in use at once, at least one and at most
/// two (each holds its chunk's nearest hits, the records on the device and their host copy, and
/// the columns on the device and their host copy: five times `IDLE_RECORD_BYTES` at most), each
/// of at most `IDLE_RECORD_BYTES` of records and of columns.
pub const IDLE_LISTS: (usize, usize) = (1, 2);
const IDLE_RECORD_BYTES: usize = 256 << 20;

/// The all-hits path. Owns the idle lists and records of the storing pass and the kernel that
/// places the lists.
pub struct AllHitsPath {
    pub(super) shared: Arc<Shared>,
    pub(super) rays: Arc<GpuRays>,
    lists: Arc<IdlePool<ListBuffers>>,
    spare: Arc<SpareRecords>,
    pub(super) offsets: ListOffsets,
    pub(super) columns: ListColumns,
}

/// A query's two passes over each chunk: the counting pass's job and the storing pass's, which
/// read the same packed rays.
struct Passes<'a> {
    scene: &'a Scene,
    counting: GpuJob<'a>,
    storing: GpuJob<'a>,
    max_hits: usize,
    /// What the caller will need per hit besides the records (`check_hits_fit`).
    host_bytes_per_hit: usize,
    interrupt: &'a dyn Interrupt,
}

impl AllHitsPath {
    pub fn new(
        shared: &Arc<Shared>,
        rays: &Arc<GpuRays>,
        lists: &Arc<IdlePool<ListBuffers>>,
        spare: &Arc<SpareRecords>,
    ) -> Result<AllHitsPath> {
        let offsets = ListOffsets::new(&shared.ctx)?;
        let columns = ListColumns::new(&shared.ctx)?;
        Ok(AllHitsPath {
            shared: shared.clone(),
            rays: rays.clone(),
            lists: lists.clone(),
            spare: spare.clone(),
            offsets,
            columns,
        })
    }

    /// Takes back the records of an answer its caller is done with, for the next query.
    pub fn recycle(&self, hits: Vec<ReferenceHit>) {
        self.spare.keep(hits);
    }

    /// Every hit of every ray (the nearest `max_hits` of each) as the GPU tier `request` names
    /// (fast: `R` = `FastHit`; exact: `ExactHit`). `host_bytes_per_hit`: what the caller will
    /// need per hit besides the records, for checking that the result fits before storing it.
    pub fn gpu_all_hits<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        host_bytes_per_hit: usize,
    ) -> Result<AllHits> {
        let started = Instant::now();
        let mut profile = TraceProfile { rays: batch.rays.len(), ..Default::default() };
        let stored = self.store::<R>(batch, max_hits, host_bytes_per_hit, None, &mut profile)?;
        let settling = Instant::now();
        let (offsets, records) = stored.settled(max_hits, batch.interrupt)?;
        profile.unpack += settling.elapsed().as_secs_f64();
        profile.total = started.elapsed().as_secs_f64();
        self.shared.keep_profile(profile);
        self.shared.ctx.check_validation()?;
        Ok(AllHits { offsets, hits: records, wide: R::WIDE })
    }

    /// `gpu_all_hits` written straight into the answer's columns of the `asked` fields (among
    /// `GPU_COLUMN_FIELDS`; the exact tier's `ExactHit`s only on scenes of one-part meshes),
    /// each hit's ray beside them: hit_columns.comp writes each chunk's columns, which the host
    /// copies once (the records of a chunk with a list the shaders could not settle come back
    /// and are written out by the host, as `gpu_all_hits` would).
    pub fn gpu_all_hit_columns<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        asked: &[Field],
    ) -> Result<HitColumns> {
        let started = Instant::now();
        let mut profile = TraceProfile { rays: batch.rays.len(), ..Default::default() };
        let way = ColumnWay::new(asked, R::WIDE);
        let stored = self.store::<R>(batch, max_hits, 0, Some(way), &mut profile)?;
        let StoredHits { offsets, columns, .. } = stored;
        let columns = columns.expect("stored the columns' way").joined()?;
        profile.total = started.elapsed().as_secs_f64();
        self.shared.keep_profile(profile);
        self.shared.ctx.check_validation()?;
        Ok(HitColumns { offsets, columns })
    }

    /// Both passes over the batch's rays, their hits stored as records or (`columns`) columns.
    fn store<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        host_bytes_per_hit: usize,
        columns: Option<ColumnWay>,
        profile: &mut TraceProfile,
    ) -> Result<StoredHits> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        self.shared.ctx.check_usable()?;
        rays.check_shapes()?;
        let n = rays.len();
        // Held across both passes, so that the lists the first sizes are the second's.
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        self.rays.probes.check_paths(scene, request.precision == Precision::Exact)?;
        let mut stored = StoredHits {
            offsets: try_zeroed(n + 1, "the hits' offsets")?,
            records: if columns.is_some() { Vec::new() } else { self.spare.take() },
            seen: try_zeroed(n, "the hits' counts")?,
            advances: Vec::new(),
            unsettled: false,
            overflowed: None,
            columns,
        };
        if n > 0 {
            self.trace_lists::<R>(batch, max_hits, host_bytes_per_hit, &mut stored, profile)?;
        }
        if let Some(i) = stored.overflowed {
            let (offsets, seen) = (&stored.offsets, &stored.seen);
            return Err(Error::Internal(format!(
                "ray {i} met {} hits in the storing pass, {} in the counting pass",
                seen[i],
                offsets[i + 1] - offsets[i]
            )));
        }
        interrupt.check()?;
        Ok(stored)
    }

    /// Both passes over every chunk of the batch's rays, in two sets of staging and lists that
    /// take turns (the second set's lists made when a second chunk needs them).
    fn trace_lists<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        host_bytes_per_hit: usize,
        stored: &mut StoredHits,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let shared = &*self.shared;
        let exact = request.precision == Precision::Exact;
        let exact_scene = if exact { Some(VulkanScene::of(scene)?.exact(scene)?) } else { None };
        let outputs = Field::Prim.bit();
        let (count, all) = (Request { query: Query::Count, ..request }, Request { query: Query::All, ..request });
        let (counting_variant, sensor) = shared.gpu_variant(scene, rays, count, exact, outputs)?;
        let storing_variant = shared.variants.get(shared.variant_key(scene, all, exact, outputs, sensor.is_some()))?;
        let compact = |request| shared.compact_variant(scene, rays, request, outputs, exact, sensor.is_some());
        let (counting_compact, storing_compact) = match (compact(count)?, compact(all)?) {
            // Both passes read the rays as packed once: compact only where both variants can.
            (Some(a), Some(b)) if a.0 == b.0 => (Some(a), Some(b)),
            _ => (None, None),
        };
        let job = |variant, compact: Option<(_, _)>| GpuJob {
            hierarchy: VulkanScene::of(scene).expect("checked by gpu_variant"),
            exact: exact_scene.as_deref(),
            rays,
            variant,
            compact,
            compact_refused: Default::default(),
            outputs,
            frame: scene.frame(),
            all_hits: true,
            sensor: sensor.as_ref(),
            cap: None,
            t_is_distance: true,
            packed_on_device: None,
        };
        let passes = Passes {
            scene,
            counting: job(&counting_variant, counting_compact.as_ref().map(|(layout, v)| (*layout, &**v))),
            storing: job(&storing_variant, storing_compact.as_ref().map(|(layout, v)| (*layout, &**v))),
            max_hits,
            host_bytes_per_hit,
            interrupt,
        };
        let ray_capacity = shared.chunk_capacity(rays.len());
        let record_bytes = (record_budget(shared.ctx.unified_memory) / size_of::<R>()).max(1) * size_of::<R>();
        let mut slots = shared.with_memory(|| shared.slots.take(ray_capacity, exact))?;
        let lists = match shared.with_memory(|| self.take_lists(ray_capacity, record_bytes)) {
            Ok(lists) => lists,
            Err(error) => {
                shared.slots.give_back(slots);
                return Err(match error {
                    // Before any hit is counted: a chunk's records come back through memory the
                    // host maps (NVIDIA's driver fails it first under an address-space limit).
                    Error::OutOfMemory(why) => Error::OutOfMemory(format!(
                        "the hits of this query need room for a chunk's records ({:.2} GB, in memory the \
                         host reads) and its rays' lists, which could not be allocated ({why}): trace \
                         fewer rays at a time or set max_hits",
                        record_bytes as f64 / 1e9
                    )),
                    other => other,
                });
            }
        };
        let room = record_bytes / size_of::<R>();
        let [first, second] = &mut slots;
        let mut sets = match (Commands::new(&shared.ctx), Commands::new(&shared.ctx)) {
            (Ok(a), Ok(b)) => [
                ChunkSet { slot: first, lists: Some(lists), room, commands: a },
                ChunkSet { slot: second, lists: None, room, commands: b },
            ],
            (Err(error), _) | (_, Err(error)) => {
                shared.slots.give_back(slots);
                self.give_back_lists(vec![lists]);
                return Err(error);
            }
        };
        let result = self.trace_chunks::<R>(&passes, &mut sets, record_bytes, stored, profile);
        // Each set's commands wait for their work in flight (after an error) before its memory goes.
        let lists: Vec<ListBuffers> = sets.into_iter().filter_map(|set| set.lists).collect();
        shared.slots.give_back(slots);
        self.give_back_lists(lists);
        result
    }

    /// Chunk after chunk, each sized by the time the last took, in two sets that take turns:
    /// while the GPU stores one chunk's hits the host packs the next chunk's rays, and while it
    /// counts the next chunk's hits the host copies out the stored ones (the host's passes beside
    /// the GPU's; besides the next chunk's counting pass, only a copy of a chunk's records for
    /// the host to settle, in its own set's memory, may be in flight).
    fn trace_chunks<R: HitRecord>(
        &self,
        passes: &Passes,
        sets: &mut [ChunkSet; 2],
        record_bytes: usize,
        stored: &mut StoredHits,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let n = stored.seen.len();
        let interrupt = passes.interrupt;
        // Idle lists and slots may hold more rays than the device's chunk allows.
        let lists_rays = sets[0].lists.as_ref().map_or(0, |l| l.rays);
        let capacity =
            lists_rays.min(sets[0].slot.capacity).min(sets[1].slot.capacity).min(self.shared.chunk_capacity(n));
        let mut pacer = ChunkPacer::on_device(capacity, self.shared.ctx.info.is_software);
        let [mut set, mut other] = sets.each_mut();
        let len = pacer.next_len(n);
        pacer.started();
        let mut pending = (0, len, self.pack_rays(passes, set, 0, len, profile)?);
        self.submit_count(passes, set, (0, len), profile)?;
        loop {
            interrupt.check()?;
            let (start, len, advances) = pending;
            let Some(chunk) = self.finish_count::<R>(set, (start, len), advances, profile)? else {
                // Records grown to hold the first ray's hits: its chunk is counted again.
                pending = (start, len, self.pack_rays(passes, set, start, len, profile)?);
                self.submit_count(passes, set, (start, len), profile)?;
                continue;
            };
            // A chunk's turn: from one chunk counted to the next (the next chunk's length, sized
            // by it, is chosen now).
            pacer.finished(chunk.len);
            let columns = self.submit_store::<R>(passes, set, &chunk, stored, profile)?;
            let next_start = chunk.start + chunk.len;
            let next_len = (next_start < n).then(|| pacer.next_len(n - next_start));
            if next_len.is_some() && other.lists.is_none() {
                // The second set's lists; where the memory is short, the chunks go one at a time.
                match self.shared.with_memory(|| self.take_lists(capacity, record_bytes)) {
                    Ok(lists) => other.lists = Some(lists),
                    Err(Error::OutOfMemory(_)) => {}
                    Err(error) => return Err(error),
                }
            }
            if other.lists.is_none() {
                // One set: this chunk stored and copied out, then the next counted in its place.
                self.wait_store(set, profile)?;
                self.unpack_store::<R>(passes, set, chunk, columns, stored, profile)?;
                interrupt.progress(next_start, n);
                let Some(len) = next_len else { return Ok(()) };
                pending = (next_start, len, self.pack_rays(passes, set, next_start, len, profile)?);
                self.submit_count(passes, set, (next_start, len), profile)?;
                continue;
            }
            let next = match next_len {
                Some(len) => Some((next_start, len, self.pack_rays(passes, other, next_start, len, profile)?)),
                None => None,
            };
            self.wait_store(set, profile)?;
            if let Some((start, len, _)) = &next {
                self.submit_count(passes, other, (*start, *len), profile)?;
            }
            self.unpack_store::<R>(passes, set, chunk, columns, stored, profile)?;
            interrupt.progress(next_start, n);
            match next {
                Some(next) => pending = next,
                None => return Ok(()),
            }
            std::mem::swap(&mut set, &mut other);
        }
    }

    /// Packs rays `start..start + len` into the set's staging.
    fn pack_rays(
        &self,
        passes: &Passes,
        set: &mut ChunkSet,
        start: usize,
        len: usize,
        profile: &mut TraceProfile,
    ) -> Result<Vec<Advance>> {
        let packing = Instant::now();
        let advances = pack_chunk(&passes.counting, set.slot.split().0, start, len)?;
        if passes.counting.sensor.is_none() {
            profile.ray_bytes += set.slot.packed_bytes(len);
        }
        profile.pack += packing.elapsed().as_secs_f64();
        Ok(advances)
    }

    /// Submits the counting pass of the set's packed rays (`start`, `len`), and the lists placed
    /// from its counts (list_offsets.comp), with the chunk's total back to the host.
    fn submit_count(
        &self,
        passes: &Passes,
        set: &mut ChunkSet,
        (start, len): (usize, usize),
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let submitting = Instant::now();
        let chunks = &self.rays.chunks;
        let ChunkSet { slot, lists, room, commands } = set;
        let lists = lists.as_ref().expect("the set's lists");
        commands.begin()?;
        let cmd = commands.buffer;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        chunks.record_upload(cmd, &passes.counting, slot, len);
        stamp(Stamp::Uploaded);
        let counting = Counting { job: &passes.counting, slot, lists, max_hits: passes.max_hits, room: *room };
        self.record_counting(cmd, &counting, (start, len), &stamp)?;
        commands.submit()?;
        profile.submit += submitting.elapsed().as_secs_f64();
        Ok(())
    }

    /// Records the counting pass of a chunk's rays (`start`, `len`), already on the device, and
    /// the lists placed from its counts (list_offsets.comp), with the chunk's total back to the
    /// host; the stamps after `Uploaded`.
    pub(super) fn record_counting(
        &self,
        cmd: vk::CommandBuffer,
        counting: &Counting,
        (start, len): (usize, usize),
        stamp: &dyn Fn(Stamp),
    ) -> Result<()> {
        let ctx = &self.shared.ctx;
        let Counting { job, slot, lists, max_hits, room } = *counting;
        // Each ray's nearest few hits kept as it is counted: most rays need no storing pass.
        let nearest_hits = lists.nearest_hits(len);
        let kept = match nearest_hits {
            0 => ChunkLists::Counted,
            hits => ChunkLists::Nearest { records: lists.nearest_address(), hits },
        };
        self.rays.chunks.record_trace(cmd, job, slot, start, len, kept);
        stamp(Stamp::Traced);
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(
            ctx,
            cmd,
            (trace_stage(ctx), vk::AccessFlags::SHADER_WRITE),
            (compute, vk::AccessFlags::SHADER_READ),
        );
        let counts = slot.hits_address() + slot.field_offset(Field::Prim) as u64;
        self.offsets.record(cmd, counts, lists, len, max_hits, nearest_hits, room)?;
        // (Every stamp written: their results are waited for.)
        stamp(Stamp::ReadBack);
        Ok(())
    }

    /// Waits for the set's counting pass of rays (`start`, `len`) and reads what it found: the
    /// chunk to store (the rays whose lists fit in the records' room: all, or as many of the
    /// first), or None where the first ray's hits alone exceed the room, which the set's lists
    /// then grow to hold (the chunk is counted again).
    fn finish_count<R: HitRecord>(
        &self,
        set: &mut ChunkSet,
        (start, len): (usize, usize),
        advances: Vec<Advance>,
        profile: &mut TraceProfile,
    ) -> Result<Option<CountedChunk>> {
        let waiting = Instant::now();
        let ChunkSet { slot, lists, room, commands } = set;
        commands.wait()?;
        let reading = Instant::now();
        profile.wait += (reading - waiting).as_secs_f64();
        profile.chunks += 1;
        if let Some(stamps) = &slot.stamps {
            stamps.add_to(profile)?;
        }
        let lists_now = lists.as_mut().expect("the set's lists");
        // The budget's, not the idle lists': they may have more.
        let capacity = *room as u64;
        let Placed { mut total, storing: needs_storing } = lists_now.read_placed();
        let mut stored_len = len;
        // The host's time reading what the pass found is `unpack`'s, its waits `wait`'s.
        let mut cut_wait = 0.0;
        if total > capacity {
            // Only the rays whose lists fit in the records.
            commands.begin()?;
            self.offsets.record_offsets(commands.buffer, lists_now, len);
            commands.submit()?;
            let waiting = Instant::now();
            commands.wait()?;
            cut_wait = waiting.elapsed().as_secs_f64();
            profile.wait += cut_wait;
            let firsts = lists_now.read_offsets(len);
            stored_len = rays_that_fit(firsts, capacity);
            if stored_len == 0 {
                // The first ray's alone: in records that hold them, after counting it again.
                let first = firsts.get(1).copied().unwrap_or(total) as usize;
                let rays = lists_now.rays;
                let grown = self.shared.with_memory(|| self.take_lists(rays, first * size_of::<R>()))?;
                let old = lists.replace(grown).expect("the set's lists");
                self.give_back_lists(vec![old]);
                *room = first;
                profile.unpack += reading.elapsed().as_secs_f64() - cut_wait;
                return Ok(None);
            }
            total = firsts[stored_len];
        }
        profile.unpack += reading.elapsed().as_secs_f64() - cut_wait;
        Ok(Some(CountedChunk { start, len: stored_len, counted: len, total, needs_storing, advances }))
    }

    /// Submits the storing pass of a counted chunk (of the rays the counting pass did not keep
    /// whole, if any), and the records (or their columns), counts and offsets back; returns the
    /// columns' layout and pipeline in the columns' way.
    fn submit_store<R: HitRecord>(
        &self,
        passes: &Passes,
        set: &mut ChunkSet,
        chunk: &CountedChunk,
        stored: &mut StoredHits,
        profile: &mut TraceProfile,
    ) -> Result<Option<(ColumnLayout, vk::Pipeline)>> {
        let preparing = Instant::now();
        let ctx = &self.shared.ctx;
        let ChunkSet { slot, lists, commands, .. } = set;
        let lists = lists.as_mut().expect("the set's lists");
        let &CountedChunk { start, len, counted, total, needs_storing, .. } = chunk;
        let base = stored.hits();
        check_hits_fit(base + total as usize, stored.bytes_per_hit(size_of::<R>() + passes.host_bytes_per_hit))?;
        // The first chunk's rate of hits for all the rays (the memory untouched until written):
        // a vector grown chunk by chunk would copy its records again each time it doubles.
        let n = stored.seen.len();
        let expected = (total as f64 * (n - start) as f64 / len as f64 * 1.1) as usize;
        stored.reserve(total as usize, expected)?;
        // The columns' layout, their host-visible memory and pipeline, before recording.
        let columns = match &stored.columns {
            Some(way) => {
                let layout = ColumnLayout::new(&way.asked, R::WIDE, total as usize);
                self.shared.with_memory(|| lists.columns(ctx, layout.bytes).map(|_| ())).map_err(
                    |error| match error {
                        Error::OutOfMemory(why) => Error::OutOfMemory(format!(
                        "the {total} hits of a chunk of this query need {:.2} GB for their columns, which could not \
                         be allocated ({why}): trace fewer rays at a time, set max_hits, or ask fewer outputs",
                        layout.bytes as f64 / 1e9
                    )),
                        other => other,
                    },
                )?;
                Some((layout, self.columns.pipeline(R::WIDE)?))
            }
            None => None,
        };
        profile.unpack += preparing.elapsed().as_secs_f64();
        let submitting = Instant::now();
        let bytes = total as usize * size_of::<R>();
        commands.begin()?;
        let cmd = commands.buffer;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        stamp(Stamp::Uploaded);
        if needs_storing {
            self.rays.chunks.record_trace(cmd, &passes.storing, slot, start, len, ChunkLists::Lists(lists));
        }
        stamp(Stamp::Traced);
        match &columns {
            Some((layout, pipeline)) => {
                // (With no hits too: it checks that no ray saw any.)
                let seen = slot.hits_address() + slot.field_offset(Field::Prim) as u64;
                let rays = ChunkRays { first: start, len, counted, seen, max_hits: passes.max_hits };
                self.columns.record(cmd, *pipeline, lists, layout, rays, trace_stage(ctx));
                // The offsets stay on the GPU: where every list is settled, the host places them
                // from the hits seen (`place_settled`), else it reads them back then.
                record_readback(ctx, cmd, slot, passes.storing.outputs, len, None);
            }
            None => {
                record_readback(ctx, cmd, slot, passes.storing.outputs, len, Some((lists, bytes)));
                self.offsets.record_offsets(cmd, lists, len);
            }
        }
        stamp(Stamp::ReadBack);
        commands.submit()?;
        profile.submit += submitting.elapsed().as_secs_f64();
        profile.store += preparing.elapsed().as_secs_f64();
        Ok(columns)
    }

    /// Waits for the set's storing submission.
    fn wait_store(&self, set: &mut ChunkSet, profile: &mut TraceProfile) -> Result<()> {
        let waiting = Instant::now();
        set.commands.wait()?;
        let waited = waiting.elapsed().as_secs_f64();
        profile.wait += waited;
        profile.store += waited;
        if let Some(stamps) = &set.slot.stamps {
            stamps.add_to(profile)?;
        }
        Ok(())
    }

    /// A stored chunk's hits, back: its counts and offsets placed among the query's, its records
    /// (or columns) copied out.
    fn unpack_store<R: HitRecord>(
        &self,
        passes: &Passes,
        set: &mut ChunkSet,
        chunk: CountedChunk,
        columns: Option<(ColumnLayout, vk::Pipeline)>,
        stored: &mut StoredHits,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let unpacking = Instant::now();
        let ChunkSet { slot, lists, commands, .. } = set;
        let lists = lists.as_ref().expect("the set's lists");
        let CountedChunk { start, len, total, advances, .. } = chunk;
        let n = stored.seen.len();
        let base = stored.hits();
        let hits = slot.hits_host.mapped().expect("hit readback is host-visible");
        let at = slot.field_offset(Field::Prim);
        let seen: &[i32] = bytemuck::cast_slice(&hits[at..at + 4 * len]);
        let range = start..start + len;
        let advances: Vec<(usize, f64)> = advances.into_iter().filter(|a| a.ray < len).map(|a| (a.ray, a.t)).collect();
        if let (Some(way), Some((layout, ..))) = (&mut stored.columns, &columns) {
            let written = lists.written_columns(layout.bytes);
            // (The query's hits seen are not kept: only the records' way settles lists from them.)
            let offsets_out = &mut stored.offsets[start..start + len + 1];
            if layout.settled(written) && place_settled(seen, passes.max_hits, (base as u64, total), offsets_out) {
                // The query's rate of hits so far, for the rays left (this chunk's included).
                let rate = (way.hits as u64 + total) as f64 / (start + len) as f64;
                let room = way.hits_left(rate, n - start);
                way.append_written(written, layout, offsets_out, (total as usize, room), &advances)?;
                profile.gpu_columns += 1;
                let spent = unpacking.elapsed().as_secs_f64();
                profile.unpack += spent;
                profile.store += spent;
                return Ok(());
            }
            // A list the shaders did not settle: the offsets, back now.
            self.read_back_offsets(commands, lists, len, profile)?;
        }
        let firsts = lists.read_offsets(len);
        let placed = StoredChunk { seen, firsts, total, base: base as u64, max_hits: passes.max_hits };
        let (unsettled, overflowed) = placed.place(&mut stored.seen[range.clone()], &mut stored.offsets[range]);
        stored.offsets[start + len] = (base as u64 + total) as i64;
        stored.overflowed = stored.overflowed.or(overflowed.map(|k| start + k));
        match (&mut stored.columns, &columns) {
            (Some(way), Some((layout, ..))) if !unsettled => {
                let written = lists.written_columns(layout.bytes);
                let rate = (way.hits as u64 + total) as f64 / (start + len) as f64;
                let room = way.hits_left(rate, n - start);
                let offsets = &stored.offsets[start..start + len + 1];
                way.append_written(written, layout, offsets, (total as usize, room), &advances)?;
                profile.gpu_columns += 1;
            }
            (Some(_), _) => {
                let chunk = BackChunk { start, seen, firsts, total, advances };
                self.append_from_records::<R>(passes, commands, lists, chunk, stored)?;
            }
            (None, _) => {
                stored.unsettled |= unsettled;
                let bytes = total as usize * size_of::<R>();
                let records = lists.records_host.mapped().expect("hit records are host-visible");
                let src: &[R] = bytemuck::cast_slice(&records[..bytes]);
                // Appended on all cores (room was reserved), each the CPU tracer's record as it
                // goes: the pages' first touch is spread too.
                let scene = passes.scene;
                let records = &mut stored.records;
                parallel::install(|| records.par_extend(src.par_iter().with_min_len(4096).map(|r| r.reference(scene))));
                stored.advances.extend(advances.into_iter().map(|(ray, t)| (start + ray, t)));
            }
        }
        let spent = unpacking.elapsed().as_secs_f64();
        profile.unpack += spent;
        profile.store += spent;
        Ok(())
    }

    /// Reads back the offsets of the set's `len` rays (the columns' way leaves them on the GPU
    /// where every list is settled), once its storing submission finished.
    fn read_back_offsets(
        &self,
        commands: &mut Commands,
        lists: &ListBuffers,
        len: usize,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        commands.begin()?;
        self.offsets.record_offsets(commands.buffer, lists, len);
        commands.submit()?;
        let waiting = Instant::now();
        commands.wait()?;
        profile.wait += waiting.elapsed().as_secs_f64();
        Ok(())
    }

    /// The columns' way for a chunk with a list the shaders could not settle: its records back
    /// (from the device, where they live there), settled and written out by the host as
    /// `gpu_all_hits` would, their columns appended.
    fn append_from_records<R: HitRecord>(
        &self,
        passes: &Passes,
        commands: &mut Commands,
        lists: &ListBuffers,
        chunk: BackChunk,
        stored: &mut StoredHits,
    ) -> Result<()> {
        let ctx = &self.shared.ctx;
        let BackChunk { start, seen, firsts, total, advances } = chunk;
        let bytes = total as usize * size_of::<R>();
        if let (Some(device), true) = (&lists.records_device, bytes > 0) {
            commands.begin()?;
            // The records' writers: the storing pass's shaders and list_offsets.comp's copies.
            memory_barrier(
                ctx,
                commands.buffer,
                (trace_stage(ctx) | vk::PipelineStageFlags::COMPUTE_SHADER, vk::AccessFlags::SHADER_WRITE),
                (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_READ),
            );
            let region = [vk::BufferCopy::default().size(bytes as u64)];
            // SAFETY: `cmd` is recording; both buffers hold at least `bytes` of records, which
            // the storing submission (waited for, its writes made visible above) wrote.
            unsafe { ctx.device.cmd_copy_buffer(commands.buffer, device.raw(), lists.records_host.raw(), &region) };
            memory_barrier(
                ctx,
                commands.buffer,
                (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
                (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ),
            );
            commands.submit()?;
            commands.wait()?;
        }
        let scene = passes.scene;
        let mapped = lists.records_host.mapped().expect("hit records are host-visible");
        let src: &[R] = bytemuck::cast_slice(&mapped[..bytes]);
        // The host's records and then their columns: refused before either is made where the
        // host has no room for both.
        let asked_bytes =
            stored.columns.as_ref().map_or(0, |way| HitColumns::bytes_per_hit(&way.asked_columns(), true));
        check_hits_fit(total as usize, size_of::<ReferenceHit>() + asked_bytes)?;
        let mut records: Vec<ReferenceHit> = Vec::new();
        records.try_reserve_exact(total as usize).map_err(|_| {
            Error::OutOfMemory(format!("the {total} hits of a chunk of this query do not fit in host memory"))
        })?;
        parallel::install(|| records.par_extend(src.par_iter().with_min_len(4096).map(|r| r.reference(scene))));
        let offsets: Vec<i64> = firsts.iter().map(|&f| f as i64).chain([total as i64]).collect();
        let chunk_hits = StoredHits {
            offsets,
            records,
            seen: seen.to_vec(),
            advances,
            unsettled: true,
            overflowed: None,
            columns: None,
        };
        let (offsets, records) = chunk_hits.settled(passes.max_hits, passes.interrupt)?;
        let way = stored.columns.as_mut().expect("the columns' way");
        let asked = way.asked_columns();
        let all = AllHits { offsets, hits: records, wide: R::WIDE };
        let (written, _) = HitColumns::from_records(scene, passes.storing.rays, all, &asked)?;
        let base = way.hits as i64;
        for (out, &offset) in stored.offsets[start..].iter_mut().zip(&written.offsets) {
            *out = base + offset;
        }
        let hits = *written.offsets.last().expect("offsets end with the total") as usize;
        way.hits += hits;
        way.segments.push(Segment { hits, room: hits, columns: written.columns });
        Ok(())
    }
}

/// One of the two sets of a query's chunks, which take turns: its staging slot (rays, counts),
/// its lists (made when a second chunk first needs them) with the records' room, and its commands.
struct ChunkSet<'s> {
    slot: &'s mut Slot,
    lists: Option<ListBuffers>,
    room: usize,
    commands: Commands<'s>,
}

/// What a chunk's counting pass records with: the counting job, the slot its counts go to, the
/// lists placed from them, the hits a ray keeps and the records the lists hold.
#[derive(Clone, Copy)]
pub(super) struct Counting<'a> {
    pub job: &'a GpuJob<'a>,
    pub slot: &'a Slot,
    pub lists: &'a ListBuffers,
    pub max_hits: usize,
    pub room: usize,
}

/// A counted chunk, to store: its first ray, the rays whose lists fit in the records (`len`) of
/// those counted, its records, whether any ray needs the storing pass, and its far rays' advances.
struct CountedChunk {
    start: usize,
    len: usize,
    counted: usize,
    total: u64,
    needs_storing: bool,
    advances: Vec<Advance>,
}

/// A stored chunk back on the host: its first ray, each ray's hits seen by the storing pass and
/// its list's first record among the chunk's `total`, and its far rays' advances (ray, t).
struct BackChunk<'a> {
    start: usize,
    seen: &'a [i32],
    firsts: &'a [u64],
    total: u64,
    advances: Vec<(usize, f64)>,
}

/// A stored chunk as it came back: each ray's hits seen by the storing pass and its list's first
/// record among the chunk's `total`, which follow `base` records of the chunks before.
struct StoredChunk<'a> {
    seen: &'a [i32],
    firsts: &'a [u64],
    total: u64,
    base: u64,
    max_hits: usize,
}

impl StoredChunk<'_> {
    /// Writes the rays' counts and offsets into the query's, on all cores, and tells whether any
    /// list needs the host (appended, or written short), and which ray first met more hits
    /// storing than counting, if any: one pass over the rays.
    fn place(&self, seen_out: &mut [i32], offsets_out: &mut [i64]) -> (bool, Option<usize>) {
        let len = self.seen.len();
        let block = |(b, (seen_out, offsets_out)): (usize, (&mut [i32], &mut [i64]))| {
            let (mut unsettled, mut overflowed) = (false, None);
            for (k, (seen_out, offset_out)) in seen_out.iter_mut().zip(offsets_out.iter_mut()).enumerate() {
                let i = b * SCAN_BLOCK + k;
                let (first, seen) = (self.firsts[i], self.seen[i]);
                let end = if i + 1 < len { self.firsts[i + 1] } else { self.total };
                let capacity = (end - first) as usize;
                *seen_out = seen;
                *offset_out = (self.base + first) as i64;
                let seen = seen.max(0) as usize;
                unsettled |= appends(capacity, self.max_hits) || seen < capacity;
                if seen > capacity && capacity < self.max_hits && overflowed.is_none() {
                    overflowed = Some(i);
                }
            }
            (unsettled, overflowed)
        };
        let either = |a: (bool, Option<usize>), b: (bool, Option<usize>)| (a.0 || b.0, a.1.or(b.1));
        parallel::install(|| {
            seen_out
                .par_chunks_mut(SCAN_BLOCK)
                .zip(offsets_out.par_chunks_mut(SCAN_BLOCK))
                .enumerate()
                .map(block)
                .reduce(|| (false, None), either)
        })
    }
}

/// A stored chunk's offsets where hit_columns.comp found every list settled: each ray's list as
/// long as the hits it saw, up to `max_hits`, after the lists before it from `base` (the chunk's
/// first hit among the query's), written on all cores with the end of the last (`offsets_out` has
/// a ray more); false, and nothing to trust, where the lists do not add up to the chunk's `total`.
fn place_settled(seen: &[i32], max_hits: usize, (base, total): (u64, u64), offsets_out: &mut [i64]) -> bool {
    let kept = |s: i32| (s.max(0) as u64).min(max_hits as u64);
    let sums: Vec<u64> =
        parallel::install(|| seen.par_chunks(SCAN_BLOCK).map(|block| block.iter().map(|&s| kept(s)).sum()).collect());
    let mut firsts = Vec::with_capacity(sums.len());
    let mut at = base;
    for sum in sums {
        firsts.push(at);
        at += sum;
    }
    if at - base != total {
        return false;
    }
    let (offsets_out, end) = offsets_out.split_at_mut(seen.len());
    end[0] = at as i64;
    parallel::install(|| {
        offsets_out.par_chunks_mut(SCAN_BLOCK).zip(seen.par_chunks(SCAN_BLOCK)).zip(firsts).for_each(
            |((offsets_out, seen), first)| {
                let mut at = first;
                for (offset_out, &s) in offsets_out.iter_mut().zip(seen) {
                    *offset_out = at as i64;
                    at += kept(s);
                }
            },
        )
    });
    true
}

/// How many of a chunk's first rays have lists that end within `capacity` records, from each
/// ray's first record among the chunk's (`firsts`; the last ray's list ends past `capacity`).
pub(super) fn rays_that_fit(firsts: &[u64], capacity: u64) -> usize {
    firsts[1..].partition_point(|&end| end <= capacity)
}

impl AllHitsPath {
    /// Lists for `rays` rays and `record_bytes` of records: idle ones where they fit, new ones
    /// (allocated outside the lock) otherwise.
    pub(super) fn take_lists(&self, rays: usize, record_bytes: usize) -> Result<ListBuffers> {
        let fits = |l: &ListBuffers| l.rays >= rays && l.record_bytes >= record_bytes;
        if let Some(lists) = self.lists.take(1, fits, |_| true).pop() {
            return Ok(lists);
        }
        ListBuffers::new(&self.shared.ctx, rays, record_bytes).inspect_err(|_| self.lists.give_back(1, []))
    }

    pub(super) fn give_back_lists(&self, mut lists: Vec<ListBuffers>) {
        let returned = lists.len();
        for l in &mut lists {
            l.drop_columns_over(IDLE_RECORD_BYTES);
        }
        self.lists.give_back(returned, lists.into_iter().filter(|l| l.record_bytes <= IDLE_RECORD_BYTES));
    }
}

/// The fields of `asked` as hit_columns.comp writes them, where it writes every one, each once
/// (not positions, normals or custom indices, which need the host).
pub fn gpu_column_fields(asked: &[AskedColumn]) -> Option<Vec<Field>> {
    let fields = asked.iter().map(|c| c.filter(|f| GPU_COLUMN_FIELDS.contains(f))).collect::<Option<Vec<_>>>()?;
    // A field asked twice: the host writes each copy.
    (!fields.iter().enumerate().any(|(k, f)| fields[..k].contains(f))).then_some(fields)
}

/// Whether every mesh of the scene has one part (geometry): `ExactHit` names its triangle among
/// all parts of its mesh, so the GPU tells the exact tier's geometry only there.
pub fn one_part_meshes(scene: &Scene) -> bool {
    scene.placements.iter().all(|p| p.triangles.part_offsets.len() <= 2)
}

/// Rays a block of the host's passes over every ray covers (a task each, on all cores).
const SCAN_BLOCK: usize = 1 << 14;

/// A hit record the shaders store (`FastHit`, `ExactHit`).
pub trait HitRecord: Pod + Send + Sync {
    /// Its distance and barycentrics are f64 (the exact tier's).
    const WIDE: bool;

    /// The CPU tracer's record of the same hit, whose triangle is counted among all parts of
    /// its mesh. Ordered as the shaders order the stored records (`is_before`): by t, then
    /// instance, then triangle (a part's triangles follow the parts before it).
    fn reference(&self, scene: &Scene) -> ReferenceHit;
}

impl HitRecord for FastHit {
    const WIDE: bool = false;

    fn reference(&self, scene: &Scene) -> ReferenceHit {
        // Checked: the end of a list written short holds bytes no shader wrote (dropped later).
        let part = scene
            .placements
            .get(self.instance as usize)
            .and_then(|p| p.triangles.part_offsets.get(self.geometry as usize));
        ReferenceHit {
            t: self.t as f64,
            u: self.u as f64,
            v: self.v as f64,
            instance: self.instance as u32,
            prim: part.map_or(0, |&first| first.wrapping_add(self.prim as u32)),
        }
    }
}

impl HitRecord for ExactHit {
    const WIDE: bool = true;

    fn reference(&self, _: &Scene) -> ReferenceHit {
        *self
    }
}

/// The order of a ray's stored hits (`Equal`: the same hit, met twice).
fn hit_order(a: &ReferenceHit, b: &ReferenceHit) -> Ordering {
    a.t.total_cmp(&b.t).then((a.instance, a.prim).cmp(&(b.instance, b.prim)))
}

impl StoredHits {
    /// Hits stored so far.
    fn hits(&self) -> usize {
        self.columns.as_ref().map_or(self.records.len(), |way| way.hits)
    }

    /// Bytes a hit takes on the host: its columns and ray, or its record and `record_and_more`.
    fn bytes_per_hit(&self, record_and_more: usize) -> usize {
        match &self.columns {
            // Its columns at most twice: written by the host from a chunk's records.
            Some(way) => 8 + way.asked.iter().map(|f| f.bytes_per_ray(true)).sum::<usize>(),
            None => record_and_more,
        }
    }

    /// Room for a chunk of `total` hits more, and at the first chunk for `expected` in all,
    /// where the host has it: asked before storing, so that a query that cannot fit fails first.
    fn reserve(&mut self, total: usize, expected: usize) -> Result<()> {
        let base = self.hits();
        let refused = || Error::OutOfMemory(format!("the {} hits do not fit in host memory", base + total));
        if self.columns.is_some() {
            // Each chunk's segment is allocated as it comes back (`ColumnWay`).
            return Ok(());
        }
        if base == 0 && self.records.capacity() < total {
            // Spare records too small: growing them would copy them whole, unused as they are.
            self.records = Vec::new();
        }
        if base == 0 && expected > total && self.records.try_reserve_exact(expected).is_ok() {
            parallel::advise_huge_pages(&mut self.records);
        }
        self.records.try_reserve(total).map_err(|_| refused())?;
        parallel::advise_huge_pages(&mut self.records);
        Ok(())
    }

    /// The offsets and records once settled (`settle`), with the advances of far rays added
    /// back to their hits' t.
    fn settled(mut self, max_hits: usize, interrupt: &dyn Interrupt) -> Result<(Vec<i64>, Vec<ReferenceHit>)> {
        self.settle(max_hits, interrupt)?;
        interrupt.check()?;
        let StoredHits { offsets, mut records, advances, .. } = self;
        for (ray, t) in advances {
            let range = offsets[ray] as usize..offsets[ray + 1] as usize;
            for hit in &mut records[range] {
                hit.t = (hit.t + t) as f32 as f64;
            }
        }
        Ok((offsets, records))
    }

    /// Sorts the appended lists (dropping hits met twice), then drops the unwritten ends of lists
    /// whose ray met fewer hits than counted (a primitive reported twice by traversal and kept
    /// once), so that each ray's hits are contiguous. On all cores, in blocks of rays.
    fn settle(&mut self, max_hits: usize, interrupt: &dyn Interrupt) -> Result<()> {
        if !self.unsettled {
            return Ok(());
        }
        let n = self.seen.len();
        let (offsets, seen) = (&self.offsets, &self.seen);
        let mut kept: Vec<usize> = parallel::install(|| {
            (0..n)
                .into_par_iter()
                .with_min_len(SCAN_BLOCK)
                .map(|i| ((offsets[i + 1] - offsets[i]) as usize).min(seen[i].max(0) as usize))
                .collect()
        });
        // Sorted in paced blocks: tens of millions of lists take seconds.
        in_paced_blocks(n, (FIRST_ON_CPU, 1 << 22), interrupt, |range| {
            let blocks = ray_blocks(&self.offsets, range, &mut self.records, &mut kept);
            parallel::install(|| {
                blocks.into_par_iter().for_each(|(rays, records, kept)| {
                    let base = self.offsets[rays.start];
                    for (k, i) in rays.enumerate() {
                        let capacity = (self.offsets[i + 1] - self.offsets[i]) as usize;
                        if appends(capacity, max_hits) {
                            let from = (self.offsets[i] - base) as usize;
                            kept[k] = sort_unique(&mut records[from..from + kept[k]]);
                        }
                    }
                })
            });
            Ok(())
        })?;
        let whole = |i: usize| kept[i] as i64 == self.offsets[i + 1] - self.offsets[i];
        if parallel::install(|| (0..n).into_par_iter().with_min_len(SCAN_BLOCK).all(whole)) {
            return Ok(());
        }
        self.compact(&kept)
    }

    /// Keeps the first `kept[i]` hits of each ray's list, contiguous: new offsets by a blocked
    /// scan, the records gathered into a new array on all cores (or moved in place, one ray
    /// after another, where the host has no room for a second array).
    fn compact(&mut self, kept: &[usize]) -> Result<()> {
        let n = kept.len();
        let sums: Vec<usize> = parallel::install(|| kept.par_chunks(SCAN_BLOCK).map(|b| b.iter().sum()).collect());
        let mut starts = Vec::with_capacity(sums.len());
        let mut total = 0;
        for sum in sums {
            starts.push(total);
            total += sum;
        }
        let mut records: Vec<ReferenceHit> = Vec::new();
        if records.try_reserve_exact(total).is_err() {
            self.compact_in_place(kept);
            return Ok(());
        }
        parallel::advise_huge_pages(&mut records);
        // Each block's records go to their own part of the new array.
        let mut parts = Vec::with_capacity(starts.len());
        let mut rest = &mut records.spare_capacity_mut()[..total];
        for (b, &start) in starts.iter().enumerate() {
            let end = starts.get(b + 1).copied().unwrap_or(total);
            let (part, tail) = rest.split_at_mut(end - start);
            parts.push(part);
            rest = tail;
        }
        let (old, offsets) = (&self.records, &self.offsets);
        parallel::install(|| {
            parts.into_par_iter().enumerate().for_each(|(b, part)| {
                let mut to = 0;
                for i in b * SCAN_BLOCK..((b + 1) * SCAN_BLOCK).min(n) {
                    let from = offsets[i] as usize;
                    for (slot, hit) in part[to..to + kept[i]].iter_mut().zip(&old[from..from + kept[i]]) {
                        slot.write(*hit);
                    }
                    to += kept[i];
                }
            })
        });
        // SAFETY: the parts cover the first `total` entries, and each block wrote all of its
        // part: its rays' kept hits, `sums[b]` of them.
        unsafe { records.set_len(total) };
        let mut running = 0i64;
        for (i, &k) in kept.iter().enumerate() {
            self.offsets[i] = running;
            running += k as i64;
        }
        self.offsets[n] = running;
        self.records = records;
        Ok(())
    }
}

impl StoredHits {
    /// `compact` without a second array: each ray's kept hits moved down in turn.
    fn compact_in_place(&mut self, kept: &[usize]) {
        let mut to = 0;
        for (i, &kept) in kept.iter().enumerate() {
            let from = self.offsets[i] as usize;
            self.records.copy_within(from..from + kept, to);
            self.offsets[i] = to as i64;
            to += kept;
        }
        let n = kept.len();
        self.offsets[n] = to as i64;
        self.records.truncate(to);
    }
}

/// The rays of `range` in blocks of `SCAN_BLOCK`: each with its records and its part of `kept`.
fn ray_blocks<'a>(
    offsets: &[i64],
    range: std::ops::Range<usize>,
    records: &'a mut [ReferenceHit],
    kept: &'a mut [usize],
) -> Vec<(std::ops::Range<usize>, &'a mut [ReferenceHit], &'a mut [usize])> {
    let mut blocks = Vec::new();
    let mut records = &mut records[offsets[range.start] as usize..offsets[range.end] as usize];
    let mut kept = &mut kept[range.clone()];
    let mut start = range.start;
    while start < range.end {
        let end = (start + SCAN_BLOCK).min(range.end);
        let (block_records, records_rest) = records.split_at_mut((offsets[end] - offsets[start]) as usize);
        let (block_kept, kept_rest) = kept.split_at_mut(end - start);
        blocks.push((start..end, block_records, block_kept));
        (records, kept, start) = (records_rest, kept_rest, end);
    }
    blocks
}

/// Sorts a list appended as met, keeping one of each hit met twice: returns how many are left.
fn sort_unique(list: &mut [ReferenceHit]) -> usize {
    list.sort_unstable_by(hit_order);
    let mut unique = 0;
    for k in 0..list.len() {
        if unique == 0 || hit_order(&list[unique - 1], &list[k]) != Ordering::Equal {
            list[unique] = list[k];
            unique += 1;
        }
    }
    unique
}

#[cfg(test)]
mod tests {
    use super::{rays_that_fit, StoredHits, SCAN_BLOCK};
    use crate::geometry::reference::ReferenceHit;

    /// Lists of 0 to 4 records over several blocks, each keeping its first 0 to `capacity`.
    fn stored(rays: usize) -> (StoredHits, Vec<usize>) {
        let (mut offsets, mut records, mut kept) = (vec![0i64], Vec::new(), Vec::new());
        for i in 0..rays {
            let capacity = i * 7 % 5;
            for k in 0..capacity {
                records.push(ReferenceHit { t: k as f64, u: 0.0, v: 0.0, instance: 0, prim: i as u32 });
            }
            offsets.push(records.len() as i64);
            kept.push(capacity.min(i * 3 % 4));
        }
        let hits = StoredHits {
            offsets,
            records,
            seen: vec![0; rays],
            advances: vec![],
            unsettled: true,
            overflowed: None,
            columns: None,
        };
        (hits, kept)
    }

    #[test]
    fn compaction_keeps_each_rays_first_hits_in_place_or_not() {
        let rays = 2 * SCAN_BLOCK + 99;
        let (mut gathered, kept) = stored(rays);
        let (mut moved, _) = stored(rays);
        gathered.compact(&kept).unwrap();
        moved.compact_in_place(&kept);
        assert_eq!(gathered.offsets, moved.offsets);
        assert_eq!(gathered.records, moved.records);
        for (i, &kept) in kept.iter().enumerate() {
            let list = &moved.records[moved.offsets[i] as usize..moved.offsets[i + 1] as usize];
            assert_eq!(list.len(), kept);
            assert!(list.iter().enumerate().all(|(k, h)| h.prim == i as u32 && h.t == k as f64));
        }
    }

    #[test]
    fn a_chunk_stores_the_rays_whose_lists_fit() {
        // Rays holding 3, 0, 5, 1 and 9 hits: lists from 0, 3, 3, 8 and 9 (18 in all).
        let firsts = [0, 3, 3, 8, 9];
        assert_eq!(rays_that_fit(&firsts, 17), 4);
        assert_eq!(rays_that_fit(&firsts, 8), 3);
        assert_eq!(rays_that_fit(&firsts, 7), 2);
        assert_eq!(rays_that_fit(&firsts, 2), 0);
        assert_eq!(rays_that_fit(&[0], 2), 0);
    }
}

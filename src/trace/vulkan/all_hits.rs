//! All hits of each ray on the GPU (fast and exact tiers), chunk by chunk. Each chunk's rays are
//! packed once; a counting pass (the all-hits shaders with lists of no room) finds how many hits
//! each ray meets, and list_offsets.comp turns the counts into each ray's list among the chunk's
//! records, all in one submission; the host reads back only the chunk's total. A storing pass then
//! keeps each ray's hits (its nearest `max_hits`), sorted, in its list, and the records come back
//! with their offsets: straight after the chunks before. Memory is bounded by the chunks (a chunk
//! whose records do not fit stores only the rays whose lists do) and nothing is truncated.

use std::cmp::Ordering;
use std::mem::size_of;
use std::time::Instant;

use ash::vk;
use bytemuck::Pod;
use rayon::prelude::*;

use super::gpu_rays::GpuRays;
use super::hit_lists::{appends, ListBuffers, ListOffsets};
use super::ray_chunks::{pack_chunk, record_readback, trace_stage, GpuJob};
use super::shared::Shared;
use super::staging::Slot;
use super::timestamps::{start_stamps, Stamp};
use crate::error::{Error, Result};
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::geometry::parallel::try_vec;
use crate::geometry::reference::ReferenceHit;
use crate::gpu::context::Commands;
use crate::gpu::memory::memory_barrier;
use crate::gpu::records::{ExactHit, FastHit};
use crate::scene::{Scene, VulkanScene};
use crate::trace::hit_fields::Field;
use crate::trace::host_tiers::{check_hits_fit, AllHits};
use crate::trace::idle::IdlePool;
use crate::trace::pacer::{in_paced_blocks, ChunkPacer, FIRST_ON_CPU};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Precision, Query, RayBatch, Request};
use std::sync::Arc;

/// What the storing pass found: ray i's hits are `records[offsets[i]..offsets[i + 1]]`, of which
/// the first `seen[i]` are written where `seen[i]` is smaller (a primitive traversal reported
/// twice, kept once); `advances` holds (ray, t) for far rays packed from nearer origins (fast
/// tier), whose records' `t` is short by `t`.
pub struct StoredHits<R> {
    pub offsets: Vec<i64>,
    pub records: Vec<R>,
    pub seen: Vec<i32>,
    pub advances: Vec<(usize, f64)>,
}

/// Bytes of hit records a chunk may hold: CPU devices share the host's memory. `VKRAY_HIT_RECORD_BYTES`
/// sets another (the tests' way to chunks that store part of their rays).
fn record_budget(unified_memory: bool) -> usize {
    let set = std::env::var("VKRAY_HIT_RECORD_BYTES").ok().and_then(|v| v.parse().ok());
    set.unwrap_or(if unified_memory { 64 << 20 } else { 256 << 20 })
}

/// Idle lists kept between queries: as many as were in use at once, at least one and at most
/// eight, each of at most `IDLE_RECORD_BYTES` of records.
pub const IDLE_LISTS: (usize, usize) = (1, 8);
const IDLE_RECORD_BYTES: usize = 256 << 20;

/// The all-hits path. Owns the idle lists and records of the storing pass and the kernel that
/// places the lists.
pub struct AllHitsPath {
    shared: Arc<Shared>,
    rays: Arc<GpuRays>,
    lists: Arc<IdlePool<ListBuffers>>,
    offsets: ListOffsets,
}

/// A query's two passes over each chunk: the counting pass's job and the storing pass's, which
/// read the same packed rays.
struct Passes<'a> {
    counting: GpuJob<'a>,
    storing: GpuJob<'a>,
    max_hits: usize,
    /// What the caller will need per hit besides the records (`check_hits_fit`).
    host_bytes_per_hit: usize,
}

impl AllHitsPath {
    pub fn new(shared: &Arc<Shared>, rays: &Arc<GpuRays>, lists: &Arc<IdlePool<ListBuffers>>) -> Result<AllHitsPath> {
        let offsets = ListOffsets::new(&shared.ctx)?;
        Ok(AllHitsPath { shared: shared.clone(), rays: rays.clone(), lists: lists.clone(), offsets })
    }

    /// Every hit of every ray (the nearest `max_hits` of each) as the GPU tier `request` names
    /// (fast: `R` = `FastHit`; exact: `ExactHit`). `host_bytes_per_hit`: what the caller will
    /// need per hit besides the records, for checking that the result fits before storing it.
    pub fn gpu_all_hits<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        host_bytes_per_hit: usize,
    ) -> Result<StoredHits<R>> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let started = Instant::now();
        self.shared.ctx.check_usable()?;
        rays.check_shapes()?;
        let n = rays.len();
        // Held across both passes, so that the lists the first sizes are the second's.
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        self.rays.probes.check_paths(scene, request.precision == Precision::Exact)?;
        let mut stored = StoredHits {
            offsets: try_vec(n + 1, 0i64, "the hits' offsets")?,
            records: Vec::new(),
            seen: try_vec(n, 0i32, "the hits' counts")?,
            advances: Vec::new(),
        };
        let mut profile = TraceProfile { rays: n, ..Default::default() };
        if n > 0 {
            self.trace_lists(batch, max_hits, host_bytes_per_hit, &mut stored, &mut profile)?;
        }
        let (offsets, seen) = (&stored.offsets, &stored.seen);
        let overflows = |i: usize| {
            let capacity = offsets[i + 1] - offsets[i];
            seen[i] as i64 > capacity && capacity < max_hits as i64
        };
        // Any, on all cores (an ordered search for the first took 1.7 ms of a million rays on an
        // H200's host); the first only where there is one.
        let overflowed = parallel::install(|| (0..n).into_par_iter().with_min_len(SCAN_BLOCK).any(overflows));
        if let Some(i) = overflowed.then(|| (0..n).find(|&i| overflows(i))).flatten() {
            return Err(Error::Internal(format!(
                "ray {i} met {} hits in the storing pass, {} in the counting pass",
                seen[i],
                offsets[i + 1] - offsets[i]
            )));
        }
        interrupt.check()?;
        let settling = Instant::now();
        stored.settle(max_hits, interrupt)?;
        interrupt.check()?;
        profile.unpack += settling.elapsed().as_secs_f64();
        profile.total = started.elapsed().as_secs_f64();
        self.shared.keep_profile(profile);
        self.shared.ctx.check_validation()?;
        Ok(stored)
    }

    /// Both passes over every chunk of the batch's rays, in one slot and one set of lists.
    fn trace_lists<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        host_bytes_per_hit: usize,
        stored: &mut StoredHits<R>,
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
        let compact = |request| shared.compact_variant(scene, rays, request, outputs, exact || sensor.is_some());
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
        };
        let passes = Passes {
            counting: job(&counting_variant, counting_compact.as_ref().map(|(layout, v)| (*layout, &**v))),
            storing: job(&storing_variant, storing_compact.as_ref().map(|(layout, v)| (*layout, &**v))),
            max_hits,
            host_bytes_per_hit,
        };
        let ray_capacity = shared.chunk_capacity(rays.len());
        let record_bytes = (record_budget(shared.ctx.unified_memory) / size_of::<R>()).max(1) * size_of::<R>();
        let mut slots = shared.with_memory(|| shared.slots.take(ray_capacity, exact))?;
        let mut lists = match shared.with_memory(|| self.take_lists(ray_capacity, record_bytes)) {
            Ok(lists) => lists,
            Err(error) => {
                shared.slots.give_back(slots);
                return Err(error);
            }
        };
        let room = record_bytes / size_of::<R>();
        let result = self.trace_chunks(&passes, &mut slots[0], (&mut lists, room), stored, interrupt, profile);
        shared.slots.give_back(slots);
        self.give_back_lists(vec![lists]);
        result
    }

    /// Chunk after chunk, each sized by the time the last took.
    fn trace_chunks<R: HitRecord>(
        &self,
        passes: &Passes,
        slot: &mut Slot,
        (lists, mut room): (&mut ListBuffers, usize),
        stored: &mut StoredHits<R>,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let n = stored.seen.len();
        // Dropping this on an error waits for the chunk in flight before its memory goes.
        let mut commands = Commands::new(&self.shared.ctx)?;
        let mut pacer = ChunkPacer::on_device(lists.rays.min(slot.capacity), self.shared.ctx.info.is_software);
        let mut start = 0;
        while start < n {
            interrupt.check()?;
            let len = pacer.next_len(n - start);
            pacer.started();
            let lists = (&mut *lists, &mut room);
            let stored_rays = self.trace_chunk(passes, slot, lists, &mut commands, (start, len), stored, profile)?;
            pacer.finished(stored_rays.max(1));
            start += stored_rays;
            interrupt.progress(start, n);
        }
        Ok(())
    }

    /// Counts, places and stores the hits of the `len` rays from `start` (or of as many of the
    /// first as the lists' `room` of records holds): returns how many rays it stored (none where
    /// it grew the records to hold the first ray's hits, which the next call then stores).
    #[allow(clippy::too_many_arguments)]
    fn trace_chunk<R: HitRecord>(
        &self,
        passes: &Passes,
        slot: &mut Slot,
        (lists, room): (&mut ListBuffers, &mut usize),
        commands: &mut Commands,
        (start, len): (usize, usize),
        stored: &mut StoredHits<R>,
        profile: &mut TraceProfile,
    ) -> Result<usize> {
        let ctx = &self.shared.ctx;
        let chunks = &self.rays.chunks;
        let Passes { counting, storing, max_hits, host_bytes_per_hit } = passes;
        let mut clock = Instant::now();
        let mut lap = |into: &mut f64| {
            let now = Instant::now();
            *into += (now - clock).as_secs_f64();
            clock = now;
        };
        let advances = pack_chunk(counting, slot.split().0, start, len)?;
        if counting.sensor.is_none() {
            profile.ray_bytes += slot.packed_bytes(len);
        }
        lap(&mut profile.pack);
        // The counting pass, and the lists placed from its counts.
        commands.begin()?;
        let cmd = commands.buffer;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        chunks.record_upload(cmd, counting, slot, len);
        stamp(Stamp::Uploaded);
        chunks.record_trace(cmd, counting, slot, start, len, None);
        stamp(Stamp::Traced);
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(
            ctx,
            cmd,
            (trace_stage(ctx), vk::AccessFlags::SHADER_WRITE),
            (compute, vk::AccessFlags::SHADER_READ),
        );
        let counts = slot.hits_address() + slot.field_offset(Field::Prim) as u64;
        self.offsets.record(cmd, counts, lists, len, *max_hits)?;
        // (Every stamp written: their results are waited for.)
        stamp(Stamp::ReadBack);
        commands.submit()?;
        lap(&mut profile.submit);
        commands.wait()?;
        lap(&mut profile.wait);
        profile.chunks += 1;
        if let Some(stamps) = &slot.stamps {
            stamps.add_to(profile)?;
        }
        // The budget's, not the idle lists': they may have more.
        let capacity = *room as u64;
        let mut total = lists.read_total();
        let mut len = len;
        if total > capacity {
            // Only the rays whose lists fit in the records.
            commands.begin()?;
            self.offsets.record_offsets(commands.buffer, lists, len);
            commands.submit()?;
            commands.wait()?;
            let offsets = lists.read_offsets(len + 1);
            len = rays_that_fit(&offsets[1..], capacity);
            if len == 0 {
                // The first ray's alone: in records that hold them, after counting it again.
                let first = offsets.get(2).copied().unwrap_or(total) as usize;
                let grown = self.shared.with_memory(|| self.take_lists(lists.rays, first * size_of::<R>()))?;
                self.give_back_lists(vec![std::mem::replace(lists, grown)]);
                *room = first;
                return Ok(0);
            }
            total = offsets[1 + len];
        }
        let base = stored.records.len();
        check_hits_fit(base + total as usize, size_of::<R>() + host_bytes_per_hit)?;
        stored.records.try_reserve(total as usize).map_err(|_| {
            Error::OutOfMemory(format!("the {} hits' records do not fit in host memory", base + total as usize))
        })?;
        lap(&mut profile.unpack);
        // The storing pass, and its records, counts and offsets back.
        let bytes = total as usize * size_of::<R>();
        commands.begin()?;
        let cmd = commands.buffer;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        stamp(Stamp::Uploaded);
        chunks.record_trace(cmd, storing, slot, start, len, Some((lists, bytes)));
        stamp(Stamp::Traced);
        record_readback(ctx, cmd, slot, storing.outputs, len, Some((lists, bytes)));
        self.offsets.record_offsets(cmd, lists, len);
        stamp(Stamp::ReadBack);
        commands.submit()?;
        lap(&mut profile.submit);
        commands.wait()?;
        lap(&mut profile.wait);
        if let Some(stamps) = &slot.stamps {
            stamps.add_to(profile)?;
        }
        let hits = slot.hits_host.mapped().expect("hit readback is host-visible");
        let at = slot.field_offset(Field::Prim);
        stored.seen[start..start + len].copy_from_slice(bytemuck::cast_slice(&hits[at..at + 4 * len]));
        let offsets = &lists.read_offsets(len + 1)[1..];
        parallel::install(|| {
            stored.offsets[start..start + len]
                .par_iter_mut()
                .zip(offsets)
                .with_min_len(SCAN_BLOCK)
                .for_each(|(out, &offset)| *out = (base as u64 + offset) as i64)
        });
        stored.offsets[start + len] = (base as u64 + total) as i64;
        let records = lists.records_host.mapped().expect("hit records are host-visible");
        let src: &[R] = bytemuck::cast_slice(&records[..bytes]);
        // Appended on all cores (room was reserved): the pages' first touch is spread too.
        parallel::install(|| stored.records.par_extend(src.par_iter().copied()));
        stored.advances.extend(advances.into_iter().filter(|a| a.ray < len).map(|a| (start + a.ray, a.t)));
        lap(&mut profile.unpack);
        Ok(len)
    }
}

/// How many of a chunk's first rays have lists that end within `capacity` records, from each
/// ray's first record among the chunk's (`firsts`; the last ray's list ends past `capacity`).
fn rays_that_fit(firsts: &[u64], capacity: u64) -> usize {
    firsts[1..].partition_point(|&end| end <= capacity)
}

impl AllHitsPath {
    /// Lists for `rays` rays and `record_bytes` of records: idle ones where they fit, new ones
    /// (allocated outside the lock) otherwise.
    fn take_lists(&self, rays: usize, record_bytes: usize) -> Result<ListBuffers> {
        let fits = |l: &ListBuffers| l.rays >= rays && l.record_bytes >= record_bytes;
        if let Some(lists) = self.lists.take(1, fits, |_| true).pop() {
            return Ok(lists);
        }
        ListBuffers::new(&self.shared.ctx, rays, record_bytes).inspect_err(|_| self.lists.give_back(1, []))
    }

    fn give_back_lists(&self, lists: Vec<ListBuffers>) {
        let returned = lists.len();
        self.lists.give_back(returned, lists.into_iter().filter(|l| l.record_bytes <= IDLE_RECORD_BYTES));
    }
}

/// Rays a block of the host's passes over every ray covers (a task each, on all cores).
const SCAN_BLOCK: usize = 1 << 14;

/// A stored hit record: the order of a ray's hits (the shaders' `is_before`; `Equal`: the same
/// hit, met twice).
pub trait HitRecord: Pod + Send + Sync {
    fn order(&self, other: &Self) -> Ordering;
}

impl HitRecord for FastHit {
    fn order(&self, other: &Self) -> Ordering {
        let key = |h: &FastHit| (h.instance, h.geometry, h.prim);
        self.t.total_cmp(&other.t).then(key(self).cmp(&key(other)))
    }
}

impl HitRecord for ExactHit {
    fn order(&self, other: &Self) -> Ordering {
        self.t.total_cmp(&other.t).then((self.instance, self.prim).cmp(&(other.instance, other.prim)))
    }
}

impl<R: HitRecord> StoredHits<R> {
    /// Sorts the appended lists (dropping hits met twice), then drops the unwritten ends of lists
    /// whose ray met fewer hits than counted (a primitive reported twice by traversal and kept
    /// once), so that each ray's hits are contiguous.
    fn settle(&mut self, max_hits: usize, interrupt: &dyn Interrupt) -> Result<()> {
        let n = self.seen.len();
        let (offsets, seen) = (&self.offsets, &self.seen);
        let capacity = |i: usize| offsets[i + 1] - offsets[i];
        let unsettled = parallel::install(|| {
            (0..n)
                .into_par_iter()
                .with_min_len(SCAN_BLOCK)
                .any(|i| appends(capacity(i) as usize, max_hits) || (seen[i] as i64) < capacity(i))
        });
        if !unsettled {
            return Ok(());
        }
        let mut kept: Vec<usize> =
            (0..n).map(|i| (self.offsets[i + 1] - self.offsets[i]).min(self.seen[i].max(0) as i64) as usize).collect();
        let mut appended: Vec<(&mut [R], &mut usize)> = Vec::new();
        let mut rest = self.records.as_mut_slice();
        for (i, kept) in kept.iter_mut().enumerate() {
            let (list, tail) = rest.split_at_mut((self.offsets[i + 1] - self.offsets[i]) as usize);
            rest = tail;
            if appends((self.offsets[i + 1] - self.offsets[i]) as usize, max_hits) {
                appended.push((list, kept));
            }
        }
        // Sorted in paced blocks: tens of millions of lists take seconds.
        in_paced_blocks(appended.len(), (FIRST_ON_CPU, 1 << 22), interrupt, |range| {
            parallel::install(|| {
                appended[range].par_iter_mut().with_min_len(1024).for_each(|(list, kept)| {
                    let list = &mut list[..**kept];
                    list.sort_unstable_by(R::order);
                    let mut unique = 0;
                    for k in 0..list.len() {
                        if unique == 0 || list[unique - 1].order(&list[k]) != Ordering::Equal {
                            list[unique] = list[k];
                            unique += 1;
                        }
                    }
                    **kept = unique;
                })
            });
            Ok(())
        })?;
        if (0..n).all(|i| kept[i] as i64 == self.offsets[i + 1] - self.offsets[i]) {
            return Ok(());
        }
        let mut to = 0;
        for (i, &kept) in kept.iter().enumerate() {
            let from = self.offsets[i] as usize;
            self.records.copy_within(from..from + kept, to);
            self.offsets[i] = to as i64;
            to += kept;
        }
        self.offsets[n] = to as i64;
        self.records.truncate(to);
        Ok(())
    }
}

impl StoredHits<ExactHit> {
    /// The exact tier's hits as the CPU tracer's (the same record).
    pub fn into_all_hits(self) -> AllHits {
        AllHits { offsets: self.offsets, hits: self.records, wide: true }
    }
}

impl StoredHits<FastHit> {
    /// The fast tier's hits with their triangles counted among all parts of their mesh and far
    /// rays' `t` measured from their own origin.
    pub fn into_all_hits(mut self, scene: &Scene) -> Result<AllHits> {
        parallel::install(|| {
            self.records.par_iter_mut().with_min_len(4096).for_each(|record| {
                let r = *record;
                let triangles = &scene.placements[r.instance as usize].triangles;
                *bytemuck::cast_mut::<FastHit, ReferenceHit>(record) = ReferenceHit {
                    t: r.t as f64,
                    u: r.u as f64,
                    v: r.v as f64,
                    instance: r.instance as u32,
                    prim: triangles.global(r.geometry as usize, r.prim as usize) as u32,
                };
            })
        });
        // Same size and alignment (records.rs): the vector is reinterpreted, not copied.
        let mut hits: Vec<ReferenceHit> = bytemuck::allocation::cast_vec(self.records);
        for &(ray, t) in &self.advances {
            let range = self.offsets[ray] as usize..self.offsets[ray + 1] as usize;
            for hit in &mut hits[range] {
                hit.t = (hit.t + t) as f32 as f64;
            }
        }
        Ok(AllHits { offsets: self.offsets, hits, wide: false })
    }
}

#[cfg(test)]
mod tests {
    use super::rays_that_fit;

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

//! All hits of each ray on the GPU (fast and exact tiers). A counting pass (the all-hits shaders
//! with lists of no room) finds how many hits each ray meets; their prefix sums place each ray's
//! hits in one array; a storing pass then keeps each ray's hits (its nearest `max_hits`), sorted,
//! in a list of exactly that length, chunk by chunk, straight into their final place. Memory is
//! bounded by the chunks and nothing is truncated.

use std::cmp::Ordering;
use std::mem::size_of;
use std::time::Instant;

use bytemuck::Pod;
use rayon::prelude::*;

use super::gpu_rays::GpuRays;
use super::ray_chunks::{pack_chunk, GpuJob, ListBuffers};
use super::shared::Shared;
use super::staging::Slot;
use crate::error::{Error, Result};
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::geometry::parallel::try_vec;
use crate::geometry::reference::ReferenceHit;
use crate::gpu::context::Commands;
use crate::gpu::records::{ExactHit, FastHit, HitList, HIT_LIST_APPEND};
use crate::scene::{Scene, VulkanScene};
use crate::trace::hit_fields::{Field, HitSink};
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

/// Bytes of hit records one chunk in flight may hold: CPU devices share the host's memory.
fn record_budget(unified_memory: bool) -> usize {
    if unified_memory {
        64 << 20
    } else {
        256 << 20
    }
}

/// The all-hits path: a counting pass sizes each ray's list, a storing pass fills them. Owns
/// the idle lists and records of the storing pass.
pub struct AllHitsPath {
    shared: Arc<Shared>,
    rays: Arc<GpuRays>,
    lists: Arc<IdlePool<ListBuffers>>,
}

impl AllHitsPath {
    pub fn new(shared: &Arc<Shared>, rays: &Arc<GpuRays>, lists: &Arc<IdlePool<ListBuffers>>) -> AllHitsPath {
        AllHitsPath { shared: shared.clone(), rays: rays.clone(), lists: lists.clone() }
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
        let mut seen = try_vec(n, 0i32, "the hits' counts")?;
        if n > 0 {
            let mut sink = HitSink::default();
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut seen));
            let count = batch.asking(Request { query: Query::Count, ..request });
            let exact = request.precision == Precision::Exact;
            self.shared.profiled(n, started, |profile| self.rays.run(count, exact, &mut sink, profile))?;
        }
        let offsets = list_offsets(&seen, max_hits)?;
        let total = offsets[n] as usize;
        check_hits_fit(total, size_of::<R>() + host_bytes_per_hit)?;
        let storing = Instant::now();
        let mut records = Vec::new();
        records
            .try_reserve_exact(total)
            .map_err(|_| Error::OutOfMemory(format!("the {total} hits' records do not fit in host memory")))?;
        let mut stored = StoredHits { offsets, records, seen, advances: Vec::new() };
        let mut profile = TraceProfile { rays: n, ..Default::default() };
        if total > 0 {
            self.store_pass(batch, max_hits, &mut stored, &mut profile)?;
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
        stored.settle(max_hits, interrupt)?;
        interrupt.check()?;
        let mut last = self.shared.profile_mut();
        last.store = storing.elapsed().as_secs_f64();
        last.total = started.elapsed().as_secs_f64();
        last.chunks += profile.chunks;
        let add = |a: Option<f64>, b: Option<f64>| Some(a? + b.unwrap_or(0.0));
        last.gpu_upload = add(last.gpu_upload, profile.gpu_upload);
        last.gpu_trace = add(last.gpu_trace, profile.gpu_trace);
        last.gpu_readback = add(last.gpu_readback, profile.gpu_readback);
        drop(last);
        self.shared.ctx.check_validation()?;
        Ok(stored)
    }

    /// The storing pass: each chunk's rays with their lists, two chunks in flight.
    fn store_pass<R: HitRecord>(
        &self,
        batch: RayBatch,
        max_hits: usize,
        stored: &mut StoredHits<R>,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let exact = request.precision == Precision::Exact;
        let exact_scene = if exact { Some(VulkanScene::of(scene)?.exact(scene)?) } else { None };
        let outputs = Field::Prim.bit();
        let all = Request { query: Query::All, ..request };
        let (variant, sensor) = self.shared.gpu_variant(scene, rays, all, exact, outputs)?;
        // The counting pass's layouts (its rays reach traversal the same either way).
        let compact_variant = self.shared.compact_variant(scene, rays, all, outputs, exact || sensor.is_some())?;
        let offsets = &stored.offsets;
        let widest = parallel::install(|| {
            offsets.par_windows(2).with_min_len(SCAN_BLOCK).map(|w| (w[1] - w[0]) as usize).max().unwrap_or(0)
        });
        let total = *offsets.last().unwrap_or(&0) as usize;
        let record_capacity =
            (record_budget(self.shared.ctx.unified_memory) / size_of::<R>()).max(widest).min(total).max(1);
        let ray_capacity = self.shared.chunk_capacity(rays.len());
        let pacer = ChunkPacer::on_device(ray_capacity, self.shared.ctx.info.is_software);
        let one_chunk = chunk_end(offsets, 0, pacer.next_len(rays.len()), record_capacity) == rays.len();
        let mut slots = self.shared.with_memory(|| self.shared.slots.take(ray_capacity, exact))?;
        // One set of lists per chunk in flight: two, or one for a query of one chunk.
        let mut lists = Vec::new();
        for _ in 0..if one_chunk { 1 } else { 2 } {
            match self.shared.with_memory(|| self.take_lists(ray_capacity, record_capacity * size_of::<R>())) {
                Ok(taken) => lists.push(taken),
                Err(error) => {
                    self.shared.slots.give_back(slots);
                    self.give_back_lists(lists);
                    return Err(error);
                }
            }
        }
        let frame = scene.frame();
        let sensor = sensor.as_ref();
        let job = GpuJob {
            hierarchy: VulkanScene::of(scene)?,
            exact: exact_scene.as_deref(),
            rays,
            variant: &variant,
            compact: compact_variant.as_ref().map(|(layout, variant)| (*layout, &**variant)),
            compact_refused: Default::default(),
            outputs,
            frame,
            all_hits: true,
            sensor,
            cap: None,
            t_is_distance: true,
        };
        let chunking = (pacer, record_capacity);
        let result = self.store_chunks(&job, chunking, max_hits, &mut slots, &mut lists, stored, interrupt, profile);
        self.shared.slots.give_back(slots);
        self.give_back_lists(lists);
        result
    }

    #[allow(clippy::too_many_arguments)]
    fn store_chunks<R: HitRecord>(
        &self,
        job: &GpuJob,
        (mut pacer, record_capacity): (ChunkPacer, usize),
        max_hits: usize,
        slots: &mut [Slot; 2],
        lists: &mut [ListBuffers],
        stored: &mut StoredHits<R>,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        // Dropping these on an error waits for the chunks in flight before their memory goes.
        let mut commands = [Commands::new(&self.shared.ctx)?, Commands::new(&self.shared.ctx)?];
        let mut in_flight: [Option<(usize, usize, Vec<crate::geometry::rays::Advance>)>; 2] = [None, None];
        let mut finished = 0;
        let n = stored.offsets.len() - 1;
        let (mut chunk, mut start) = (0, 0);
        while start < n {
            interrupt.check()?;
            let s = chunk % 2;
            commands[s].wait()?;
            if let Some(done) = in_flight[s].take() {
                pacer.finished(done.1 - done.0);
                finished += done.1 - done.0;
                finish_stored(&slots[s], &lists[s], done, stored, profile)?;
                interrupt.progress(finished, stored.seen.len());
            }
            let end = chunk_end(&stored.offsets, start, pacer.next_len(n - start), record_capacity);
            let advances = pack_chunk(job, slots[s].split().0, start, end - start)?;
            write_lists(&mut lists[s], &stored.offsets, max_hits, start, end);
            let bytes = (stored.offsets[end] - stored.offsets[start]) as usize * size_of::<R>();
            profile.chunks += 1;
            commands[s].begin()?;
            self.rays.chunks.record_chunk(
                commands[s].buffer,
                job,
                &slots[s],
                start,
                end - start,
                Some((&lists[s], bytes)),
            );
            commands[s].submit()?;
            pacer.started();
            in_flight[s] = Some((start, end, advances));
            (chunk, start) = (chunk + 1, end);
        }
        // In chunk order: the records are appended.
        for k in 0..2 {
            let s = (chunk + k) % 2;
            commands[s].wait()?;
            if let Some(done) = in_flight[s].take() {
                finished += done.1 - done.0;
                finish_stored(&slots[s], &lists[s], done, stored, profile)?;
                interrupt.progress(finished, stored.seen.len());
            }
        }
        Ok(())
    }
}

/// Idle lists kept between queries (two a query): as many as were in use at once, at least two
/// and at most eight, each of at most `IDLE_RECORD_BYTES` of records.
pub const IDLE_LISTS: (usize, usize) = (2, 8);
const IDLE_RECORD_BYTES: usize = 64 << 20;

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

/// Where each ray's list starts among all hits (and, last, their total): the prefix sums of the
/// counting pass's counts, each at most `max_hits`. Block sums on all cores, then each block's
/// run from its start (a serial pass over a million rays took 3.6 ms on an H200's host).
fn list_offsets(seen: &[i32], max_hits: usize) -> Result<Vec<i64>> {
    let n = seen.len();
    let mut offsets = try_vec(n + 1, 0i64, "the hits' offsets")?;
    let kept = |count: i32| (count.max(0) as usize).min(max_hits) as i64;
    parallel::install(|| {
        let sums: Vec<i64> = seen.par_chunks(SCAN_BLOCK).map(|block| block.iter().map(|&c| kept(c)).sum()).collect();
        let mut starts = Vec::with_capacity(sums.len());
        let mut total = 0i64;
        for sum in sums {
            starts.push(total);
            total += sum;
        }
        offsets[1..].par_chunks_mut(SCAN_BLOCK).zip(seen.par_chunks(SCAN_BLOCK)).zip(starts).for_each(
            |((out, block), start)| {
                let mut running = start;
                for (slot, &count) in out.iter_mut().zip(block) {
                    running += kept(count);
                    *slot = running;
                }
            },
        );
    });
    Ok(offsets)
}

/// The end of the chunk from ray `start`: at most `max_rays` rays, whose lists hold at most
/// `max_records` hits together (or one ray, however many it holds).
fn chunk_end(offsets: &[i64], start: usize, max_rays: usize, max_records: usize) -> usize {
    let n = offsets.len() - 1;
    let limit = offsets[start] + max_records as i64;
    let last = (start + max_rays).min(n);
    let end = start + offsets[start + 1..=last].partition_point(|&o| o <= limit);
    end.max(start + 1)
}

/// Each ray's list within its chunk's records.
fn write_lists(buffers: &mut ListBuffers, offsets: &[i64], max_hits: usize, start: usize, end: usize) {
    let bytes = buffers.lists_host.mapped_mut().expect("hit lists are host-visible");
    let lists: &mut [HitList] = bytemuck::cast_slice_mut(&mut bytes[..(end - start) * size_of::<HitList>()]);
    let base = offsets[start];
    parallel::install(|| {
        lists.par_iter_mut().enumerate().with_min_len(4096).for_each(|(k, list)| {
            let i = start + k;
            let capacity = offsets[i + 1] - offsets[i];
            let append = if appends(capacity, max_hits) { HIT_LIST_APPEND } else { 0 };
            *list = HitList { first: (offsets[i] - base) as u32, capacity: capacity as u32 | append };
        })
    });
}

/// A finished chunk: its counts and records into place, its far rays' advances noted.
fn finish_stored<R: HitRecord>(
    slot: &Slot,
    buffers: &ListBuffers,
    (start, end, advances): (usize, usize, Vec<crate::geometry::rays::Advance>),
    stored: &mut StoredHits<R>,
    profile: &mut TraceProfile,
) -> Result<()> {
    if let Some(stamps) = &slot.stamps {
        stamps.add_to(profile)?;
    }
    let hits = slot.hits_host.mapped().expect("hit readback is host-visible");
    let at = slot.field_offset(Field::Prim);
    stored.seen[start..end].copy_from_slice(bytemuck::cast_slice(&hits[at..at + 4 * (end - start)]));
    let (first, last) = (stored.offsets[start] as usize, stored.offsets[end] as usize);
    assert_eq!(stored.records.len(), first, "chunks finish in order");
    let records = buffers.records_host.mapped().expect("hit records are host-visible");
    let src: &[R] = bytemuck::cast_slice(&records[..(last - first) * size_of::<R>()]);
    // Appended on all cores (room was reserved): the pages' first touch is spread too.
    parallel::install(|| stored.records.par_extend(src.par_iter().copied()));
    stored.advances.extend(advances.into_iter().map(|a| (start + a.ray, a.t)));
    Ok(())
}

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

/// Lists longer than this are filled in the order traversal meets their hits and sorted by the
/// host (`HIT_LIST_APPEND`): insertion costs the square of a list's length.
const INSERTION_LIMIT: i64 = 32;

/// Whether a list of `capacity` hits (as many as its ray met, unless `max_hits` cut it) is
/// appended to: long, and holding every hit of its ray.
fn appends(capacity: i64, max_hits: usize) -> bool {
    capacity > INSERTION_LIMIT && (capacity as u64) < max_hits as u64
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
                .any(|i| appends(capacity(i), max_hits) || (seen[i] as i64) < capacity(i))
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
            if appends(self.offsets[i + 1] - self.offsets[i], max_hits) {
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
    use super::{chunk_end, list_offsets, SCAN_BLOCK};

    #[test]
    fn offsets_are_the_prefix_sums_of_the_kept_counts() {
        let seen: Vec<i32> = (0..3 * SCAN_BLOCK as i32 + 17).map(|i| (i * 7919) % 13 - 2).collect();
        let mut expected = vec![0i64];
        for &count in &seen {
            expected.push(expected.last().unwrap() + count.clamp(0, 5) as i64);
        }
        assert_eq!(list_offsets(&seen, 5).unwrap(), expected);
        assert_eq!(list_offsets(&[], 5).unwrap(), vec![0]);
    }

    /// Every chunk from the start, at most `max_rays` rays and `max_records` records each.
    fn plan(offsets: &[i64], max_rays: usize, max_records: usize) -> Vec<(usize, usize)> {
        let mut chunks = vec![];
        let mut start = 0;
        while start < offsets.len() - 1 {
            let end = chunk_end(offsets, start, max_rays, max_records);
            chunks.push((start, end));
            start = end;
        }
        chunks
    }

    #[test]
    fn chunks_respect_rays_and_records() {
        // Rays holding 3, 0, 5, 1, 9 and 2 hits.
        let offsets = [0, 3, 3, 8, 9, 18, 20];
        assert_eq!(plan(&offsets, 100, 100), [(0, 6)]);
        assert_eq!(plan(&offsets, 2, 100), [(0, 2), (2, 4), (4, 6)]);
        // A ray holding more than a chunk's records gets a chunk of its own.
        assert_eq!(plan(&offsets, 100, 8), [(0, 3), (3, 4), (4, 5), (5, 6)]);
        assert_eq!(plan(&[0, 0, 0], 1, 1), [(0, 1), (1, 2)]);
    }
}

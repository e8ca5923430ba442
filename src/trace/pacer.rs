//! Chunks sized by the time they take (`ChunkPacer`). Ctrl-C is heard between chunks (and the
//! chunks a GPU has in flight finish first), so a chunk must last a fraction of a second whatever
//! the engine and however many hits a ray meets: a fixed count of rays took 5 s a chunk on
//! lavapipe with 200 hits a ray, 20 s on the CPU engine's all hits. The first chunk is small and
//! measures the rate; each later one aims at a fraction of a second at the rate its predecessor
//! ran, growing at most eightfold, within the caller's capacity.

use std::ops::Range;
use std::time::Instant;

use crate::error::Result;
use crate::geometry::interrupt::Interrupt;

/// What a chunk aims to last: with two in flight and a check between chunks, Ctrl-C's wait stays
/// under a second.
pub const CHUNK_SECONDS: f64 = 0.25;

/// Items (rays, points) of a first chunk before any rate is known, on a CPU (the CPU engine, a
/// software GPU or the host's f64 tiers: 10^5 rays a second with many hits each) and on a GPU
/// (where each chunk costs a submission and a pass of the host's threads: chunks of 2^18 cost an
/// H200 10-30% of its rate on 1M rays).
pub const FIRST_ON_CPU: usize = 1 << 15;
pub const FIRST_ON_GPU: usize = 1 << 20;

/// The CPU engine's first chunk a thread of its pool (`first_on_cpu`): the share of each a first
/// chunk of `FIRST_ON_CPU` gives two threads.
const FIRST_ON_CPU_PER_THREAD: usize = FIRST_ON_CPU / 2;

/// The first chunk of the CPU engine's ray queries, `threads` threads tracing it: as long on many
/// cores as `FIRST_ON_CPU` on two. A fixed count would be one block a thread on 16 cores, and each
/// chunk ends in a wait for its slowest block (on an H200's host, 1M rays in chunks from 2^15:
/// closest hits, occlusion and counts 3-7% slower than in one chunk).
pub fn first_on_cpu(threads: usize) -> usize {
    FIRST_ON_CPU_PER_THREAD * threads.max(2)
}

/// No chunk smaller than this once measured (within the capacity): each costs a pass.
const SMALLEST_CHUNK: usize = 1 << 10;

/// How much a chunk may grow over the one measured.
const MOST_GROWTH: usize = 8;

/// The length of each chunk of a query.
pub struct ChunkPacer {
    capacity: usize,
    next: usize,
    /// When the last chunk finished (or the first started).
    clock: Option<Instant>,
}

impl ChunkPacer {
    /// Chunks of at most `capacity` items, the first of `first`.
    pub fn new(first: usize, capacity: usize) -> ChunkPacer {
        let capacity = capacity.max(1);
        ChunkPacer { capacity, next: first.clamp(1, capacity), clock: None }
    }

    /// Chunks of at most `capacity` items on a device: a CPU one (`on_cpu`) or a GPU.
    pub fn on_device(capacity: usize, on_cpu: bool) -> ChunkPacer {
        ChunkPacer::new(if on_cpu { FIRST_ON_CPU } else { FIRST_ON_GPU }, capacity)
    }

    /// The next chunk's length, `remaining` items being left.
    pub fn next_len(&self, remaining: usize) -> usize {
        self.next.min(remaining)
    }

    /// A chunk started (was submitted): the clock starts with the first.
    pub fn started(&mut self) {
        self.clock.get_or_insert_with(Instant::now);
    }

    /// A chunk of `len` items finished: the time since the last one finished (or the first
    /// started) is its own, chunks running one after the other.
    pub fn finished(&mut self, len: usize) {
        let now = Instant::now();
        let Some(since) = self.clock.replace(now) else { return };
        let seconds = (now - since).as_secs_f64().max(1e-6);
        let at_rate = (len as f64 / seconds * CHUNK_SECONDS) as usize;
        let next = at_rate.min(len.max(1) * MOST_GROWTH).min(self.capacity);
        self.next = next.max(SMALLEST_CHUNK.min(self.capacity));
    }
}

/// Runs `work` over `0..n` in chunks paced from `first` items up to `most`, asking `interrupt`
/// before each and reporting progress after each.
pub fn in_paced_blocks(
    n: usize,
    (first, most): (usize, usize),
    interrupt: &dyn Interrupt,
    mut work: impl FnMut(Range<usize>) -> Result<()>,
) -> Result<()> {
    let mut pacer = ChunkPacer::new(first, most);
    let mut start = 0;
    while start < n {
        interrupt.check()?;
        let end = start + pacer.next_len(n - start);
        pacer.started();
        work(start..end)?;
        pacer.finished(end - start);
        interrupt.progress(end, n);
        start = end;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn starts_small_grows_to_capacity_and_shrinks_for_slow_chunks() {
        let mut pacer = ChunkPacer::on_device(1 << 22, true);
        assert_eq!(pacer.next_len(usize::MAX), FIRST_ON_CPU);
        assert_eq!(pacer.next_len(100), 100);
        pacer.started();
        // A fast chunk: growth is bounded.
        pacer.finished(FIRST_ON_CPU);
        assert_eq!(pacer.next_len(usize::MAX), FIRST_ON_CPU * MOST_GROWTH);
        // A slow one: 2000 items in at least 20 ms, so at most 25,000 aim at 0.25 s.
        std::thread::sleep(std::time::Duration::from_millis(20));
        pacer.finished(2000);
        let next = pacer.next_len(usize::MAX);
        assert!((SMALLEST_CHUNK..=25_000).contains(&next), "{next}");
        // Never past the capacity.
        assert_eq!(ChunkPacer::on_device(777, false).next_len(usize::MAX), 777);
    }

    #[test]
    fn the_cpu_engines_first_chunk_grows_with_its_threads() {
        assert_eq!(first_on_cpu(1), FIRST_ON_CPU);
        assert_eq!(first_on_cpu(2), FIRST_ON_CPU);
        assert_eq!(first_on_cpu(16), 8 * FIRST_ON_CPU);
    }
}

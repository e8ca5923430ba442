//! Idle resources kept between queries (staging slots, packing scratch, list buffers, CUDA
//! leases; and the host's records of all hits, `SpareRecords`): allocating them costs more than a
//! chunk's trace on discrete GPUs, so a device keeps what its queries used, as many as were ever
//! in use at once (up to a cap). A fixed number
//! made every query beyond it allocate anew when more threads queried one device at once: with
//! four threads, a 4M-ray call went from 7 to 45 ms on an H200 (docs/benchmarks.md, session 15).

use std::sync::Mutex;

use crate::geometry::reference::ReferenceHit;

/// What an idle item holds: the bytes of its buffers (host-visible staging and device copies).
pub trait Held {
    fn bytes(&self) -> u64;
}

/// A pool of idle resources as the memory retry and `release_idle_memory` see it, whatever it
/// holds: an engine sums and frees all of its pools through this.
pub trait Idle: Send + Sync {
    /// What the pool holds now, and how many items were made.
    fn memory(&self) -> IdleMemory;
    /// Drops every idle item.
    fn clear(&self);
}

impl<T: Held + Send> Idle for IdlePool<T> {
    fn memory(&self) -> IdleMemory {
        IdlePool::memory(self)
    }

    fn clear(&self) {
        IdlePool::clear(self)
    }
}

/// A device's idle resources, summed over its pools (`Engine::idle_memory`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct IdleMemory {
    /// Bytes the idle items hold.
    pub bytes: u64,
    /// Idle items.
    pub items: usize,
    /// Items the device's queries had to make because none was idle (over its lifetime).
    pub made: u64,
}

impl std::ops::Add for IdleMemory {
    type Output = IdleMemory;
    fn add(self, other: IdleMemory) -> IdleMemory {
        IdleMemory { bytes: self.bytes + other.bytes, items: self.items + other.items, made: self.made + other.made }
    }
}

/// A pool of idle `T`s. The lock is held only to take or return items: making new ones and
/// dropping surplus ones (a CUDA lease's drop waits for its stream) happen outside it.
pub struct IdlePool<T> {
    state: Mutex<State<T>>,
    /// Kept whatever the peak: a query of one kind between queries of another finds them.
    floor: usize,
    cap: usize,
}

struct State<T> {
    /// Oldest first.
    idle: Vec<T>,
    /// Items taken and not yet given back (including those the takers made).
    out: usize,
    /// The most items ever out at once.
    peak: usize,
    /// Items takers had to make (asked for and not found idle).
    made: u64,
}

impl<T: Held> IdlePool<T> {
    /// A pool that keeps as many idle items as were ever out at once, at least `floor` (for
    /// items of several kinds, which one peak does not count apart) and at most `cap`.
    pub fn new(floor: usize, cap: usize) -> IdlePool<T> {
        IdlePool { state: Mutex::new(State { idle: Vec::new(), out: 0, peak: 0, made: 0 }), floor, cap }
    }

    /// Counts `count` items out and takes up to that many idle ones for which `fits` holds (the
    /// newest first); the taker makes the rest. Idle items for which `keep` fails are dropped
    /// (after the lock is released).
    pub fn take(&self, count: usize, fits: impl Fn(&T) -> bool, keep: impl Fn(&T) -> bool) -> Vec<T> {
        let dropped: Vec<T>;
        let found = {
            let mut state = self.lock();
            state.out += count;
            state.peak = state.peak.max(state.out);
            let (kept, unwanted): (Vec<T>, Vec<T>) = std::mem::take(&mut state.idle).into_iter().partition(&keep);
            state.idle = kept;
            dropped = unwanted;
            let mut found = Vec::with_capacity(count);
            while found.len() < count {
                match state.idle.iter().rposition(&fits) {
                    Some(k) => found.push(state.idle.remove(k)),
                    None => break,
                }
            }
            state.made += (count - found.len()) as u64;
            found
        };
        drop(dropped);
        found
    }

    /// Gives back `returned` items taken before (fewer where some were lost), of which `items`
    /// are kept for later queries: as many as were ever out at once (at least the floor, at
    /// most the cap); the oldest go first.
    pub fn give_back(&self, returned: usize, items: impl IntoIterator<Item = T>) {
        let surplus: Vec<T> = {
            let mut state = self.lock();
            state.out = state.out.saturating_sub(returned);
            state.idle.extend(items);
            let keep = state.peak.max(self.floor).min(self.cap);
            let extra = state.idle.len().saturating_sub(keep);
            state.idle.drain(..extra).collect()
        };
        drop(surplus);
    }

    /// Drops every idle item (after an allocation failed: the memory they hold may be what
    /// the next one needs).
    pub fn clear(&self) {
        let idle = std::mem::take(&mut self.lock().idle);
        drop(idle);
    }

    /// What the pool holds now, and how many items were made.
    pub fn memory(&self) -> IdleMemory {
        let state = self.lock();
        IdleMemory { bytes: state.idle.iter().map(Held::bytes).sum(), items: state.idle.len(), made: state.made }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::{Held, IdleMemory, IdlePool};

    impl Held for u32 {
        fn bytes(&self) -> u64 {
            u64::from(*self)
        }
    }

    #[test]
    fn keeps_as_many_as_were_out_at_once_up_to_the_cap() {
        let pool = IdlePool::<u32>::new(0, 5);
        // Three takers at once, two items each: six out at the peak; five kept (the cap).
        let taken: Vec<Vec<u32>> = (0..3).map(|_| pool.take(2, |_| true, |_| true)).collect();
        assert!(taken.iter().all(Vec::is_empty));
        for k in 0..3 {
            pool.give_back(2, [2 * k, 2 * k + 1]);
        }
        assert_eq!(pool.lock().idle, vec![1, 2, 3, 4, 5]);
        // One taker at a time after that: still five kept.
        assert_eq!(pool.take(2, |_| true, |_| true), vec![5, 4]);
        pool.give_back(2, [7, 8]);
        assert_eq!(pool.lock().idle, vec![1, 2, 3, 7, 8]);
        assert_eq!(pool.memory(), IdleMemory { bytes: 21, items: 5, made: 6 });
    }

    #[test]
    fn a_pool_used_by_one_taker_keeps_one_takers_worth() {
        let pool = IdlePool::<u32>::new(0, 16);
        for round in 0..3 {
            let found = pool.take(2, |_| true, |_| true);
            assert_eq!(found.len(), if round == 0 { 0 } else { 2 });
            pool.give_back(2, [10 * round, 10 * round + 1]);
        }
        assert_eq!(pool.lock().idle.len(), 2);
    }

    #[test]
    fn keeps_the_floor_for_items_of_another_kind() {
        // One taker at a time, two items of one kind (even) then of another (odd): the peak is
        // two, the floor four, so each kind finds its items after the other's query.
        let pool = IdlePool::<u32>::new(4, 16);
        for round in 0..4 {
            let kind = round % 2;
            let found = pool.take(2, |x| x % 2 == kind, |_| true);
            assert_eq!(found.len(), if round < 2 { 0 } else { 2 }, "round {round}");
            pool.give_back(2, [10 + kind, 20 + kind]);
        }
        assert_eq!(pool.memory().made, 4);
        assert_eq!(pool.memory().items, 4);
    }

    #[test]
    fn takes_only_what_fits_and_drops_what_is_not_kept() {
        let pool = IdlePool::<u32>::new(0, 8);
        let _ = pool.take(4, |_| true, |_| true);
        pool.give_back(4, [1, 5, 9, 3]);
        // Items under 3 are no longer wanted; of the rest, those over 4 fit.
        assert_eq!(pool.take(2, |&x| x > 4, |&x| x >= 3), vec![9, 5]);
        assert_eq!(pool.lock().idle, vec![3]);
        pool.give_back(1, []); // one of the two was lost
        pool.clear();
        assert!(pool.lock().idle.is_empty());
        assert_eq!(pool.lock().out, 1);
    }
}

/// Most bytes of records kept for the next query.
const MOST_SPARE_BYTES: usize = 256 << 20;

/// The records of the last answer its caller handed back (`Engine::recycle_hits`), for the next
/// query to fill: a million hits' records in fresh memory cost their pages' first touch, about
/// as much again as their copying (and their release as much).
#[derive(Default)]
pub struct SpareRecords(Mutex<Vec<ReferenceHit>>);

impl SpareRecords {
    /// The spare records (empty, with their room), or a new vector.
    pub fn take(&self) -> Vec<ReferenceHit> {
        let mut records = std::mem::take(&mut *self.0.lock().unwrap_or_else(|e| e.into_inner()));
        records.clear();
        records
    }

    /// Keeps `records` for the next query where they have more room than the spare ones (and at
    /// most `MOST_SPARE_BYTES`).
    pub fn keep(&self, records: Vec<ReferenceHit>) {
        if records.capacity() * std::mem::size_of::<ReferenceHit>() > MOST_SPARE_BYTES {
            return;
        }
        let mut spare = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let dropped =
            if records.capacity() > spare.capacity() { std::mem::replace(&mut *spare, records) } else { records };
        drop(spare);
        // Freed outside the lock.
        drop(dropped);
    }
}

impl Idle for SpareRecords {
    fn memory(&self) -> IdleMemory {
        let capacity = self.0.lock().unwrap_or_else(|e| e.into_inner()).capacity();
        IdleMemory {
            bytes: (capacity * std::mem::size_of::<ReferenceHit>()) as u64,
            items: (capacity > 0) as usize,
            made: 0,
        }
    }

    fn clear(&self) {
        drop(std::mem::take(&mut *self.0.lock().unwrap_or_else(|e| e.into_inner())));
    }
}

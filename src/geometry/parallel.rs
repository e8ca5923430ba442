//! The thread pool host passes run on: rayon's global pool in the process that first used it,
//! and a pool of its own in a forked child (whose copy of the parent's pool has no threads behind
//! it, so work given to it would never run); or, for a thread inside `with_pool`, the pool it
//! names (a device's own threads: the host passes of several GPUs run side by side on threads of
//! their own instead of queuing for one pool; docs/benchmarks.md, issue 15).

use std::cell::RefCell;
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex, OnceLock};

use rayon::{ThreadPool, ThreadPoolBuilder};

use crate::error::Error;

/// The process whose threads rayon's global pool has (the first to run parallel work here).
static GLOBAL_POOL_OWNER: OnceLock<u32> = OnceLock::new();

/// A forked child's own pool, with the process it belongs to.
static CHILD_POOL: Mutex<Option<(u32, Arc<ThreadPool>)>> = Mutex::new(None);

thread_local! {
    /// The pool this thread's parallel sections go to, while it runs `with_pool`'s work.
    static CHOSEN: RefCell<Option<Arc<ThreadPool>>> = const { RefCell::new(None) };
}

/// A pool of threads of its own, for one device's host passes (`with_pool`).
pub struct OwnPool {
    pool: ManuallyDrop<Arc<ThreadPool>>,
    threads: usize,
    /// The process that started the threads: a forked child has none of them.
    pid: u32,
}

impl OwnPool {
    /// A pool of `threads` threads named `name-k`.
    pub fn new(threads: usize, name: &str) -> Result<OwnPool, String> {
        let name = name.to_string();
        let pool = ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(move |k| format!("{name}-{k}"))
            .build()
            .map_err(|e| format!("cannot start {threads} host threads: {e}"))?;
        Ok(OwnPool { pool: ManuallyDrop::new(Arc::new(pool)), threads, pid: std::process::id() })
    }

    pub fn threads(&self) -> usize {
        self.threads
    }
}

impl Drop for OwnPool {
    fn drop(&mut self) {
        // In a forked child the threads stayed behind: dropping the pool would signal threads
        // that do not exist here (as `child_pool` does with a grandparent's pool).
        if self.pid == std::process::id() {
            // SAFETY: `pool` is dropped once, here, and not used after.
            unsafe { ManuallyDrop::drop(&mut self.pool) }
        }
    }
}

/// Runs `work` on this thread, its parallel sections (`install`) on `pool`'s threads; with
/// `None`, or in a forked child of the process that started the pool, as `install` would anyway.
/// `work` may take locks and wait: only its parallel sections run on the pool.
pub fn with_pool<R>(pool: Option<&OwnPool>, work: impl FnOnce() -> R) -> R {
    let Some(own) = pool.filter(|own| own.pid == std::process::id()) else {
        return work();
    };
    /// Puts back the thread's earlier choice, also when `work` panics.
    struct Restore(Option<Arc<ThreadPool>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            CHOSEN.with(|chosen| *chosen.borrow_mut() = self.0.take());
        }
    }
    let _restore = Restore(CHOSEN.with(|chosen| chosen.borrow_mut().replace(Arc::clone(&own.pool))));
    work()
}

/// Runs `work` where its parallel iterators find live threads: on the pool this thread is a
/// thread of, if any (work already running on a pool stays there); else on the pool
/// `with_pool` chose for this thread, if any; else directly (rayon's global pool) in the process
/// that owns it, in a pool of the child's own after a fork.
///
/// `work` must be pure computation: a pool thread waiting for its share of one call's work may
/// run another call's, so nothing inside may take a lock or wait for the GPU.
pub fn install<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        return work();
    }
    if let Some(pool) = CHOSEN.with(|chosen| chosen.borrow().clone()) {
        return pool.install(work);
    }
    let pid = std::process::id();
    if *GLOBAL_POOL_OWNER.get_or_init(|| pid) == pid {
        return work();
    }
    match child_pool(pid) {
        Some(pool) => pool.install(work),
        None => work(),
    }
}

/// `dst.copy_from_slice(src)` in pieces of 128 KiB on all cores (host staging passes). Pieces of
/// a megabyte left a chunk's 2 MB of counts to two cores: on the H200's 16, a million rays' `t`
/// unpacked in 0.13 ms instead of 0.21, and every field of a closest hit in 0.73 instead of 1.75.
pub fn copy(dst: &mut [u8], src: &[u8]) {
    use rayon::prelude::*;
    const PIECE_BYTES: usize = 1 << 17;
    assert_eq!(dst.len(), src.len(), "a parallel copy's two sides differ in length");
    install(|| {
        dst.par_chunks_mut(PIECE_BYTES).zip(src.par_chunks(PIECE_BYTES)).for_each(|(d, s)| d.copy_from_slice(s))
    });
}

/// This forked child's pool (made on first use); `None` if no thread can be started.
fn child_pool(pid: u32) -> Option<Arc<ThreadPool>> {
    let mut held = CHILD_POOL.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((owner, pool)) = held.as_ref() {
        if *owner == pid {
            return Some(pool.clone());
        }
    }
    let pool = Arc::new(ThreadPoolBuilder::new().thread_name(|k| format!("vkray-{k}")).build().ok()?);
    // A grandparent's pool in a child of a child: its threads stayed behind. Dropping it would
    // signal threads that do not exist here; leave it be.
    if let Some(inherited) = held.replace((pid, pool.clone())) {
        std::mem::forget(inherited);
    }
    Some(pool)
}

/// Bytes of a huge page (x86-64 and arm64 with 4 KiB pages, Linux's transparent huge pages).
const HUGE_PAGE: usize = 2 << 20;

/// Asks Linux to back the whole huge pages inside `v`'s spare room with huge pages, before their
/// first touch: each fault of fresh memory then maps 2 MiB rather than 4 KiB (where transparent
/// huge pages are `madvise`d; numpy asks the same for its large arrays). Below 4 MiB, nothing.
pub fn advise_huge_pages<T>(v: &mut Vec<T>) {
    let spare = v.spare_capacity_mut();
    advise_range(spare.as_mut_ptr() as usize, std::mem::size_of_val(spare));
}

/// `advise_huge_pages` for a vector's values (zeros no one has touched yet).
fn advise_huge_pages_of<T>(v: &mut [T]) {
    advise_range(v.as_mut_ptr() as usize, std::mem::size_of_val(v));
}

/// `advise_huge_pages` for `bytes` of memory from `start`.
fn advise_range(start: usize, bytes: usize) {
    #[cfg(target_os = "linux")]
    {
        if bytes < 2 * HUGE_PAGE {
            return;
        }
        let (first, end) = (start.next_multiple_of(HUGE_PAGE), (start + bytes) / HUGE_PAGE * HUGE_PAGE);
        if end > first {
            // SAFETY: the range lies within one allocation of the caller's; MADV_HUGEPAGE changes
            // how its pages are backed, never their contents. A failure (no transparent huge
            // pages) leaves them as they were.
            unsafe { libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE) };
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (start, bytes);
}

/// A vector of `len` zeros, or `OutOfMemory` where the host cannot give the memory. Zeroed by the
/// allocator (fresh pages of a large allocation are zero already): its pages are first touched
/// by whoever writes the values, not by a pass of zeros before them.
pub fn try_zeroed<T: bytemuck::Zeroable>(len: usize, what: &str) -> crate::error::Result<Vec<T>> {
    let refused = || {
        Error::OutOfMemory(format!(
            "{what} needs {} bytes of host memory, which could not be allocated",
            len.saturating_mul(std::mem::size_of::<T>())
        ))
    };
    let layout = std::alloc::Layout::array::<T>(len).map_err(|_| refused())?;
    if layout.size() == 0 {
        return Ok(Vec::new());
    }
    // SAFETY: the layout's size is not zero.
    let memory = unsafe { std::alloc::alloc_zeroed(layout) } as *mut T;
    if memory.is_null() {
        return Err(refused());
    }
    // SAFETY: `memory` was allocated by the global allocator with `T`'s alignment and room for
    // exactly `len` values, all zero bytes, which `Zeroable` makes valid values of `T`.
    let mut v = unsafe { Vec::from_raw_parts(memory, len, len) };
    advise_huge_pages_of(&mut v);
    Ok(v)
}

/// A vector of `len` copies of `value`, or `OutOfMemory` where the host cannot give the memory
/// (a plain `vec!` aborts the process instead).
pub fn try_vec<T: Clone + Send + Sync>(len: usize, value: T, what: &str) -> crate::error::Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(len).map_err(|_| {
        Error::OutOfMemory(format!(
            "{what} needs {} bytes of host memory, which could not be allocated",
            len.saturating_mul(std::mem::size_of::<T>())
        ))
    })?;
    // Large vectors are filled on all cores: the first touch of fresh pages costs more than the
    // writing (a quarter of a second per GiB on the H100 machine).
    advise_huge_pages(&mut v);
    if len >= 1 << 16 {
        use rayon::prelude::*;
        install(|| v.par_extend(rayon::iter::repeat_n(value, len)));
    } else {
        v.resize(len, value);
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parallel_sections_run_on_the_chosen_pool_and_only_inside_with_pool() {
        let own = OwnPool::new(3, "test-pool").unwrap();
        let inside = with_pool(Some(&own), || {
            install(|| (rayon::current_num_threads(), std::thread::current().name().map(str::to_string)))
        });
        assert_eq!(inside.0, 3);
        assert!(inside.1.unwrap().starts_with("test-pool-"));
        let outside = install(|| std::thread::current().name().map(str::to_string));
        assert!(!outside.unwrap_or_default().starts_with("test-pool-"));
    }

    #[test]
    fn the_earlier_choice_comes_back_after_a_panic() {
        let own = OwnPool::new(1, "panicking-pool").unwrap();
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| with_pool(Some(&own), || panic!("x"))));
        assert!(caught.is_err());
        assert!(CHOSEN.with(|chosen| chosen.borrow().is_none()));
        let nested = OwnPool::new(2, "outer-pool").unwrap();
        let threads = with_pool(Some(&nested), || {
            with_pool(Some(&own), || ());
            install(rayon::current_num_threads)
        });
        assert_eq!(threads, 2);
    }
}

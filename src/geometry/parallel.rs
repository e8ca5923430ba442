//! The thread pool host passes run on: rayon's global pool in the process that first used it,
//! and a pool of its own in a forked child (whose copy of the parent's pool has no threads behind
//! it, so work given to it would never run).

use std::sync::{Arc, Mutex, OnceLock};

use rayon::{ThreadPool, ThreadPoolBuilder};

/// The process whose threads rayon's global pool has (the first to run parallel work here).
static GLOBAL_POOL_OWNER: OnceLock<u32> = OnceLock::new();

/// A forked child's own pool, with the process it belongs to.
static CHILD_POOL: Mutex<Option<(u32, Arc<ThreadPool>)>> = Mutex::new(None);

/// Runs `work` where its parallel iterators find live threads: directly (rayon's global pool)
/// in the process that owns it, in a pool of the child's own after a fork.
///
/// `work` must be pure computation: a pool thread waiting for its share of one call's work may
/// run another call's, so nothing inside may take a lock or wait for the GPU.
pub fn install<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    let pid = std::process::id();
    if *GLOBAL_POOL_OWNER.get_or_init(|| pid) == pid {
        return work();
    }
    match child_pool(pid) {
        Some(pool) => pool.install(work),
        None => work(),
    }
}

/// `dst.copy_from_slice(src)` in pieces of a megabyte on all cores (host staging passes).
pub fn copy(dst: &mut [u8], src: &[u8]) {
    use rayon::prelude::*;
    const PIECE_BYTES: usize = 1 << 20;
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

//! The thread pool host passes run on: rayon's, made anew in a forked child (whose copy of the
//! parent's pool has no threads behind it, so work given to it would never run).

use std::sync::{Arc, Mutex};

use rayon::{ThreadPool, ThreadPoolBuilder};

/// This process's pool, with the process it belongs to.
static POOL: Mutex<Option<(u32, Arc<ThreadPool>)>> = Mutex::new(None);

/// Runs `work` in this process's pool, so that every parallel iterator inside it uses live
/// threads; falls back to the calling thread's default pool if no threads can be started.
///
/// `work` must be pure computation: a pool thread waiting for its share of one call's work may
/// run another call's, so nothing inside may take a lock or wait for the GPU.
pub fn install<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    match pool() {
        Some(pool) => pool.install(work),
        None => work(),
    }
}

fn pool() -> Option<Arc<ThreadPool>> {
    let pid = std::process::id();
    let mut held = POOL.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((owner, pool)) = held.as_ref() {
        if *owner == pid {
            return Some(pool.clone());
        }
    }
    let pool = Arc::new(ThreadPoolBuilder::new().thread_name(|k| format!("vkray-{k}")).build().ok()?);
    // A parent's pool in a forked child: its threads stayed with the parent. Dropping it would
    // signal threads that do not exist here; leave it be.
    if let Some(inherited) = held.replace((pid, pool.clone())) {
        std::mem::forget(inherited);
    }
    Some(pool)
}

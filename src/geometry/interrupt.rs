//! Asking long work whether to stop, and telling how far it got (`Interrupt`): every layer's
//! long loops take one; the Python binding's checks for signals.

use crate::error::Result;

/// Asked between pieces of long work (chunks of rays, blocks of host work) whether the caller
/// wants it stopped: the Python binding checks for signals there, so Ctrl-C stops a query within
/// a chunk's time. An error it returns ends the work; the device stays usable.
pub trait Interrupt: Sync {
    fn check(&self) -> Result<()>;

    /// Hears how far the work got: `done` of `total` items (rays, points). Called between the
    /// same pieces as `check`; by default nobody listens.
    fn progress(&self, _done: usize, _total: usize) {}
}

/// Work that nobody interrupts.
pub struct NoInterrupt;

impl Interrupt for NoInterrupt {
    fn check(&self) -> Result<()> {
        Ok(())
    }
}

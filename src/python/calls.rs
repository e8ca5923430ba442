//! Every call into the core from Python: the GIL released for the whole call, signals (Ctrl-C)
//! and progress checked between its pieces, panics and core errors turned into vkray's
//! exceptions.

use std::panic::AssertUnwindSafe;
use std::sync::Mutex;

use pyo3::create_exception;
use pyo3::exceptions::{PyKeyboardInterrupt, PyMemoryError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;

use crate::error::{Error, Result};
use crate::geometry::interrupt::Interrupt;

create_exception!(_core, VkrayError, PyRuntimeError, "Base class of vkray's own errors.");
create_exception!(_core, NoDeviceError, VkrayError, "No usable Vulkan device (or loader) was found.");
create_exception!(_core, UnsupportedError, VkrayError, "The device lacks something the request needs.");
create_exception!(_core, VulkanError, VkrayError, "A Vulkan call failed.");
create_exception!(_core, ValidationError, VkrayError, "The Khronos validation layer reported a problem.");
create_exception!(
    _core,
    ForkedDeviceError,
    VkrayError,
    "A Device was used in a forked child of the process that opened it."
);

impl From<Error> for PyErr {
    fn from(error: Error) -> PyErr {
        let message = error.to_string();
        match error {
            Error::InvalidValue(_) => PyValueError::new_err(message),
            Error::InvalidType(_) => PyTypeError::new_err(message),
            Error::NoDevice(_) => NoDeviceError::new_err(message),
            Error::Unsupported(_) => UnsupportedError::new_err(message),
            Error::Vulkan { .. } | Error::Allocation(_) => VulkanError::new_err(message),
            Error::OutOfMemory(_) => PyMemoryError::new_err(message),
            Error::Forked(_) => ForkedDeviceError::new_err(message),
            Error::Interrupted => PyKeyboardInterrupt::new_err(()),
            Error::Internal(_) | Error::Cuda { .. } => VkrayError::new_err(message),
            Error::Validation(_) => ValidationError::new_err(message),
        }
    }
}

/// Checks for signals (Ctrl-C) with the GIL taken back for a moment; keeps what the handler
/// raised, for `run` to raise.
struct Signals {
    raised: Mutex<Option<PyErr>>,
    /// Called with (done, total) as the work goes (a progress bar's update).
    progress: Option<Py<PyAny>>,
}

impl Signals {
    fn raise(&self, error: PyErr) {
        self.raised.lock().unwrap_or_else(|e| e.into_inner()).get_or_insert(error);
    }
}

impl Interrupt for Signals {
    fn check(&self) -> Result<()> {
        // An exception from the progress callback stops the work as a signal's does.
        if self.raised.lock().unwrap_or_else(|e| e.into_inner()).is_some() {
            return Err(Error::Interrupted);
        }
        Python::attach(|py| py.check_signals()).map_err(|raised| {
            self.raise(raised);
            Error::Interrupted
        })
    }

    fn progress(&self, done: usize, total: usize) {
        if let Some(callback) = &self.progress {
            if let Err(error) = Python::attach(|py| callback.call1(py, (done, total)).map(drop)) {
                self.raise(error);
            }
        }
    }
}

/// Runs core work with the GIL released, interruptible between its pieces; a panic becomes
/// `VkrayError`, never pyo3's `PanicException`.
pub(super) fn run<T: Send>(py: Python<'_>, work: impl FnOnce(&dyn Interrupt) -> Result<T> + Send) -> PyResult<T> {
    run_reporting(py, None, work)
}

/// `run`, telling `progress` (a callable, if any) how far the work got: (done, total).
pub(super) fn run_reporting<T: Send>(
    py: Python<'_>,
    progress: Option<Py<PyAny>>,
    work: impl FnOnce(&dyn Interrupt) -> Result<T> + Send,
) -> PyResult<T> {
    let signals = Signals { raised: Mutex::new(None), progress };
    // Runs on this thread, not in the thread pool: the work takes locks and waits, which a pool
    // thread must never do (waiting for its own parallel work, it may pick up another call's
    // job that needs a lock this thread holds). Parallel sections enter the pool themselves.
    let outcome = py.detach(|| std::panic::catch_unwind(AssertUnwindSafe(|| work(&signals))));
    let result = outcome.unwrap_or_else(|panic| {
        let message = panic
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| panic.downcast_ref::<&str>().copied())
            .unwrap_or("a panic without a message");
        Err(Error::Internal(message.to_string()))
    });
    result.map_err(|error| match error {
        Error::Interrupted => {
            signals.raised.lock().unwrap_or_else(|e| e.into_inner()).take().unwrap_or_else(|| error.into())
        }
        error => error.into(),
    })
}

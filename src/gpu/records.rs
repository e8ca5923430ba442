//! GPU records: see below.

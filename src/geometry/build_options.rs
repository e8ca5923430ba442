//! What a caller asks of a hierarchy's build (its preference, refits, compaction) and what a
//! build reports (bytes and time): the same words for every engine.

use crate::error::{invalid_value, Result};

/// What a build optimizes for (Vulkan's `PREFER_*` flags; a CPU engine's builder quality).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildPreference {
    FastTrace,
    FastBuild,
    LowMemory,
}

impl BuildPreference {
    pub fn parse(name: &str) -> Result<BuildPreference> {
        match name {
            "fast_trace" => Ok(BuildPreference::FastTrace),
            "fast_build" => Ok(BuildPreference::FastBuild),
            "low_memory" => Ok(BuildPreference::LowMemory),
            other => {
                Err(invalid_value(format!("build must be 'fast_trace', 'fast_build' or 'low_memory', got {other:?}")))
            }
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            BuildPreference::FastTrace => "fast_trace",
            BuildPreference::FastBuild => "fast_build",
            BuildPreference::LowMemory => "low_memory",
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct BuildOptions {
    pub preference: BuildPreference,
    pub allow_update: bool,
    pub compact: bool,
}

/// Sizes and time of one build.
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildStats {
    /// Bytes of the structure as built.
    pub built_size: u64,
    /// Bytes it occupies now (after compaction where asked).
    pub size: u64,
    pub scratch_size: u64,
    pub update_scratch_size: u64,
    /// Wall time from submission to a usable structure, compaction included (for structures
    /// built together, their batch's time).
    pub build_seconds: f64,
    /// Which submission of a batched build made it (0 for a single build).
    pub batch: u32,
}

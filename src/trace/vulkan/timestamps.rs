//! The device's own timestamps of a chunk's phases (upload, trace, readback), for `TraceProfile`.

use std::sync::Arc;

use ash::vk;

use crate::error::{Result, VkResultExt};
use crate::gpu::context::Context;
use crate::trace::profile::TraceProfile;

/// The phases of one chunk that timestamps separate, in order (their query slots 0 to 3): start,
/// after upload, after trace, after readback.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stamp {
    Start,
    Uploaded,
    Traced,
    ReadBack,
}

const STAMPS: u32 = 4;

/// A timestamp query pool for one chunk in flight: each staging slot owns one, so traces running
/// at once never share (or lock) timestamps.
pub struct Stamps {
    ctx: Arc<Context>,
    pool: vk::QueryPool,
    tick_seconds: f64,
    mask: u64,
}

impl Stamps {
    /// A pool where the device's queue has timestamps, else `None`.
    pub fn new(ctx: &Arc<Context>) -> Result<Option<Stamps>> {
        let bits = ctx.limits.timestamp_valid_bits;
        if bits == 0 || ctx.limits.timestamp_period <= 0.0 {
            return Ok(None);
        }
        let info = vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(STAMPS);
        // SAFETY: a valid create info on a live device.
        let pool = unsafe { ctx.device.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        let mask = if bits >= 64 { u64::MAX } else { (1u64 << bits) - 1 };
        Ok(Some(Stamps { ctx: ctx.clone(), pool, tick_seconds: ctx.limits.timestamp_period as f64 * 1e-9, mask }))
    }

    pub fn reset(&self, cmd: vk::CommandBuffer) {
        // SAFETY: `cmd` is recording; the pool is this device's and no submitted work uses it (the
        // slot's previous chunk was waited for before its commands are recorded again).
        unsafe { self.ctx.device.cmd_reset_query_pool(cmd, self.pool, 0, STAMPS) };
    }

    /// Writes `stamp` once all earlier commands are done.
    pub fn write(&self, cmd: vk::CommandBuffer, stamp: Stamp) {
        let stage = match stamp {
            Stamp::Start => vk::PipelineStageFlags::TOP_OF_PIPE,
            _ => vk::PipelineStageFlags::BOTTOM_OF_PIPE,
        };
        // SAFETY: `cmd` is recording and the query was reset earlier in the same command buffer.
        unsafe { self.ctx.device.cmd_write_timestamp(cmd, stage, self.pool, stamp as u32) };
    }

    /// Adds a finished chunk's upload, trace and readback times to `profile`.
    pub fn add_to(&self, profile: &mut TraceProfile) -> Result<()> {
        let mut ticks = [0u64; STAMPS as usize];
        // SAFETY: the chunk's fence was waited for, so every query was written; 64-bit results.
        unsafe {
            self.ctx.device.get_query_pool_results(
                self.pool,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .vk("vkGetQueryPoolResults")?;
        let span = |k: usize| (ticks[k + 1].wrapping_sub(ticks[k]) & self.mask) as f64 * self.tick_seconds;
        for (k, phase) in
            [&mut profile.gpu_upload, &mut profile.gpu_trace, &mut profile.gpu_readback].into_iter().enumerate()
        {
            *phase = Some(phase.unwrap_or(0.0) + span(k));
        }
        Ok(())
    }
}

/// Resets a chunk's `stamps` (where the device has them) and writes `Stamp::Start`; the returned
/// closure writes the chunk's later stamps.
pub fn start_stamps(stamps: Option<&Stamps>, cmd: vk::CommandBuffer) -> impl Fn(Stamp) + '_ {
    if let Some(stamps) = stamps {
        stamps.reset(cmd);
        stamps.write(cmd, Stamp::Start);
    }
    move |stamp| {
        if let Some(stamps) = stamps {
            stamps.write(cmd, stamp);
        }
    }
}

impl Drop for Stamps {
    fn drop(&mut self) {
        if self.ctx.forked() {
            return;
        }
        // SAFETY: slots are dropped only when no chunk of theirs is in flight.
        unsafe { self.ctx.device.destroy_query_pool(self.pool, None) };
    }
}

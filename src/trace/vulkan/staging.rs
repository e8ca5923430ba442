//! Staging for chunks in flight: host-visible rays and hits (plus device copies on discrete GPUs),
//! each slot with its own timestamps; and the pool that keeps idle slots for the next query.

use std::sync::Arc;

use ash::vk;

use super::timestamps::Stamps;
use crate::error::Result;
use crate::geometry::align::align_up;
use crate::geometry::rays::{RayLayout, RAY_FLOATS};
use crate::gpu::context::Context;
use crate::gpu::memory::{upload_staging, Buffer, MemoryLocation};
use crate::gpu::records::ExactBest;
use crate::trace::hit_fields::{Field, FIELDS, FIELD_COUNT};
use crate::trace::idle::{Held, IdleMemory, IdlePool};

/// Bytes of a pair of device copies, where there is one.
pub fn pair_bytes(device: &Option<(Buffer, Buffer)>) -> u64 {
    device.as_ref().map_or(0, |(a, b)| a.size() + b.size())
}

/// Host-visible staging for one chunk in flight (plus device copies on discrete GPUs). An exact
/// slot holds f64 rays, f64 `t`/`uv` and the pipeline's scratch records.
pub struct Slot {
    pub rays_host: Buffer,
    pub hits_host: Buffer,
    pub device: Option<(Buffer, Buffer)>,
    pub capacity: usize,
    pub exact: bool,
    pub stamps: Option<Stamps>,
    /// How the chunk now in the slot lies in its ray staging (f32 rays; set as it is packed).
    pub layout: RayLayout,
}

/// Where a chunk's rays are packed: a slot's ray staging (`Slot::split`).
pub struct RayStaging<'a> {
    pub rays: &'a mut Buffer,
    /// How the chunk lies in it (set as it is packed).
    pub layout: &'a mut RayLayout,
    pub masks_at: usize,
    pub exact: bool,
}

/// Where a finished chunk's hits are read: a slot's readback and timestamps (`Slot::split`).
pub struct HitReadback<'a> {
    pub hits: &'a Buffer,
    pub stamps: Option<&'a Stamps>,
    pub capacity: usize,
    pub exact: bool,
}

impl HitReadback<'_> {
    /// Byte offset of a field's array within the readback.
    pub fn field_offset(&self, field: Field) -> usize {
        Slot::layout(self.capacity, self.exact).0[field as usize]
    }
}

impl Held for Slot {
    fn bytes(&self) -> u64 {
        self.rays_host.size() + self.hits_host.size() + pair_bytes(&self.device)
    }
}

impl Slot {
    fn new(ctx: &Arc<Context>, capacity: usize, exact: bool) -> Result<Slot> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let ray_bytes = (capacity * (Slot::ray_bytes(exact) + 4)) as u64;
        let hit_bytes = Slot::layout(capacity, exact).1 as u64;
        let (rays_host, hits_host, device) = if ctx.unified_memory {
            let rays = Buffer::new(ctx, ray_bytes, storage, MemoryLocation::CpuToGpu, "rays")?;
            (rays, Buffer::new(ctx, hit_bytes, storage, MemoryLocation::GpuToCpu, "hits")?, None)
        } else {
            (
                Buffer::new(ctx, ray_bytes, U::TRANSFER_SRC, upload_staging(), "rays staging")?,
                Buffer::new(ctx, hit_bytes, U::TRANSFER_DST, MemoryLocation::GpuToCpu, "hits readback")?,
                Some((
                    Buffer::new(ctx, ray_bytes, storage | U::TRANSFER_DST, MemoryLocation::GpuOnly, "rays")?,
                    Buffer::new(ctx, hit_bytes, storage | U::TRANSFER_SRC, MemoryLocation::GpuOnly, "hits")?,
                )),
            )
        };
        Ok(Slot { rays_host, hits_host, device, capacity, exact, stamps: Stamps::new(ctx)?, layout: RayLayout::Full })
    }

    /// The slot's ray staging (which packing writes) and hit readback (which finishing reads),
    /// borrowed apart: once the slot's chunk is done on the GPU, its hits are copied out while
    /// the next chunk's rays are packed into the same slot.
    pub fn split(&mut self) -> (RayStaging<'_>, HitReadback<'_>) {
        let masks_at = self.masks_offset();
        let Slot { rays_host, hits_host, capacity, exact, stamps, layout, .. } = self;
        (
            RayStaging { rays: rays_host, layout, masks_at, exact: *exact },
            HitReadback { hits: hits_host, stamps: stamps.as_ref(), capacity: *capacity, exact: *exact },
        )
    }

    /// Bytes of one packed ray; the rays buffer holds `capacity` of them, then one u32 mask each.
    pub fn ray_bytes(exact: bool) -> usize {
        RAY_FLOATS * if exact { 8 } else { 4 }
    }

    /// Host bytes a slot of `capacity` rays takes (its staging, not its device copies).
    pub fn host_bytes(capacity: usize, exact: bool) -> usize {
        capacity * (Slot::ray_bytes(exact) + 4) + Slot::layout(capacity, exact).1
    }

    /// Bytes of the chunk of `len` rays now in the slot's ray staging.
    pub fn packed_bytes(&self, len: usize) -> usize {
        if self.exact {
            self.layout.exact_bytes(len)
        } else {
            self.layout.bytes(len)
        }
    }

    pub fn masks_offset(&self) -> usize {
        self.capacity * Slot::ray_bytes(self.exact)
    }

    /// Byte offsets of each field's array and of the scratch records, and the total, each array
    /// 8-byte aligned (f64 fields).
    pub fn layout(capacity: usize, exact: bool) -> ([usize; FIELD_COUNT + 1], usize) {
        let mut offsets = [0; FIELD_COUNT + 1];
        let mut at = 0;
        for field in FIELDS {
            offsets[field as usize] = at;
            at = align_up((at + capacity * field.bytes_per_ray(exact)) as u64, 8) as usize;
        }
        offsets[FIELD_COUNT] = at;
        if exact {
            at += capacity * std::mem::size_of::<ExactBest>();
        }
        (offsets, at)
    }

    /// Byte offset of a field's array within the hits buffer.
    pub fn field_offset(&self, field: Field) -> usize {
        Slot::layout(self.capacity, self.exact).0[field as usize]
    }

    pub fn scratch_offset(&self) -> usize {
        Slot::layout(self.capacity, self.exact).0[FIELD_COUNT]
    }

    pub fn rays_address(&self) -> u64 {
        self.device.as_ref().map_or(self.rays_host.address(), |(rays, _)| rays.address())
    }

    pub fn hits_address(&self) -> u64 {
        self.device.as_ref().map_or(self.hits_host.address(), |(_, hits)| hits.address())
    }
}

/// Idle slots kept between queries (allocating staging is slow on discrete GPUs), a pool for
/// each kind (f32 rays, and the exact tier's f64 ones): a burst of one kind does not push the
/// other kind's slots out.
pub struct SlotPool {
    ctx: Arc<Context>,
    idle: [IdlePool<Slot>; 2],
}

/// Two slots serve one query: keep as many as ran at once, at least one query's worth and at
/// most eight, of each kind.
const IDLE_SLOTS: (usize, usize) = (2, 16);

impl SlotPool {
    pub fn new(ctx: &Arc<Context>) -> SlotPool {
        let pool = || IdlePool::new(IDLE_SLOTS.0, IDLE_SLOTS.1);
        SlotPool { ctx: ctx.clone(), idle: [pool(), pool()] }
    }

    /// Two slots of at least `capacity` rays for one query: idle ones where they fit, new ones
    /// (allocated outside the lock) otherwise. Idle slots too small for it stay for smaller
    /// queries (the pool drops the oldest beyond what it keeps).
    pub fn take(&self, capacity: usize, exact: bool) -> Result<[Slot; 2]> {
        let idle = &self.idle[exact as usize];
        let mut found = idle.take(2, |s| s.capacity >= capacity, |_| true);
        while found.len() < 2 {
            match Slot::new(&self.ctx, capacity, exact) {
                Ok(slot) => found.push(slot),
                Err(error) => {
                    idle.give_back(2, found);
                    return Err(error);
                }
            }
        }
        let second = found.pop().expect("two slots");
        let first = found.pop().expect("two slots");
        Ok([first, second])
    }

    pub fn give_back(&self, slots: [Slot; 2]) {
        self.idle[slots[0].exact as usize].give_back(2, slots);
    }

    pub fn memory(&self) -> IdleMemory {
        self.idle[0].memory() + self.idle[1].memory()
    }

    pub fn clear(&self) {
        self.idle.iter().for_each(IdlePool::clear);
    }
}

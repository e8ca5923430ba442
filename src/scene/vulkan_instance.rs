//! The bits of a placement's Vulkan instance record: its flags, custom index and hit group.

use super::instance::Placement;
use super::mesh::MeshKind;
use crate::gpu::accel::InstanceBits;

// Instance flags of `VkGeometryInstanceFlagBitsKHR`.
const INSTANCE_CULL_DISABLE: u8 = 0x1;
const INSTANCE_FRONT_COUNTERCLOCKWISE: u8 = 0x2;
const INSTANCE_FORCE_OPAQUE: u8 = 0x4;
const INSTANCE_FORCE_NO_OPAQUE: u8 = 0x8;

/// Largest custom index a Vulkan instance can carry (24 bits).
pub const MAX_CUSTOM_INDEX: u32 = (1 << 24) - 1;

/// The bits of `placement`'s Vulkan instance record: spheres' hits go to the second hit group of
/// the shader binding table (the procedural one).
pub fn instance_bits(placement: &Placement) -> InstanceBits {
    InstanceBits {
        custom_index: placement.custom_index,
        mask: placement.mask,
        flags: vulkan_flags(placement),
        sbt_offset: (placement.mesh.kind == MeshKind::Spheres) as u32,
    }
}

/// Vulkan's instance flags. Vulkan judges facing in object space and by default calls front the
/// side `cross(v1 - v0, v2 - v0)` points to (clockwise seen from the ray, in its left-handed
/// wording), our convention too; its counter-clockwise flag swaps the two.
fn vulkan_flags(placement: &Placement) -> u8 {
    let mut flags = 0;
    if placement.flags.cull_disable {
        flags |= INSTANCE_CULL_DISABLE;
    }
    if placement.flip_facing {
        flags |= INSTANCE_FRONT_COUNTERCLOCKWISE;
    }
    if placement.flags.force_opaque {
        flags |= INSTANCE_FORCE_OPAQUE;
    }
    if placement.flags.force_no_opaque {
        flags |= INSTANCE_FORCE_NO_OPAQUE;
    }
    flags
}

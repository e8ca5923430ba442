//! Host-side geometry: the caller's arrays and their checks, rays and their packing, vertex
//! formats, Morton order, f64 ray–triangle math, the CPU BVH and winding numbers over it.
//! Nothing here touches Vulkan.

pub mod arrays;
pub mod morton;
pub mod parallel;
pub mod precision;
pub mod rays;
pub mod reference;
pub mod sensor;
pub mod vertex_format;
pub mod winding;

/// Rounds `value` up to a multiple of `alignment` (a power of two, or 0/1 for none).
pub fn align_up(value: u64, alignment: u64) -> u64 {
    if alignment <= 1 {
        value
    } else {
        value.div_ceil(alignment) * alignment
    }
}

#[cfg(test)]
mod tests {
    use super::align_up;

    #[test]
    fn align_up_rounds_to_multiples() {
        assert_eq!(align_up(0, 128), 0);
        assert_eq!(align_up(1, 128), 128);
        assert_eq!(align_up(128, 128), 128);
        assert_eq!(align_up(129, 8), 136);
        assert_eq!(align_up(7, 0), 7);
        assert_eq!(align_up(7, 1), 7);
    }
}

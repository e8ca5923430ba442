//! Rounding sizes and offsets up to alignments (buffers, records, shader binding tables).

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

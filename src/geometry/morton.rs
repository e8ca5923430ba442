//! Morton (Z-order) sorting of triangles, for BVH builders that split primitives in input order.

use super::arrays::{Indices, Vec3s};

/// Spreads the low 21 bits of `x` to every third bit.
fn spread_bits(x: u64) -> u64 {
    let mut x = x & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    (x | x << 2) & 0x1249_2492_4924_9249
}

/// Triangles sorted along a Morton (Z-order) curve through their centroids: new position ->
/// caller's triangle. Neighbours in this order are neighbours in space, which is what a BVH
/// builder that splits primitives in input order (lavapipe's) needs to build a good tree.
pub fn morton_order(vertices: Vec3s, faces: Indices) -> Vec<u32> {
    let n = faces.triangles();
    let centroid = |t: usize| {
        let mut c = [0.0f64; 3];
        for k in 0..3 {
            let v = vertices.row_f64(faces.corner(t, k));
            for a in 0..3 {
                c[a] += v[a] / 3.0;
            }
        }
        c
    };
    let centroids: Vec<[f64; 3]> = (0..n).map(centroid).collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for c in &centroids {
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let scale: Vec<f64> = (0..3).map(|a| if hi[a] > lo[a] { 2097151.0 / (hi[a] - lo[a]) } else { 0.0 }).collect();
    let mut keyed: Vec<(u64, u32)> = centroids
        .iter()
        .enumerate()
        .map(|(t, c)| {
            let q = |a: usize| ((c[a] - lo[a]) * scale[a]) as u64;
            (spread_bits(q(0)) | spread_bits(q(1)) << 1 | spread_bits(q(2)) << 2, t as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, t)| t).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_order_groups_neighbours() {
        // Four triangles along x, given far-near-far-near: the order visits them left to right.
        let mut v = Vec::new();
        for x in [3.0, 0.0, 2.0, 1.0] {
            v.extend_from_slice(&[x, 0.0, 0.0, x + 0.1, 0.0, 0.0, x, 0.1, 0.0]);
        }
        let f: Vec<u32> = (0..12).collect();
        assert_eq!(morton_order(Vec3s::F64(&v), Indices::U32(&f)), vec![1, 3, 2, 0]);
        // A permutation of every triangle.
        let mut sorted = morton_order(Vec3s::F64(&v), Indices::U32(&f));
        sorted.sort();
        assert_eq!(sorted, vec![0, 1, 2, 3]);
    }
}

//! Morton (Z-order) sorting of triangles, for BVH builders that split primitives in input order,
//! and of points, for queries whose neighbouring invocations should walk the same nodes.

use glam::DVec3;
use rayon::prelude::*;

use super::arrays::{Indices, Vec3s};
use super::parallel;

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

/// Cells along each axis of `point_order`'s grid.
pub const POINT_GRID: u32 = 64;

/// The points sorted cell by cell of a `POINT_GRID`³ grid over the box [lo, hi], the cells along
/// a Morton curve (points outside the box go to its border cells), in input order within a cell:
/// new position -> caller's point. On all cores. Rays cast from neighbouring points in this
/// order cross the same nodes, which a GPU runs side by side far faster (the host's version of
/// shaders/point_order.comp, for rays).
pub fn point_order(points: Vec3s, lo: DVec3, hi: DVec3) -> Vec<u32> {
    let extent = (hi - lo).max(DVec3::splat(f64::MIN_POSITIVE));
    let scale = DVec3::splat(f64::from(POINT_GRID)) / extent;
    let top = f64::from(POINT_GRID - 1);
    let cell = |i: usize| {
        let q = ((DVec3::from_array(points.row_f64(i)) - lo) * scale).clamp(DVec3::ZERO, DVec3::splat(top));
        // NaN (never: contains refuses non-finite points) would go to cell 0.
        spread_bits(q.x as u64) | spread_bits(q.y as u64) << 1 | spread_bits(q.z as u64) << 2
    };
    parallel::install(|| {
        let mut keyed: Vec<u64> =
            (0..points.rows()).into_par_iter().with_min_len(4096).map(|i| cell(i) << 32 | i as u64).collect();
        keyed.par_sort_unstable();
        keyed.into_par_iter().with_min_len(4096).map(|k| k as u32).collect()
    })
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

    #[test]
    fn point_order_visits_cells_along_the_curve() {
        // Along x: cells 3, 0, 2, 0 (two in cell 0, kept in input order), and one far outside.
        let step = 1.0 / f64::from(POINT_GRID);
        let xs = [3.5 * step, 0.2 * step, 2.5 * step, 0.7 * step, -5.0];
        let v: Vec<f64> = xs.iter().flat_map(|&x| [x, 0.0, 0.0]).collect();
        let order = point_order(Vec3s::F64(&v), DVec3::ZERO, DVec3::ONE);
        assert_eq!(order, vec![1, 3, 4, 2, 0]);
        // A step along y comes after the cells of x 0 and 1 (the curve's first square).
        let v = [0.0, 1.5 * step, 0.0, 1.5 * step, 0.0, 0.0, 2.5 * step, 0.0, 0.0];
        assert_eq!(point_order(Vec3s::F64(&v), DVec3::ZERO, DVec3::ONE), vec![1, 0, 2]);
    }
}

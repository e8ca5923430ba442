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

/// Cells along each axis of the grid points are ordered by (here and in point_order.comp).
pub const POINT_GRID: u32 = 64;

/// Cells along each axis of the host's grid (`point_order`): a counting sort over 32³ cells
/// keeps each thread's counters in its cache.
const HOST_GRID: u32 = 32;

/// An order of n points: new position -> caller's point, each point exactly once (only
/// `point_order` makes one, which is what lets `scatter` write from several threads).
pub struct Permutation(Vec<u32>);

/// The points sorted cell by cell of a 32³ grid over the box [lo, hi], the cells along a Morton
/// curve (points outside the box go to its border cells; NaN to the first), in input order within
/// a cell. A counting sort on all cores. Rays cast from neighbouring points in this order cross
/// the same nodes, which a GPU runs side by side far faster (the host's version of
/// shaders/point_order.comp, for rays).
pub fn point_order(points: Vec3s, lo: DVec3, hi: DVec3) -> Permutation {
    const CELLS: usize = (HOST_GRID * HOST_GRID * HOST_GRID) as usize;
    let n = points.rows();
    let extent = (hi - lo).max(DVec3::splat(f64::MIN_POSITIVE));
    let scale = DVec3::splat(f64::from(HOST_GRID)) / extent;
    let top = DVec3::splat(f64::from(HOST_GRID - 1));
    let cell = |i: usize| {
        let q = ((DVec3::from_array(points.row_f64(i)) - lo) * scale).clamp(DVec3::ZERO, top);
        (spread_bits(q.x as u64) | spread_bits(q.y as u64) << 1 | spread_bits(q.z as u64) << 2) as u32
    };
    parallel::install(|| {
        // One block of points a thread: each counts its points per cell.
        let block = n.div_ceil(rayon::current_num_threads().max(1)).max(1 << 14);
        let cells: Vec<u32> = (0..n).into_par_iter().with_min_len(4096).map(cell).collect();
        let mut next: Vec<Vec<u32>> = cells
            .par_chunks(block)
            .map(|chunk| {
                let mut counts = vec![0u32; CELLS];
                for &c in chunk {
                    counts[c as usize] += 1;
                }
                counts
            })
            .collect();
        // Where each block's points of each cell start: cell by cell, block by block.
        let mut total = 0u32;
        for c in 0..CELLS {
            for counts in next.iter_mut() {
                let count = counts[c];
                counts[c] = total;
                total += count;
            }
        }
        let mut order = vec![0u32; n];
        let out = SharedOut(order.as_mut_ptr());
        cells.par_chunks(block).zip(next.par_iter_mut()).enumerate().for_each(|(b, (chunk, next))| {
            let out = &out;
            for (k, &c) in chunk.iter().enumerate() {
                let at = &mut next[c as usize];
                // SAFETY: `at` runs over this block's own range of this cell's slots (the prefix
                // sums above), so every slot of `order` (n of them) is written by one block once.
                unsafe { out.0.add(*at as usize).write((b * block + k) as u32) };
                *at += 1;
            }
        });
        Permutation(order)
    })
}

/// A pointer the blocks of one scatter share, each writing its own slots.
struct SharedOut<T>(*mut T);
// SAFETY: the threads that share it write disjoint slots (see its uses).
unsafe impl<T: Send> Sync for SharedOut<T> {}

impl Permutation {
    /// New position -> caller's point.
    pub fn as_slice(&self) -> &[u32] {
        &self.0
    }

    /// Writes `values[k]` to `out[self[k]]` for every k, on all cores.
    pub fn scatter<T: Copy + Send + Sync>(&self, values: &[T], out: &mut [T]) {
        assert!(values.len() == self.0.len() && out.len() == self.0.len(), "a permutation scatters its own length");
        let shared = SharedOut(out.as_mut_ptr());
        parallel::install(|| {
            self.0.par_iter().zip(values).with_min_len(4096).for_each(|(&i, &v)| {
                let shared = &shared;
                // SAFETY: `self` is a permutation of 0..out.len() (point_order's): each slot is
                // written once, by one thread, within bounds.
                unsafe { shared.0.add(i as usize).write(v) };
            })
        });
    }
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
        let step = 1.0 / f64::from(HOST_GRID);
        let xs = [3.5 * step, 0.2 * step, 2.5 * step, 0.7 * step, -5.0];
        let v: Vec<f64> = xs.iter().flat_map(|&x| [x, 0.0, 0.0]).collect();
        let order = point_order(Vec3s::F64(&v), DVec3::ZERO, DVec3::ONE);
        assert_eq!(order.as_slice(), [1, 3, 4, 2, 0]);
        let mut back = [0.0; 5];
        order.scatter(&[10.0, 11.0, 12.0, 13.0, 14.0], &mut back);
        assert_eq!(back, [14.0, 10.0, 13.0, 11.0, 12.0]);
        // A step along y comes after the cells of x 0 and 1 (the curve's first square).
        let v = [0.0, 1.5 * step, 0.0, 1.5 * step, 0.0, 0.0, 2.5 * step, 0.0, 0.0];
        assert_eq!(point_order(Vec3s::F64(&v), DVec3::ZERO, DVec3::ONE).as_slice(), [1, 0, 2]);
    }
}

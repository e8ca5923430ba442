//! A grid over a scene's bounds that answers `contains` for the points of most of its cells with
//! one lookup. A cell that no surface comes near lies, with its neighbours of the same kind, in one
//! region of the space that the scene's closed surfaces part; the count of crossings of a closed
//! surface is the same (mod 2, or signed) from every point of a region, so one exact answer at one
//! point of the region is every point's. A mesh closed by caps over its holes (the winding method
//! of a scene of one instance) keeps each region's signed count of crossings of the mesh and its
//! caps; the caps' solid angles add less than `CAP_WINDING_LIMIT` to it except in the cells near
//! a hole, whose points add their own. Points in cells near a surface are left to the exact test
//! (`trace::grid_contains` runs it on a short ray to the next decided cell).

use std::f64::consts::PI;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;

use super::instance::Placement;
use super::winding_cap::CapGeometry;
use crate::error::Result;
use crate::geometry::parallel;
use crate::geometry::precision::Aabb;

/// A grid cell's answer: every point of the cell is outside.
pub const GRID_OUTSIDE: u8 = 0;
/// Every point of the cell is inside.
pub const GRID_INSIDE: u8 = 1;
/// The cell lies near a surface (or a cap): its points take the exact test.
pub const GRID_UNDECIDED: u8 = 2;

/// The most cells a grid holds (two bytes each for the build's values, two bits for the marks
/// the queries read): 128³. Undecided points fall as the cells shrink
/// (as the cube root of their count), the build's time grows with the count.
pub const GRID_CELLS: usize = 1 << 21;

/// The most triangles (over all instances) a grid is built over: each is placed and drawn in once.
pub const GRID_MAX_TRIANGLES: usize = 1 << 24;

/// Regions of fewer cells than this are left undecided: their one exact answer would cost more
/// than their points' own tests saved.
const SMALLEST_REGION: usize = 4;

/// Cells near enough a hole for the caps' winding number about them to reach this (a bound: the
/// sum over the holes) stay undecided: elsewhere it stays below 1/2 by more than any rounding, so
/// the integer count of crossings of the mesh and its caps alone decides.
pub const CAP_WINDING_LIMIT: f64 = 0.45;

/// A scene's grid of answers (`GRID_OUTSIDE`, `GRID_INSIDE`, `GRID_UNDECIDED` a cell), in the
/// scene's frame.
pub struct InsideGrid {
    min: DVec3,
    inverse_cell: f64,
    dims: [usize; 3],
    /// Each cell's region's value (`CellValue`, packed by `pack`).
    cells: Vec<u16>,
    /// Each cell's answer as `mark_rows` gives it (`GRID_OUTSIDE`, `GRID_INSIDE`, `GRID_UNDECIDED`),
    /// two bits a cell, four cells a byte (cell i in bits 2(i % 4) of byte i / 4): 2.2M cells
    /// take 0.55 MB, which a core's cache holds (a byte a cell: 1M points' lookups 12 against 17
    /// ms on one core of this project's machine).
    marks: Vec<u8>,
    counts: bool,
    /// The caps the grid was built with (the winding method of a scene of one instance).
    cap: Option<CapGeometry>,
    /// The share of cells left undecided (near a surface, or in too small a region).
    pub undecided: f64,
    /// The share of cells near a cap's hole, whose points add the caps' winding number.
    pub near_caps: f64,
    /// How many regions took an exact answer.
    pub regions: usize,
    pub build_seconds: f64,
}

/// What a grid is built over: the scene's triangle placements and, for the winding method of a
/// scene of one instance with holes, the caps over them.
pub struct GridSurfaces<'a> {
    pub placements: &'a [Placement],
    pub cap: Option<CapGeometry>,
    /// The scene's bounds (its frame).
    pub bounds: Aabb,
    /// The largest size of a world coordinate of the scene: points were moved into the scene's
    /// frame with rounding of this size.
    pub world_scale: f64,
}

impl InsideGrid {
    /// The answer of the cell holding each of the 3-column `rows` (world frame; the scene's frame
    /// is `center` away) into `marks`; whether every row was finite. A point beyond the grid,
    /// which holds the scene's bounds grown by a cell, is outside. Batches of points take two
    /// loops: their cells' indices (arithmetic alone, which the compiler unrolls and vectorizes),
    /// then the cells' lookups, without branches on the point: the answers of random points are
    /// unpredictable, and a mispredicted branch also discards the loads begun for the points after
    /// it. 1M random points in a grid of 2.2M cells: 12–14 ms on one core of this project's
    /// machine (24–29 a point at a time, 78 with branches), 1.0 ms on the H200 machine's 16 cores
    /// (2.0 a point at a time).
    pub fn mark_rows<T: Copy + Into<f64>>(&self, rows: &[T], center: DVec3, marks: &mut [u8]) -> bool {
        const BATCH: usize = 256;
        let [nx, ny, nz] = self.dims;
        let inside = |v: f64, n: usize| v >= 0.0 && v < n as f64;
        debug_assert_eq!(rows.len(), 3 * marks.len(), "a mark for every row");
        let (mut finite, mut cells) = (true, [0u32; BATCH]);
        for (marks, rows) in marks.chunks_mut(BATCH).zip(rows.chunks(3 * BATCH)) {
            for (cell, p) in cells.iter_mut().zip(rows.chunks_exact(3)) {
                let p = DVec3::new(p[0].into(), p[1].into(), p[2].into());
                finite &= p.is_finite();
                let q = (p - center - self.min) * self.inverse_cell;
                // NaN compares false: outside. `as` saturates; the index of a cell beyond the
                // grid is not used.
                let within = inside(q.x, nx) & inside(q.y, ny) & inside(q.z, nz);
                let (x, y, z) = (q.x as u32, q.y as u32, q.z as u32);
                let index = (z.wrapping_mul(ny as u32).wrapping_add(y)).wrapping_mul(nx as u32).wrapping_add(x);
                *cell = if within { index } else { u32::MAX };
            }
            for (mark, &cell) in marks.iter_mut().zip(&cells) {
                let within = cell != u32::MAX;
                let at = if within { cell as usize } else { 0 };
                let value = (self.marks[at >> 2] >> (2 * (at & 3))) & 3;
                *mark = if within { value } else { GRID_OUTSIDE };
            }
        }
        finite
    }

    /// The value of the cell holding `p` (the scene's frame; `Undecided` beyond the grid).
    #[inline]
    pub fn cell(&self, p: DVec3) -> CellValue {
        let q = ((p - self.min) * self.inverse_cell).to_array();
        if !(0..3).all(|k| q[k] >= 0.0 && q[k] < self.dims[k] as f64) {
            return CellValue::Undecided;
        }
        let [x, y, z] = q.map(|v| v as usize);
        unpack(self.cells[(z * self.dims[1] + y) * self.dims[0] + x])
    }

    /// What a device needs to read the grid as `mark_rows` does: its corner and cells per unit
    /// (the scene's frame), its cells per axis, and its cells' answers (two bits a cell).
    pub fn marks_layout(&self) -> (DVec3, f64, [usize; 3], &[u8]) {
        (self.min, self.inverse_cell, self.dims, &self.marks)
    }

    /// The caps the grid was built with, where it counts crossings of the mesh and its caps.
    pub fn cap(&self) -> Option<&CapGeometry> {
        self.cap.as_ref().filter(|_| self.counts)
    }

    /// The first decided cell that the ray from `p` along `direction` (the scene's frame; every
    /// component positive) enters within `max_cells` cells after `p`'s own: a distance along the
    /// ray inside that cell (halfway through it) and its value (its answer, or where the grid
    /// counts, its count of crossings). None where the ray leaves the grid
    /// or passes `max_cells` undecided cells first.
    pub fn first_decided_along(&self, p: DVec3, direction: DVec3, max_cells: usize) -> Option<(f64, i32)> {
        debug_assert!(direction.cmpgt(DVec3::ZERO).all());
        let cell = 1.0 / self.inverse_cell;
        let q = (p - self.min) * self.inverse_cell;
        let mut at = [q.x.floor(), q.y.floor(), q.z.floor()];
        // The distance along the ray to the next cell wall on each axis.
        let step = (DVec3::splat(cell) / direction).to_array();
        let mut next: [f64; 3] = std::array::from_fn(|k| (self.min[k] + (at[k] + 1.0) * cell - p[k]) / direction[k]);
        for _ in 0..max_cells {
            let axis = if next[0] <= next[1] && next[0] <= next[2] {
                0
            } else if next[1] <= next[2] {
                1
            } else {
                2
            };
            let entered = next[axis];
            at[axis] += 1.0;
            next[axis] += step[axis];
            if !(0..3).all(|k| at[k] >= 0.0 && at[k] < self.dims[k] as f64) {
                return None;
            }
            let [x, y, z] = at.map(|v| v as usize);
            if let CellValue::Decided(value) = unpack(self.cells[(z * self.dims[1] + y) * self.dims[0] + x]) {
                let left = next[0].min(next[1]).min(next[2]);
                return Some((0.5 * (entered + left), value));
            }
        }
        None
    }

    /// The grid's cell count.
    pub fn cell_count(&self) -> usize {
        self.cells.len()
    }

    /// Builds the grid of `surfaces` (see `GridSurfaces`); `decide` tells each region's value from
    /// a point of it (the scene's frame): where the grid `counts`, the signed count of crossings
    /// of the mesh and its caps of a ray from it (the integer part of its winding number), else
    /// `contains`' exact answer (0 or 1).
    pub fn build(
        surfaces: GridSurfaces,
        counts: bool,
        decide: impl FnOnce(&[DVec3], Option<&CapGeometry>) -> Result<Vec<i32>>,
    ) -> Result<InsideGrid> {
        let started = Instant::now();
        let layout = CellLayout::new(surfaces.bounds);
        // Far beyond the rounding of moving a point into the scene's frame (an ulp of its world
        // coordinates) and of telling its cell, and of the exact test's on-surface margin (a few
        // units in the last place of the scene's own coordinates).
        let pad = 1e-12 * surfaces.world_scale + 1e-9 * surfaces.bounds.extent().max_element() + 1e-6 * layout.cell;
        let near_fans = layout.near_fans(&surfaces, pad);
        let near = layout.near_surfaces(&surfaces, pad, &near_fans);
        let near_caps = layout.near_caps(&surfaces, pad, &near_fans, &near);
        let (labels, representatives) = layout.regions(&near);
        let centers: Vec<DVec3> = representatives.iter().map(|&cell| layout.center(cell)).collect();
        let values = decide(&centers, surfaces.cap.as_ref())?;
        let cells: Vec<u16> = parallel::install(|| {
            labels
                .par_iter()
                .zip(&near_caps)
                .map(|(&label, near_caps)| {
                    let value = values.get(label as usize).copied().filter(|_| label != NO_REGION);
                    pack(match value {
                        Some(v) if near_caps.load(Ordering::Relaxed) => CellValue::NearCaps(v),
                        Some(v) => CellValue::Decided(v),
                        None => CellValue::Undecided,
                    })
                })
                .collect()
        });
        let share =
            |of: fn(CellValue) -> bool| cells.iter().filter(|&&c| of(unpack(c))).count() as f64 / cells.len() as f64;
        let undecided = share(|c| c == CellValue::Undecided);
        let near_caps = share(|c| matches!(c, CellValue::NearCaps(_)));
        let mark = |cell: u16| match unpack(cell) {
            CellValue::Decided(v) if counts => u8::from(v >= 1),
            CellValue::Decided(v) => v as u8,
            CellValue::Undecided | CellValue::NearCaps(_) => GRID_UNDECIDED,
        };
        let marks = parallel::install(|| {
            cells
                .par_chunks(4)
                .map(|four| four.iter().enumerate().fold(0u8, |byte, (k, &cell)| byte | mark(cell) << (2 * k)))
                .collect()
        });
        Ok(InsideGrid {
            min: layout.min,
            inverse_cell: 1.0 / layout.cell,
            dims: layout.dims,
            cells,
            marks,
            counts,
            cap: surfaces.cap,
            undecided,
            near_caps,
            regions: centers.len(),
            build_seconds: started.elapsed().as_secs_f64(),
        })
    }
}

/// The caps a grid of `placements` for `contains` (by winding number, or parity) is built with
/// (`Some(None)`: none), or None where no grid answers: a sphere set, more than
/// `GRID_MAX_TRIANGLES` triangles, or an open surface (by winding number, one instance whose holes
/// caps close is answered too).
pub fn grid_caps(placements: &[Placement], winding: bool) -> Option<Option<CapGeometry>> {
    if placements.iter().any(|p| p.triangles.is_spheres()) {
        return None;
    }
    if placements.iter().map(|p| p.triangles.faces.len()).sum::<usize>() > GRID_MAX_TRIANGLES {
        return None;
    }
    if winding {
        if let Some(cap) = super::winding_cap::cap_geometry(placements) {
            return Some(Some(cap));
        }
    }
    placements.iter().all(|p| p.triangles.is_closed()).then_some(None)
}

/// What a cell says of its points.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CellValue {
    /// Near a surface (or in too small a region, or beyond the grid): their own test decides.
    Undecided,
    /// The region's value, every point's: the answer, or where the grid counts, the count of
    /// crossings of the mesh and its caps (inside from 1 up).
    Decided(i32),
    /// The region's count of crossings, to which each point adds the caps' winding number about it.
    NearCaps(i32),
}

/// A packed undecided cell.
const UNDECIDED_CELL: u16 = u16::MAX;
/// The bit of a packed cell near the caps.
const NEAR_CAPS_BIT: u16 = 1 << 12;
/// Counts from -2048 to 2047 are packed (offset by 2048); beyond, the region is undecided.
const COUNT_OFFSET: i32 = 2048;

fn pack(value: CellValue) -> u16 {
    let packed = |v: i32, bit: u16| {
        u16::try_from(v + COUNT_OFFSET).ok().filter(|&p| p < NEAR_CAPS_BIT).map_or(UNDECIDED_CELL, |p| p | bit)
    };
    match value {
        CellValue::Undecided => UNDECIDED_CELL,
        CellValue::Decided(v) => packed(v, 0),
        CellValue::NearCaps(v) => packed(v, NEAR_CAPS_BIT),
    }
}

#[inline]
fn unpack(cell: u16) -> CellValue {
    if cell == UNDECIDED_CELL {
        return CellValue::Undecided;
    }
    let v = i32::from(cell & (NEAR_CAPS_BIT - 1)) - COUNT_OFFSET;
    if cell & NEAR_CAPS_BIT != 0 {
        CellValue::NearCaps(v)
    } else {
        CellValue::Decided(v)
    }
}

/// The marks `CellLayout::near_caps` reads and clears.
#[derive(Clone, Copy)]
struct CapMarks<'a> {
    /// Cells the caps' winding number may reach the limit in (cleared as bounds show otherwise).
    near_caps: &'a [AtomicBool],
    /// Cells near a fan (where the caps' winding number jumps).
    near_fans: &'a [AtomicBool],
    /// Cells near any surface (the mesh's or a fan): undecided whatever the caps add.
    near_surfaces: &'a [AtomicBool],
}

/// Cells a side of the boxes in which `CellLayout::near_caps` first bounds the caps' winding
/// number (a power of two: halved down to `SMALLEST_CAP_BOX`).
const CAP_BOX: usize = 8;

/// The smallest boxes bounded: a bound costs about what the caps' winding number of a point
/// does (an arctangent an edge), and a grid's cell holds about half a point of a million
/// spread over the scene, so that bounding single cells costs a first query more than it saves
/// (the bunny: boxes of 2 leave 1.2% of its cells near the caps, single cells 0.6%, for 60 and
/// 160 ms of a build of 100 ms on 2 cores).
const SMALLEST_CAP_BOX: usize = 2;

/// A cell's region label where it belongs to none (near a surface, or in too small a region).
const NO_REGION: u32 = u32::MAX;

/// Cubic cells over a box: the bounds grown by one cell on every side.
struct CellLayout {
    min: DVec3,
    cell: f64,
    dims: [usize; 3],
}

impl CellLayout {
    fn new(bounds: Aabb) -> CellLayout {
        let extent = bounds.extent();
        let largest = extent.max_element().max(f64::MIN_POSITIVE);
        // Flat bounds (a closed mesh of no volume) still get cells a 512th of their size.
        let volume = extent.max(DVec3::splat(largest / 512.0));
        let cell = (volume.x * volume.y * volume.z / GRID_CELLS as f64).cbrt().max(largest / 512.0);
        let dims = extent.to_array().map(|e| ((e / cell).ceil() as usize).max(1) + 2);
        CellLayout { min: bounds.min - DVec3::splat(cell), cell, dims }
    }

    fn count(&self) -> usize {
        self.dims.iter().product()
    }

    fn index(&self, [x, y, z]: [usize; 3]) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    fn coords(&self, index: usize) -> [usize; 3] {
        let [nx, ny, _] = self.dims;
        [index % nx, (index / nx) % ny, index / (nx * ny)]
    }

    fn center(&self, index: usize) -> DVec3 {
        let [x, y, z] = self.coords(index);
        self.min + (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * self.cell
    }

    /// The cells (inclusive range per axis) that the box `b` overlaps, clamped to the grid.
    fn span(&self, b: &Aabb) -> [std::ops::RangeInclusive<usize>; 3] {
        let lo = ((b.min - self.min) / self.cell).floor();
        let hi = ((b.max - self.min) / self.cell).floor();
        std::array::from_fn(|axis| {
            let last = self.dims[axis] as f64 - 1.0;
            (lo[axis].clamp(0.0, last) as usize)..=(hi[axis].clamp(0.0, last) as usize)
        })
    }

    /// Which cells lie within `pad` of a triangle of some placement, or of a fan over a hole
    /// (`near_fans`: the fans part regions as the mesh does).
    fn near_surfaces(&self, surfaces: &GridSurfaces, pad: f64, near_fans: &[AtomicBool]) -> Vec<AtomicBool> {
        let near: Vec<AtomicBool> = near_fans.iter().map(|n| AtomicBool::new(n.load(Ordering::Relaxed))).collect();
        for placement in surfaces.placements {
            let set = &placement.triangles;
            parallel::install(|| {
                set.faces.par_iter().with_min_len(1024).for_each(|face| {
                    let [a, b, c] = face.map(|i| placement.to_scene.point(set.vertices[i as usize]));
                    self.mark_triangle(&near, [a, b, c], pad);
                })
            });
        }
        near
    }

    /// Which cells lie within `pad` of a fan over one of the caps' holes.
    fn near_fans(&self, surfaces: &GridSurfaces, pad: f64) -> Vec<AtomicBool> {
        let near: Vec<AtomicBool> = (0..self.count()).map(|_| AtomicBool::new(false)).collect();
        if let Some(cap) = &surfaces.cap {
            parallel::install(|| {
                cap.holes.par_iter().for_each(|hole| {
                    let apex = DVec3::from_array(hole.apex_scene);
                    for edge in &cap.edges[hole.first as usize..(hole.first + hole.count) as usize] {
                        let [a, b] = [edge.a_scene, edge.b_scene].map(DVec3::from_array);
                        self.mark_triangle(&near, [apex, a, b], pad);
                    }
                })
            });
        }
        near
    }

    /// Which cells lie near enough a cap's hole for the caps' winding number about a point of
    /// them to reach `CAP_WINDING_LIMIT`: their points add it to their region's count. First the
    /// cells within each hole's share of the limit by its area alone (a ball about its apex),
    /// then of those, boxes of cells where a closer bound (`CapGeometry::winding_stays_within`)
    /// keeps the caps' winding number below the limit: about a hole's fan the area's bound
    /// reaches far (the bunny's holes: 6.9% of its cells), where the winding number of a point
    /// off the fan's face is small.
    fn near_caps(
        &self,
        surfaces: &GridSurfaces,
        pad: f64,
        near_fans: &[AtomicBool],
        near_surfaces: &[AtomicBool],
    ) -> Vec<AtomicBool> {
        let near_caps: Vec<AtomicBool> = (0..self.count()).map(|_| AtomicBool::new(false)).collect();
        let Some(cap) = &surfaces.cap else { return near_caps };
        let holes = &cap.holes[..];
        let total_area: f64 = holes.iter().map(|h| h.area_scene).sum();
        for hole in holes.iter().filter(|hole| hole.area_scene > 0.0) {
            // A hole's winding number about a point `gap` beyond its radius is at most
            // area / (4π gap²) (`host_winding::fan_winding_bound`). Each hole's share of the
            // limit is its share of the holes' area: past `reach`, the sum stays below the limit.
            let share = CAP_WINDING_LIMIT * hole.area_scene / total_area;
            let reach = hole.radius_scene + (hole.area_scene / (4.0 * PI * share)).sqrt() + pad;
            let apex = DVec3::from_array(hole.apex_scene);
            let ball = Aabb { min: apex - DVec3::splat(reach), max: apex + DVec3::splat(reach) };
            let [xs, ys, zs] = self.span(&ball);
            for z in zs {
                for y in ys.clone() {
                    for x in xs.clone() {
                        let center = self.center(self.index([x, y, z]));
                        let cell = Aabb { min: center - 0.5 * self.cell, max: center + 0.5 * self.cell };
                        if cell.distance_to(apex) <= reach {
                            near_caps[self.index([x, y, z])].store(true, Ordering::Relaxed);
                        }
                    }
                }
            }
        }
        let [bx, by, bz] = self.dims.map(|n| n.div_ceil(CAP_BOX));
        parallel::install(|| {
            (0..bx * by * bz).into_par_iter().for_each(|b| {
                let corner = [b % bx, (b / bx) % by, b / (bx * by)].map(|k| k * CAP_BOX);
                let marks = CapMarks { near_caps: &near_caps, near_fans, near_surfaces };
                self.clear_far_from_caps(cap, &marks, (corner, CAP_BOX), pad);
            })
        });
        near_caps
    }

    /// Clears the `near_caps` marks of the cells of the box of `size` cells a side from `corner`
    /// (clamped to the grid) where the caps' winding number stays below the limit, the box
    /// whole where its bound says so (and no fan passes through it), else its eight halves in
    /// turn, down to `SMALLEST_CAP_BOX`; only where a cell would gain (one away from surfaces).
    fn clear_far_from_caps(&self, cap: &CapGeometry, marks: &CapMarks, (corner, size): ([usize; 3], usize), pad: f64) {
        let CapMarks { near_caps, near_fans, near_surfaces } = *marks;
        let end: [usize; 3] = std::array::from_fn(|k| (corner[k] + size).min(self.dims[k]));
        if (0..3).any(|k| corner[k] >= end[k]) {
            return;
        }
        let cells = || {
            (corner[2]..end[2]).flat_map(move |z| {
                (corner[1]..end[1]).flat_map(move |y| (corner[0]..end[0]).map(move |x| self.index([x, y, z])))
            })
        };
        if !cells().any(|i| near_caps[i].load(Ordering::Relaxed) && !near_surfaces[i].load(Ordering::Relaxed)) {
            return;
        }
        if !cells().any(|i| near_fans[i].load(Ordering::Relaxed)) {
            let lo = self.min + DVec3::new(corner[0] as f64, corner[1] as f64, corner[2] as f64) * self.cell;
            let hi = self.min + DVec3::new(end[0] as f64, end[1] as f64, end[2] as f64) * self.cell;
            // Past the box by the pad: its points' rounding into their cells. Every such point
            // lies in the box grown by the pad, convex and met by no fan (none comes within the
            // pad of its cells), so the segment from the centre to it meets no fan either.
            let reach = 0.5 * (hi - lo).length() + pad;
            if cap.winding_stays_within(0.5 * (lo + hi), reach, CAP_WINDING_LIMIT) {
                cells().for_each(|i| near_caps[i].store(false, Ordering::Relaxed));
                return;
            }
        }
        if size <= SMALLEST_CAP_BOX {
            return;
        }
        let half = size / 2;
        for octant in 0..8 {
            let at = std::array::from_fn(|k| corner[k] + if octant >> k & 1 == 1 { half } else { 0 });
            self.clear_far_from_caps(cap, marks, (at, half), pad);
        }
    }

    /// Marks the cells within `pad` of the triangle (a, b, c): those its padded box overlaps,
    /// less those its plane passes farther from (a large triangle's box holds many cells it never
    /// comes near). Conservative: a cell is marked wherever the triangle may come within `pad`.
    fn mark_triangle(&self, near: &[AtomicBool], [a, b, c]: [DVec3; 3], pad: f64) {
        let [xs, ys, zs] = self.span(&Aabb::of_points([a, b, c]).padded(pad));
        let cells = xs.clone().count() * ys.clone().count() * zs.clone().count();
        let normal = (b - a).cross(c - a);
        let length = normal.length();
        // Small triangles (and degenerate ones, whose normal says nothing) mark their whole box.
        let plane_test = cells > 8 && length > 0.0 && length.is_finite();
        let unit = if plane_test { normal / length } else { DVec3::ZERO };
        let half = 0.5 * self.cell;
        // The plane's reach over a cell: its half-diagonal projected on the normal, the pad, and
        // the corners' own distances from the computed plane (a sliver's normal rounds far off:
        // the triangle still lies within that slab about `a`, whatever the normal's error).
        let slab = unit.dot(b - a).abs().max(unit.dot(c - a).abs());
        let reach = half * unit.abs().element_sum() + pad + slab + 1e-12 * (a.abs().max_element() + self.cell);
        for z in zs {
            for y in ys.clone() {
                for x in xs.clone() {
                    let index = self.index([x, y, z]);
                    if plane_test && unit.dot(self.center(index) - a).abs() > reach {
                        continue;
                    }
                    near[index].store(true, Ordering::Relaxed);
                }
            }
        }
    }

    /// Labels the regions of cells away from surfaces (face-connected), each region's cells with
    /// its number (`NO_REGION` for the rest and for regions of fewer than `SMALLEST_REGION` cells);
    /// and one cell of each region.
    fn regions(&self, near: &[AtomicBool]) -> (Vec<u32>, Vec<usize>) {
        let mut labels: Vec<u32> =
            near.iter().map(|n| if n.load(Ordering::Relaxed) { NO_REGION } else { UNSEEN }).collect();
        let mut representatives = Vec::new();
        let mut stack = Vec::new();
        let mut members = Vec::new();
        let [nx, ny, nz] = self.dims;
        for start in 0..labels.len() {
            if labels[start] != UNSEEN {
                continue;
            }
            let label = representatives.len() as u32;
            labels[start] = label;
            stack.push(start);
            members.clear();
            while let Some(i) = stack.pop() {
                members.push(i);
                let [x, y, z] = self.coords(i);
                let mut visit = |j: usize| {
                    if labels[j] == UNSEEN {
                        labels[j] = label;
                        stack.push(j);
                    }
                };
                if x > 0 {
                    visit(i - 1);
                }
                if x + 1 < nx {
                    visit(i + 1);
                }
                if y > 0 {
                    visit(i - nx);
                }
                if y + 1 < ny {
                    visit(i + nx);
                }
                if z > 0 {
                    visit(i - nx * ny);
                }
                if z + 1 < nz {
                    visit(i + nx * ny);
                }
            }
            if members.len() < SMALLEST_REGION {
                for &i in &members {
                    labels[i] = NO_REGION;
                }
            } else {
                representatives.push(start);
            }
        }
        (labels, representatives)
    }
}

/// A cell away from surfaces whose region is not labelled yet.
const UNSEEN: u32 = u32::MAX - 1;

#[cfg(test)]
mod tests {
    use super::*;

    /// The answer of the cell holding `p` (the scene's frame), a point at a time with usize
    /// indices: the pass before `mark_rows`, its oracle.
    fn mark(grid: &InsideGrid, p: DVec3) -> u8 {
        let q = (p - grid.min) * grid.inverse_cell;
        let [nx, ny, nz] = grid.dims;
        let inside = |v: f64, n: usize| v >= 0.0 && v < n as f64;
        if !(inside(q.x, nx) && inside(q.y, ny) && inside(q.z, nz)) {
            return GRID_OUTSIDE;
        }
        let cell = (q.z as usize * ny + q.y as usize) * nx + q.x as usize;
        (grid.marks[cell >> 2] >> (2 * (cell & 3))) & 3
    }

    /// A grid of `dims` cells of size 0.25 from `min`, each cell's mark `(i * 7) % 3`.
    fn striped_grid(min: DVec3, dims: [usize; 3]) -> InsideGrid {
        let cells = dims.iter().product::<usize>();
        let mut marks = vec![0u8; cells.div_ceil(4)];
        for i in 0..cells {
            marks[i >> 2] |= (((i * 7) % 3) as u8) << (2 * (i & 3));
        }
        InsideGrid {
            min,
            inverse_cell: 4.0,
            dims,
            cells: Vec::new(),
            marks,
            counts: false,
            cap: None,
            undecided: 0.0,
            near_caps: 0.0,
            regions: 0,
            build_seconds: 0.0,
        }
    }

    #[test]
    fn the_marks_in_batches_are_each_points_own_mark() {
        for center in [DVec3::new(0.125, -3.0, 1e3), DVec3::new(0.1, 1e5 + 0.3, -7.7)] {
            marks_in_batches_match(center);
        }
    }

    /// `mark_rows` against `mark` about a grid whose frame is `center` away: edge values, points
    /// on and beside every cell boundary (where the order of the subtractions rounds), random ones.
    fn marks_in_batches_match(center: DVec3) {
        let (min, dims) = (DVec3::new(-1.0, -0.5, 2.0), [9, 5, 13]);
        let grid = striped_grid(min, dims);
        let top = min + DVec3::new(9.0, 5.0, 13.0) / 4.0;
        let mut points: Vec<[f64; 3]> = vec![
            (min + center).to_array(),
            (top + center).to_array(), // q == n on every axis: beyond the grid
            [(top.x + center.x).next_down(), min.y + center.y, min.z + center.z],
            [f64::NAN, 0.0, 0.0],
            [f64::INFINITY, 0.0, 0.0],
            [0.0, f64::NEG_INFINITY, 0.0],
            [-0.0, -0.0, -0.0],
            [1e300, -1e300, 3e38],
            [(min.x + center.x).next_down(), min.y + center.y, min.z + center.z],
        ];
        let mut seed = 12345u64;
        let mut random = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for k in 0..=dims[0] {
            let x = min.x + k as f64 * 0.25 + center.x;
            for x in [x.next_down(), x, x.next_up()] {
                points.push([x, min.y + 0.3 + center.y, min.z + 1.1 + center.z]);
            }
        }
        let edges = points.len();
        // 700 points about the grid (past the first batch of 256, a last one partial).
        for _ in 0..700 {
            let p = min + center + DVec3::new(random() * 2.8 - 0.2, random() * 1.7 - 0.2, random() * 3.7 - 0.2);
            points.push(p.to_array());
        }
        let flat: Vec<f64> = points.iter().flatten().copied().collect();
        let want: Vec<u8> = points.iter().map(|p| mark(&grid, DVec3::from_array(*p) - center)).collect();
        let mut got = vec![9u8; points.len()];
        assert!(!grid.mark_rows(&flat, center, &mut got));
        assert_eq!(got, want);
        assert!(want.contains(&GRID_UNDECIDED) && want.contains(&GRID_INSIDE));
        // f32 rows, finite: the same marks as their f64 values, and finite.
        let narrow: Vec<f32> = flat[3 * edges..].iter().map(|&v| v as f32).collect();
        let want: Vec<u8> = narrow
            .chunks_exact(3)
            .map(|p| mark(&grid, DVec3::new(p[0].into(), p[1].into(), p[2].into()) - center))
            .collect();
        let mut got = vec![9u8; want.len()];
        assert!(grid.mark_rows(&narrow, center, &mut got));
        assert_eq!(got, want);
    }
}

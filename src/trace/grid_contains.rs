//! `contains` at the exact tier through the scene's inside grid (`scene::InsideGrid`): one lookup
//! answers a point whose cell lies away from every surface; a point near a surface (an undecided
//! cell) is answered, on the engines of the host's cores, by a short exact ray to the next decided
//! cell in a scene of one instance, and otherwise (and on a GPU) by the engine's exact test. The
//! grid is built by a large query on a scene it suits (`GridUse`), its regions' values from the
//! host's exact test, and kept until the scene's next update.

use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

use super::host_tiers::{self, PARITY_DIRECTION, WHOLE_RAY};
use super::host_winding::{caps_winding, fan_winding_bound, signed_crossings_with_caps, winding_ray};
use super::request::Crossings;
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::morton;
use crate::geometry::parallel::{self, try_vec};
use crate::geometry::precision::{Cull, Ray64};
use crate::geometry::reference::Filter;
use crate::scene::{
    grid_caps, CapGeometry, CellValue, GridSurfaces, InsideGrid, Scene, CAP_WINDING_LIMIT, GRID_UNDECIDED,
};

/// A query of fewer points neither builds a grid (its build costs tens of milliseconds) nor
/// waits for one; it uses one a larger query built.
pub const GRID_MIN_POINTS: usize = 1 << 15;

/// How an engine answers `contains` at the exact tier through a scene's grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridUse {
    /// The grid is built by the scene's `build_at`-th query of at least `GRID_MIN_POINTS` points
    /// (by winding number, or by parity) that finds none.
    pub build_at: u32,
    /// The points of undecided cells take the host's short rays to the next decided cell (in a
    /// scene of one instance); else the engine's own exact test answers them.
    pub segments: bool,
    /// One build at a time: a query that finds another's build under way goes on without the
    /// grid rather than building one beside it (a GPU answers alone about as fast as it would
    /// wait). Else each builds its own and the first kept wins (the host's cores answer without
    /// the grid far more slowly).
    pub one_build: bool,
}

impl GridUse {
    /// For an engine whose queries run on the host's cores (`on_host`) or on a GPU: on the host,
    /// the first large query builds the grid and undecided points take short rays there. On a
    /// GPU, the grid answers most points at a lookup each and the GPU's exact test the rest (1M
    /// points on an H200: 1.5–3.7× faster than the GPU alone); its build (50–80 ms on 16 cores,
    /// several GPU queries' time) waits for a scene's second large query, so that a single query
    /// does not pay it. `VKRAY_CONTAINS_GRID`: "off", no grid is built or used (for measuring
    /// what it saves); "gpu", every engine uses it as a GPU does (for tests on any engine);
    /// "engine", as "gpu" but built by the first large query.
    pub fn of_engine(on_host: bool) -> Option<GridUse> {
        let gpu = |build_at| Some(GridUse { build_at, segments: false, one_build: true });
        match std::env::var("VKRAY_CONTAINS_GRID").as_deref() {
            Ok("off") => None,
            Ok("engine") => gpu(1),
            Ok("gpu") => gpu(2),
            _ if on_host => Some(GridUse { build_at: 1, segments: true, one_build: false }),
            _ => gpu(2),
        }
    }
}

/// The scene's grid for `contains` by winding number (or parity): the one kept, else one built
/// now for a query of `points` points where the scene suits one (see `grid_caps`) and `grid_use`
/// asks for it at this query; else None.
pub fn inside_grid(
    scene: &Scene,
    winding: bool,
    points: usize,
    grid_use: GridUse,
    interrupt: &dyn Interrupt,
) -> Result<Option<Arc<InsideGrid>>> {
    if let Some(grid) = scene.inside_grid(winding) {
        return Ok(Some(grid));
    }
    if points < GRID_MIN_POINTS || scene.count_gridless_query(winding) < grid_use.build_at {
        return Ok(None);
    }
    let build = scene.start_grid_build(winding);
    if grid_use.one_build && build.is_none() {
        return Ok(None);
    }
    let _in_use = scene.hold_meshes();
    scene.check_current()?;
    let Some(cap) = grid_caps(&scene.placements, winding) else { return Ok(None) };
    let bounds = scene.bounds();
    let world_scale = scene.center.abs().max_element() + bounds.min.abs().max(bounds.max.abs()).max_element();
    // Bounds of no size (every vertex at one point) or near f64's least have no cells to speak of.
    let extent = bounds.extent().max_element();
    if extent.is_nan() || extent <= 1e-200 {
        return Ok(None);
    }
    // With caps (by winding number, one instance), each region keeps its count of crossings of
    // the mesh and its caps, which short rays from points near the surface add to.
    let counts = cap.is_some();
    let surfaces = GridSurfaces { placements: &scene.placements, cap, bounds, world_scale };
    // Built outside the scene's lock (its regions' values are exact tests on every core), kept
    // under it: a query built beside it keeps the first.
    let grid = InsideGrid::build(surfaces, counts, |centers, cap| match cap {
        Some(cap) => Ok(region_counts(scene, cap, centers)),
        None => {
            let world: Vec<f64> = centers.iter().flat_map(|&c| (c + scene.center).to_array()).collect();
            let mut answers = vec![0u8; centers.len()];
            host_tiers::contains(scene, Vec3s::F64(&world), winding, &mut answers, interrupt)?;
            Ok(answers.into_iter().map(i32::from).collect())
        }
    })?;
    Ok(Some(scene.keep_inside_grid(winding, grid)))
}

/// Points a block of `mark_points`' pass.
const MARK_BLOCK: usize = 1 << 14;

/// Each point's mark in `out` (its cell's answer, or `GRID_UNDECIDED`), in one pass on all cores
/// that also checks that every point is finite (`check_points`' error where one is not) and
/// gathers the points of undecided cells, in order. A point far beyond the scene (even beyond
/// f32's range) lies beyond the grid: outside. On an H200's 16 cores, 1M points: separate
/// passes took 0.4 ms (the check), 0.45 (far points moved in), 1.6 (the marks) and 0.5 (the
/// undecided points); this pass 2.0 ms a point at a time, 1.0 by `InsideGrid::mark_rows`' batches.
fn mark_points(grid: &InsideGrid, points: Vec3s, center: DVec3, out: &mut [u8]) -> Result<Vec<usize>> {
    let blocks: Vec<(bool, Vec<usize>)> = parallel::install(|| {
        out.par_chunks_mut(MARK_BLOCK)
            .enumerate()
            .map(|(b, marks)| {
                let rows = b * MARK_BLOCK..b * MARK_BLOCK + marks.len();
                let finite = match points {
                    Vec3s::F32(v) => grid.mark_rows(&v[3 * rows.start..3 * rows.end], center, marks),
                    Vec3s::F64(v) => grid.mark_rows(&v[3 * rows.start..3 * rows.end], center, marks),
                };
                let undecided = marks.iter().enumerate().filter(|(_, &m)| m == GRID_UNDECIDED);
                (finite, undecided.map(|(k, _)| rows.start + k).collect())
            })
            .collect()
    });
    if !blocks.iter().all(|(finite, _)| *finite) {
        crate::geometry::arrays::check_points("points", points)?;
    }
    let mut undecided = Vec::new();
    undecided
        .try_reserve_exact(blocks.iter().map(|(_, u)| u.len()).sum())
        .map_err(|_| crate::error::Error::OutOfMemory("the points near a surface do not fit in host memory".into()))?;
    for (_, block) in blocks {
        undecided.extend_from_slice(&block);
    }
    Ok(undecided)
}

/// `contains` of `points` (world frame) into `out` through `grid`: each point's cell answers;
/// the points of undecided cells take short rays (`parity_by_segments`, `winding_by_segments`) in a
/// scene of one instance where `segments` (the host's cores run the engine), else `exact`
/// answers them (gathered, in the points' own type).
#[allow(clippy::too_many_arguments)]
pub fn contains_by_grid(
    scene: &Scene,
    grid: &InsideGrid,
    points: Vec3s,
    winding: bool,
    segments: bool,
    out: &mut [u8],
    interrupt: &dyn Interrupt,
    exact: impl FnOnce(Vec3s, &mut [u8]) -> Result<()>,
) -> Result<()> {
    let undecided = mark_points(grid, points, scene.center, out)?;
    if undecided.is_empty() {
        return Ok(());
    }
    let undecided = in_curve_order(scene, points, undecided)?;
    let mut answers = try_vec(undecided.len(), 0u8, "the answers of points near a surface")?;
    if let (Some(cap), true) = (grid.cap(), segments) {
        let gathered = gather_f64(points, &undecided)?;
        winding_by_segments(scene, grid, cap, Vec3s::F64(&gathered), &mut answers, interrupt)?;
    } else if segments && !winding && scene.placements.len() == 1 {
        parity_by_segments(scene, grid, points, &undecided, &mut answers, interrupt)?;
    } else {
        match points {
            Vec3s::F32(v) => exact(Vec3s::F32(&gather(v, &undecided)?), &mut answers)?,
            Vec3s::F64(v) => exact(Vec3s::F64(&gather(v, &undecided)?), &mut answers)?,
        }
    }
    for (&i, &answer) in undecided.iter().zip(&answers) {
        out[i] = answer;
    }
    Ok(())
}

/// `undecided` (rows of `points`) sorted along a Morton curve over the scene: the rays and
/// searches of neighbouring points then cross the same nodes while they are in cache (the
/// caller's order is any; 200,000 points uniform about the bunny: `contains` 20 → 17 ms on two
/// cores).
fn in_curve_order(scene: &Scene, points: Vec3s, undecided: Vec<usize>) -> Result<Vec<usize>> {
    let gathered = gather_f64(points, &undecided)?;
    let bounds = scene.bounds();
    let order = morton::point_order(Vec3s::F64(&gathered), bounds.min + scene.center, bounds.max + scene.center);
    Ok(order.as_slice().iter().map(|&k| undecided[k as usize]).collect())
}

/// The rows `rows` of the 3-column `values`, in order.
fn gather<T: Copy + Default + Send + Sync>(values: &[T], rows: &[usize]) -> Result<Vec<T>> {
    let mut gathered = try_vec(3 * rows.len(), T::default(), "the points near a surface")?;
    parallel::install(|| {
        gathered.par_chunks_exact_mut(3).zip(rows).with_min_len(4096).for_each(|(dst, &i)| {
            dst.copy_from_slice(&values[3 * i..3 * i + 3]);
        })
    });
    Ok(gathered)
}

/// How many undecided cells a point's segment crosses at most before it takes the whole ray.
const MOST_SEGMENT_CELLS: usize = 64;

/// `contains` by parity of the `undecided` points of a scene of one closed instance, into
/// `answers`: each point's ray (the parity direction) runs only to the first decided cell along
/// it, whose answer the parity of the crossings on the way flips (each crossing counted once by
/// the exact test; the cell's point lies far from any surface). Points on a surface are inside,
/// as `host_tiers::contains` has them; a ray that finds no decided cell soon runs to infinity,
/// where every point is outside.
fn parity_by_segments(
    scene: &Scene,
    grid: &InsideGrid,
    points: Vec3s,
    undecided: &[usize],
    answers: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    let direction = PARITY_DIRECTION;
    host_tiers::in_blocks(answers.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            answers[range].par_iter_mut().enumerate().with_min_len(64).for_each_init(Vec::new, |found, (k, inside)| {
                let p = DVec3::from_array(points.row_f64(undecided[start + k])) - scene.center;
                // In the reference tier's order: beyond the scene, then on a surface.
                *inside = if host_tiers::beyond_the_scene(scene, p) {
                    0
                } else if tracer.on_surface(p, host_tiers::ON_SURFACE_ULPS) {
                    1
                } else {
                    let (tmax, beyond) =
                        grid.first_decided_along(p, direction, MOST_SEGMENT_CELLS).unwrap_or(WHOLE_RAY);
                    found.clear();
                    let ray = Ray64 { origin: p, direction, tmin: 0.0, tmax };
                    tracer.trace_every(&ray, 0xFF, Filter::sides(Cull::None), found);
                    (beyond as u8) ^ (found.len() as u8 & 1)
                };
            })
        });
    })
}

/// The signed count of crossings of the scene's one instance and its caps of each point's ray
/// (the scene's frame; points away from every surface and cap): the integer part of its winding
/// number, which the caps' small part about such a point leaves whole.
fn region_counts(scene: &Scene, cap: &CapGeometry, centers: &[DVec3]) -> Vec<i32> {
    let tracer = scene.reference_tracer();
    let (placement, band) = (&scene.placements[0], cap.band());
    parallel::install(|| {
        centers
            .par_iter()
            .map(|&p| winding_ray(&tracer, placement, cap, band, p, (PARITY_DIRECTION, WHOLE_RAY)).0.sum())
            .collect()
    })
}

/// `contains` by winding number of the undecided `points` (world frame) of a scene of one
/// instance closed by `cap`, into `answers`: each point's ray runs only to the first decided
/// cell along it, whose count of crossings those on the way add to; the caps' winding number about
/// the point completes its own, and the points within the band about 1/2 take the whole winding
/// number (as `host_tiers::contains` decides them).
fn winding_by_segments(
    scene: &Scene,
    grid: &InsideGrid,
    cap: &CapGeometry,
    points: Vec3s,
    answers: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    let (placement, band) = (&scene.placements[0], cap.band());
    host_tiers::in_blocks(answers.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            answers[range].par_iter_mut().enumerate().with_min_len(64).for_each(|(k, inside)| {
                let p = DVec3::from_array(points.row_f64(start + k)) - scene.center;
                *inside = match grid.cell(p) {
                    // In the reference tier's order: beyond the scene, then on a surface.
                    _ if host_tiers::beyond_the_scene(scene, p) => 0,
                    // Away from every surface: the region's count.
                    CellValue::NearCaps(count) => inside_with_caps(cap, band, p, count),
                    _ if tracer.on_surface(p, host_tiers::ON_SURFACE_ULPS) => 1,
                    _ => {
                        let end =
                            grid.first_decided_along(p, PARITY_DIRECTION, MOST_SEGMENT_CELLS).unwrap_or(WHOLE_RAY);
                        let count = signed_crossings_with_caps(&tracer, placement, cap, p, (PARITY_DIRECTION, end));
                        inside_with_caps(cap, band, p, count)
                    }
                };
            })
        });
    })?;
    host_tiers::decide_on_the_cpu(scene, points, answers, interrupt)
}

/// Whether a point `p` (scene frame, off the surface) whose ray's count of crossings of the mesh
/// and its caps is `count` lies inside (1), outside (0), or `UNSURE` (within `band` of 1/2):
/// `count` plus the caps' winding number about `p`, which the holes' bounds about `p` often show
/// too small to matter (below `CAP_WINDING_LIMIT`, the count alone decides) before it is summed.
fn inside_with_caps(cap: &CapGeometry, band: f64, p: DVec3, count: i32) -> u8 {
    if cap.holes.iter().map(|hole| fan_winding_bound(p, hole)).sum::<f64>() < CAP_WINDING_LIMIT {
        u8::from(count >= 1)
    } else {
        host_tiers::mark_by_crossings(Crossings(count << 1), caps_winding(cap, band, p, count), band)
    }
}

/// The rows `rows` of `points`, in f64.
fn gather_f64(points: Vec3s, rows: &[usize]) -> Result<Vec<f64>> {
    let mut gathered = try_vec(3 * rows.len(), 0.0, "the points near a surface")?;
    parallel::install(|| {
        gathered.par_chunks_exact_mut(3).zip(rows).with_min_len(4096).for_each(|(dst, &i)| {
            dst.copy_from_slice(&points.row_f64(i));
        })
    });
    Ok(gathered)
}

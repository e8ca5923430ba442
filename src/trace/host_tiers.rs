//! The host's part of the f64 precision tiers: refining f32 hits against their triangles
//! (`"refined"`) and tracing on the CPU (`"reference"`), each writing the caller's hit fields.

use glam::DVec3;
use rayon::prelude::*;

use super::hit_fields::{position_bytes_per_ray, Field, HitSink};
use super::host_winding::winding_ray;
use super::pacer::in_paced_blocks;
use super::request::Crossings;
use crate::error::{Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::morton;
use crate::geometry::parallel;
use crate::geometry::parallel::{try_vec, try_zeroed};
use crate::geometry::precision::{plane_hit, sphere_normal, world_normal, Cull, Ray64};
use crate::geometry::rays::Rays;
use crate::geometry::reference::{ClosestHit, Filter, ReferenceHit};
use crate::scene::{cap_geometry, CapGeometry, MeshKind, Scene};

fn put_f64s(dst: &mut [u8], values: &[f64]) {
    for (d, v) in dst.chunks_exact_mut(8).zip(values) {
        d.copy_from_slice(&v.to_ne_bytes());
    }
}

fn put_f32s(dst: &mut [u8], values: &[f32]) {
    for (d, v) in dst.chunks_exact_mut(4).zip(values) {
        d.copy_from_slice(&v.to_ne_bytes());
    }
}

fn int_at(bytes: &[u8], i: usize) -> i32 {
    i32::from_ne_bytes(bytes[4 * i..4 * i + 4].try_into().expect("4 bytes"))
}

/// Items (rays, points) the host tiers process between two checks for an interrupt: the first
/// block and the most in one; the others are paced to a fraction of a second (`ChunkPacer`: a ray
/// through hundreds of triangles takes a thousand times one that misses).
const HOST_BLOCK: (usize, usize) = (4096, 1 << 20);

/// Runs `work` over `0..n` in paced blocks, asking `interrupt` before each.
pub(super) fn in_blocks(
    n: usize,
    interrupt: &dyn Interrupt,
    mut work: impl FnMut(std::ops::Range<usize>),
) -> Result<()> {
    in_paced_blocks(n, HOST_BLOCK, interrupt, |range| {
        work(range);
        Ok(())
    })
}

/// Re-intersects each hit the GPU found (the sink's `prim`, `instance`, `geometry`) with its
/// triangle in f64, in the mesh's own frame, and writes the fields the sink asks for (`t` and
/// `uv` as f64, the normal from f64 vertices). Where the f64 answer leaves the ray's interval
/// (f32 traversal accepted a triangle the ray only grazes, or one just behind an origin that
/// sits on it, as secondary rays do), that ray is traced again by the CPU tracer.
pub fn refine(scene: &Scene, rays: &Rays, filter: Filter, sink: &mut HitSink, interrupt: &dyn Interrupt) -> Result<()> {
    let n = rays.len();
    let (prim, instance, geometry) = (
        sink.field(Field::Prim).unwrap_or_default(),
        sink.field(Field::Instance).unwrap_or_default(),
        sink.field(Field::Geometry).unwrap_or_default(),
    );
    let mut hits: Vec<Option<ReferenceHit>> = try_vec(n, None, "refining hits")?;
    let mut again: Vec<bool> = try_vec(n, false, "refining hits")?;
    in_blocks(n, interrupt, |range| {
        let start = range.start;
        let (hits, again) = (&mut hits[range.clone()], &mut again[range]);
        parallel::install(|| {
            hits.par_iter_mut().zip(again).enumerate().with_min_len(1024).for_each(|(k, (hit, again))| {
                let i = start + k;
                let (p, x) = (int_at(prim, i), int_at(instance, i));
                if p < 0 {
                    return;
                }
                let placement = &scene.placements[x as usize];
                let ray = rays.ray64(i, scene.center).transformed(&placement.to_local);
                let global = placement.triangles.global(int_at(geometry, i) as usize, p as usize);
                let [a, b, c] = placement.triangles.triangle(global);
                match plane_hit(&ray, a, b, c) {
                    Some(h) if h.t >= ray.tmin && h.t <= ray.tmax => {
                        *hit = Some(ReferenceHit { t: h.t, u: h.u, v: h.v, instance: x as u32, prim: global as u32 })
                    }
                    _ => *again = true,
                }
            })
        });
    })?;
    let retrace: Vec<usize> = (0..n).filter(|&i| again[i]).collect();
    if !retrace.is_empty() {
        let tracer = scene.reference_tracer();
        in_blocks(retrace.len(), interrupt, |range| {
            for &i in &retrace[range] {
                hits[i] = tracer.trace(&rays.ray64(i, scene.center), rays.mask.get(i), filter, false);
            }
        })?;
    }
    // Sphere scenes are not refined (their f64 tiers are the reference tier's).
    write_hit_fields(scene, sink, true, |i| hits[i], |_| None);
    Ok(())
}

/// Traces every ray on the CPU in f64 and writes every field the sink asks for.
pub fn reference(
    scene: &Scene,
    rays: &Rays,
    filter: Filter,
    any: bool,
    sink: &mut HitSink,
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    let mut hits: Vec<Option<ReferenceHit>> = try_vec(rays.len(), None, "the reference tier's hits")?;
    in_blocks(rays.len(), interrupt, |range| {
        let start = range.start;
        tracer.trace_all(
            |k| (rays.ray64(start + k, scene.center), rays.mask.get(start + k)),
            filter,
            any,
            &mut hits[range],
        );
    })?;
    let spheres = scene.has_spheres();
    let point = |i: usize| {
        let hit = hits[i].filter(|_| spheres)?;
        let ray = rays.ray64(i, scene.center);
        Some(ray.origin + hit.t * ray.direction)
    };
    write_hit_fields(scene, sink, true, |i| hits[i], point);
    Ok(())
}

/// Writes `values` as f64 (`wide`) or f32.
fn put_floats(dst: &mut [u8], values: &[f64], wide: bool) {
    if wide {
        put_f64s(dst, values)
    } else {
        for (d, v) in dst.chunks_exact_mut(4).zip(values) {
            d.copy_from_slice(&(*v as f32).to_ne_bytes());
        }
    }
}

/// Rows of `write_hit_fields`' block: every field of a block's rows is written before the next
/// block's, its hits still in the cache (a pass a field over a million closest points read their
/// 48 MB of hits seven times: 13 ms of an H200 machine's 16 cores, most of the query).
const FIELD_BLOCK_ROWS: usize = 2048;

/// An output `write_hit_fields` writes: a hit field, or the hit's position.
#[derive(Clone, Copy)]
enum HitColumn {
    Field(Field),
    Position,
}

/// Writes every field the sink asks for of the hit `hit(i)` of entry i (None: a miss; its
/// `prim` counts among all parts of the mesh): `t`, `uv` and `position` as f64 where `wide`, else
/// f32; normals from the f64 vertices; (geometry, triangle in it). `point(i)`: where a sphere hit
/// lies, in the scene's frame (a sphere's normal and position are its ray's at `t`). On all cores,
/// a block of rows at a time (`FIELD_BLOCK_ROWS`); the sink's `position` is taken.
fn write_hit_fields(
    scene: &Scene,
    sink: &mut HitSink,
    wide: bool,
    hit: impl Fn(usize) -> Option<ReferenceHit> + Sync,
    point: impl Fn(usize) -> Option<DVec3> + Sync,
) {
    let mut columns: Vec<(HitColumn, usize, &mut [u8])> = Vec::new();
    let position = sink.position.take();
    for (field, out) in sink.iter_mut() {
        columns.push((HitColumn::Field(field), field.bytes_per_ray(wide), out));
    }
    if let Some(out) = position {
        columns.push((HitColumn::Position, position_bytes_per_ray(wide), out));
    }
    let Some(rows) = columns.first().map(|(_, width, out)| out.len() / width) else { return };
    // Each block's piece of every column.
    let mut blocks: Vec<Vec<(HitColumn, usize, &mut [u8])>> =
        (0..rows.div_ceil(FIELD_BLOCK_ROWS)).map(|_| Vec::with_capacity(columns.len())).collect();
    for (column, width, out) in columns {
        for (block, piece) in blocks.iter_mut().zip(out.chunks_mut(FIELD_BLOCK_ROWS * width)) {
            block.push((column, width, piece));
        }
    }
    parallel::install(|| {
        // Each row's hit made once for all its columns (a closure call and a record's copy a
        // field a row before).
        blocks.into_par_iter().enumerate().for_each_init(Vec::new, |hits, (b, pieces)| {
            let first = b * FIELD_BLOCK_ROWS;
            let Some(rows) = pieces.first().map(|(_, width, piece)| piece.len() / width) else { return };
            hits.clear();
            hits.extend((first..first + rows).map(&hit));
            for (column, width, piece) in pieces {
                for ((k, dst), hit) in piece.chunks_exact_mut(width).enumerate().zip(hits.iter()) {
                    write_hit_column(scene, column, wide, *hit, || point(first + k), dst);
                }
            }
        })
    });
}

/// One row's `column` of the hit `hit` (None: a miss) into `dst` (see `write_hit_fields`).
fn write_hit_column(
    scene: &Scene,
    column: HitColumn,
    wide: bool,
    hit: Option<ReferenceHit>,
    point: impl Fn() -> Option<DVec3>,
    dst: &mut [u8],
) {
    fn split(s: &Scene, h: &ReferenceHit) -> (usize, usize) {
        s.placements[h.instance as usize].triangles.split(h.prim as usize)
    }
    let id = |value: &dyn Fn(&ReferenceHit) -> i32| hit.as_ref().map_or(-1, value).to_ne_bytes();
    let field = match column {
        HitColumn::Position => {
            let position = hit.map_or(DVec3::NAN, |h| {
                let placement = &scene.placements[h.instance as usize];
                if placement.triangles.is_spheres() {
                    return point().unwrap_or(DVec3::NAN) + scene.center;
                }
                let [a, b, c] = placement.triangles.triangle(h.prim as usize);
                placement.to_scene.point(a + h.u * (b - a) + h.v * (c - a)) + scene.center
            });
            return put_floats(dst, &position.to_array(), wide);
        }
        HitColumn::Field(field) => field,
    };
    match field {
        Field::T => put_floats(dst, &[hit.map_or(f64::INFINITY, |h| h.t)], wide),
        Field::Uv => put_floats(dst, &hit.map_or([f64::NAN; 2], |h| [h.u, h.v]), wide),
        Field::Prim => dst.copy_from_slice(&id(&|h| split(scene, h).1 as i32)),
        Field::Instance => dst.copy_from_slice(&id(&|h| h.instance as i32)),
        Field::Custom => dst.copy_from_slice(&id(&|h| scene.placements[h.instance as usize].custom_index as i32)),
        Field::Geometry => dst.copy_from_slice(&id(&|h| split(scene, h).0 as i32)),
        Field::Normal => {
            let n = hit.map_or(DVec3::NAN, |h| {
                let placement = &scene.placements[h.instance as usize];
                if let Some(&(center, radius)) = placement.triangles.spheres.get(h.prim as usize) {
                    let local = placement.to_local.point(point().unwrap_or(DVec3::NAN));
                    return sphere_normal(&placement.to_local, center, radius, local);
                }
                let [a, b, c] = placement.triangles.triangle(h.prim as usize);
                world_normal(&placement.to_local, a, b, c)
            });
            put_f32s(dst, &n.as_vec3().to_array())
        }
    }
}

/// Every hit of every ray: ray i's are `hits[offsets[i]..offsets[i + 1]]`, in the order
/// `ReferenceTracer::trace_every` gives; `t` and barycentrics are f64 values where `wide`, else
/// f32 values (the fast tier's).
pub struct AllHits {
    pub offsets: Vec<i64>,
    pub hits: Vec<ReferenceHit>,
    pub wide: bool,
}

/// Hits the reference tier keeps while it counts them (256 MB of records): a query with no more
/// is traced once; one with more is counted first (nothing stored), refused where it cannot fit
/// in host memory, and traced again into its exact allocation, as the GPU tiers count first.
const KEPT_WHILE_COUNTING: usize = 1 << 23;

/// Traces every ray for all of its hits (the nearest `max_hits` of each) on all cores.
/// `host_bytes_per_hit`: what the caller will need per hit besides the records, for refusing
/// (MemoryError, naming the size) an answer that cannot fit before it is stored.
pub fn all_hits(
    scene: &Scene,
    rays: &Rays,
    filter: Filter,
    max_hits: usize,
    host_bytes_per_hit: usize,
    interrupt: &dyn Interrupt,
) -> Result<AllHits> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let tracer = scene.reference_tracer();
    let n = rays.len();
    let trace = |i: usize, found: &mut Vec<ReferenceHit>| {
        found.clear();
        tracer.trace_every(&rays.ray64(i, scene.center), rays.mask.get(i), filter, found);
        found.truncate(max_hits);
    };
    // Pass 1: each ray's count, and its hits while the kept total stays within the budget.
    let mut counts = try_vec(n, 0usize, "the counts of all hits")?;
    let mut kept: Vec<Vec<ReferenceHit>> = try_vec(n, Vec::new(), "the reference tier's hits")?;
    let kept_total = AtomicUsize::new(0);
    in_blocks(n, interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            counts[range.clone()].par_iter_mut().zip(&mut kept[range]).enumerate().with_min_len(256).for_each_init(
                Vec::new,
                |found, (k, (count, slot))| {
                    trace(start + k, found);
                    *count = found.len();
                    if kept_total.load(Ordering::Relaxed) <= KEPT_WHILE_COUNTING
                        && kept_total.fetch_add(found.len(), Ordering::Relaxed) + found.len() <= KEPT_WHILE_COUNTING
                    {
                        *slot = found.clone();
                    }
                },
            )
        });
    })?;
    let mut offsets = try_vec(n + 1, 0i64, "the offsets of all hits")?;
    for i in 0..n {
        offsets[i + 1] = offsets[i] + counts[i] as i64;
    }
    drop(counts);
    let total = offsets[n] as usize;
    if kept_total.into_inner() <= KEPT_WHILE_COUNTING {
        let mut hits = Vec::new();
        hits.try_reserve_exact(total)
            .map_err(|_| Error::OutOfMemory(format!("the {total} hits do not fit in host memory")))?;
        for found in kept {
            hits.extend(found);
        }
        return Ok(AllHits { offsets, hits, wide: true });
    }
    drop(kept);
    // Pass 2: refused before anything is stored where it cannot fit, else traced again into place.
    check_hits_fit(total, std::mem::size_of::<ReferenceHit>() + host_bytes_per_hit)?;
    let mut hits = try_vec(total, ReferenceHit { t: 0.0, u: 0.0, v: 0.0, instance: 0, prim: 0 }, "all hits")?;
    let mut rest = hits.as_mut_slice();
    let mut per_ray: Vec<&mut [ReferenceHit]> = Vec::new();
    per_ray
        .try_reserve_exact(n)
        .map_err(|_| Error::OutOfMemory("the hits' places do not fit in host memory".into()))?;
    for i in 0..n {
        let (mine, tail) = std::mem::take(&mut rest).split_at_mut((offsets[i + 1] - offsets[i]) as usize);
        per_ray.push(mine);
        rest = tail;
    }
    in_blocks(n, interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            per_ray[range].par_iter_mut().enumerate().with_min_len(256).for_each_init(Vec::new, |found, (k, slot)| {
                trace(start + k, found);
                // The same ray meets the same hits again (the tracer is deterministic).
                let m = slot.len().min(found.len());
                slot[..m].copy_from_slice(&found[..m]);
            })
        });
    })?;
    drop(per_ray);
    Ok(AllHits { offsets, hits, wide: true })
}

/// The light each ray keeps: the product of (1 - opacity) over its hits (every crossing, taken
/// with threshold 0), in f64.
pub fn transmittance(scene: &Scene, all: &AllHits, out: &mut [f64]) {
    parallel::install(|| {
        out.par_iter_mut().enumerate().with_min_len(1024).for_each(|(i, left)| {
            let hits = &all.hits[all.offsets[i] as usize..all.offsets[i + 1] as usize];
            *left = hits
                .iter()
                .map(|h| {
                    let placement = &scene.placements[h.instance as usize];
                    let opacity = match (&placement.mesh.opacity, placement.flags.force_opaque) {
                        (Some(opacity), false) => opacity[h.prim as usize] as f64,
                        _ => 1.0,
                    };
                    1.0 - opacity
                })
                .product();
        })
    });
}

/// The ray of each hit of a CSR list (`offsets`: ray i's hits are `offsets[i]..offsets[i + 1]`),
/// filled on all cores.
pub fn ray_indices(offsets: &[i64]) -> Result<Vec<i64>> {
    const BLOCK: usize = 4096;
    let rays = offsets.len() - 1;
    let mut out: Vec<i64> = try_zeroed(offsets[rays] as usize, "the hits' ray indices")?;
    let mut blocks = Vec::with_capacity(rays.div_ceil(BLOCK));
    let mut rest = out.as_mut_slice();
    for start in (0..rays).step_by(BLOCK) {
        let end = (start + BLOCK).min(rays);
        let (block, tail) = rest.split_at_mut((offsets[end] - offsets[start]) as usize);
        blocks.push((start, end, block));
        rest = tail;
    }
    parallel::install(|| {
        blocks.into_par_iter().for_each(|(start, end, block)| {
            let base = offsets[start];
            for ray in start..end {
                block[(offsets[ray] - base) as usize..(offsets[ray + 1] - base) as usize].fill(ray as i64);
            }
        })
    });
    Ok(out)
}

/// Writes every field the sink asks for, one entry per hit of `all` (of `rays`): where no field
/// needs the hit's ray or triangle's vertices (`normal`, `position`), in one pass over the hits on
/// all cores, a block of rays at a time, each record read from memory once for every field (a
/// pass per field: the columns of a million hits took 3 ms on an H200's host); else field by
/// field.
pub fn write_all_hit_columns(scene: &Scene, rays: &Rays, all: &AllHits, sink: &mut HitSink) -> Result<()> {
    if sink.position.is_some() || sink.field(Field::Normal).is_some() {
        return write_all_hits(scene, rays, all, sink);
    }
    const BLOCK: usize = 4096;
    let offsets = &all.offsets;
    let n = offsets.len() - 1;
    let wide = all.wide;
    // Each column cut at the same blocks of rays' hits.
    let mut columns: Vec<(Field, &mut [u8])> = sink.iter_mut().collect();
    let mut blocks: Vec<HitsBlock> = Vec::with_capacity(n.div_ceil(BLOCK));
    for start in (0..n).step_by(BLOCK) {
        let hits = (offsets[(start + BLOCK).min(n)] - offsets[start]) as usize;
        let mut parts = Vec::with_capacity(columns.len());
        for (field, column) in columns.iter_mut() {
            let (part, tail) = std::mem::take(column).split_at_mut(hits * field.bytes_per_ray(wide));
            *column = tail;
            parts.push((*field, part));
        }
        blocks.push((start, parts));
    }
    let split = |h: &ReferenceHit| scene.placements[h.instance as usize].triangles.split(h.prim as usize);
    parallel::install(|| {
        blocks.into_par_iter().for_each(|(start, parts)| {
            let end = (start + BLOCK).min(n);
            let hits = &all.hits[offsets[start] as usize..offsets[end] as usize];
            for (field, out) in parts {
                match field {
                    Field::T => write_floats(out, hits, wide, |h| [h.t]),
                    Field::Uv => write_floats(out, hits, wide, |h| [h.u, h.v]),
                    Field::Prim => write_ints(out, hits, |h| split(h).1 as i32),
                    Field::Geometry => write_ints(out, hits, |h| split(h).0 as i32),
                    Field::Instance => write_ints(out, hits, |h| h.instance as i32),
                    Field::Custom => {
                        write_ints(out, hits, |h| scene.placements[h.instance as usize].custom_index as i32)
                    }
                    Field::Normal => unreachable!("normals are written field by field"),
                }
            }
        })
    });
    Ok(())
}

/// A block of rays' hits to write: its first ray and its part of each column.
type HitsBlock<'a> = (usize, Vec<(Field, &'a mut [u8])>);

/// Each hit's `K` floats (f64 where `wide`, else f32) into `out`.
fn write_floats<const K: usize>(
    out: &mut [u8],
    hits: &[ReferenceHit],
    wide: bool,
    value: impl Fn(&ReferenceHit) -> [f64; K],
) {
    if wide {
        let out: &mut [f64] = bytemuck::cast_slice_mut(out);
        for (dst, h) in out.chunks_exact_mut(K).zip(hits) {
            dst.copy_from_slice(&value(h));
        }
    } else {
        let out: &mut [f32] = bytemuck::cast_slice_mut(out);
        for (dst, h) in out.chunks_exact_mut(K).zip(hits) {
            dst.copy_from_slice(&value(h).map(|v| v as f32));
        }
    }
}

/// Each hit's i32 into `out`.
fn write_ints(out: &mut [u8], hits: &[ReferenceHit], value: impl Fn(&ReferenceHit) -> i32) {
    let out: &mut [i32] = bytemuck::cast_slice_mut(out);
    for (dst, h) in out.iter_mut().zip(hits) {
        *dst = value(h);
    }
}

/// Writes every field the sink asks for, one entry per hit of `all` (of `rays`), `position`
/// included.
pub fn write_all_hits(scene: &Scene, rays: &Rays, all: &AllHits, sink: &mut HitSink) -> Result<()> {
    // A sphere's normal and position are its ray's at t: each hit's ray, where they are asked.
    let asks_points = sink.field(Field::Normal).is_some() || sink.position.is_some();
    let ray_of = if scene.has_spheres() && asks_points { ray_indices(&all.offsets)? } else { Vec::new() };
    let point = |k: usize| {
        let ray = rays.ray64(*ray_of.get(k)? as usize, scene.center);
        Some(ray.origin + all.hits[k].t * ray.direction)
    };
    write_hit_fields(scene, sink, all.wide, |k| Some(all.hits[k]), point);
    Ok(())
}

/// The refined tier's all hits from the fast tier's: each hit re-intersected with its triangle in
/// f64 and the ray's hits sorted again; a ray with a hit whose f64 answer leaves its interval
/// (f32 traversal accepted a graze, or a triangle just behind an origin on it) is traced again by
/// the CPU tracer.
pub fn refine_all(
    scene: &Scene,
    rays: &Rays,
    filter: Filter,
    max_hits: usize,
    fast: &AllHits,
    interrupt: &dyn Interrupt,
) -> Result<AllHits> {
    let tracer = scene.reference_tracer();
    let mut per_ray: Vec<Vec<ReferenceHit>> = try_vec(rays.len(), Vec::new(), "refining hits")?;
    in_blocks(rays.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            per_ray[range].par_iter_mut().enumerate().with_min_len(256).for_each(|(k, refined)| {
                let i = start + k;
                let ray = rays.ray64(i, scene.center);
                let found = &fast.hits[fast.offsets[i] as usize..fast.offsets[i + 1] as usize];
                let again = found.iter().any(|h| {
                    let placement = &scene.placements[h.instance as usize];
                    let local = ray.transformed(&placement.to_local);
                    let [a, b, c] = placement.triangles.triangle(h.prim as usize);
                    match plane_hit(&local, a, b, c) {
                        Some(p) if p.t >= local.tmin && p.t <= local.tmax => {
                            refined.push(ReferenceHit { t: p.t, u: p.u, v: p.v, ..*h });
                            false
                        }
                        _ => true,
                    }
                });
                if again {
                    refined.clear();
                    tracer.trace_every(&ray, rays.mask.get(i), filter, refined);
                    refined.truncate(max_hits);
                } else {
                    refined.sort_unstable_by(|x, y| {
                        x.t.total_cmp(&y.t).then((x.instance, x.prim).cmp(&(y.instance, y.prim)))
                    });
                }
            })
        });
    })?;
    let mut offsets = try_vec(rays.len() + 1, 0i64, "the offsets of all hits")?;
    for (i, refined) in per_ray.iter().enumerate() {
        offsets[i + 1] = offsets[i] + refined.len() as i64;
    }
    let mut hits = Vec::new();
    hits.try_reserve_exact(offsets[rays.len()] as usize)
        .map_err(|_| Error::OutOfMemory("the refined hits do not fit in host memory".into()))?;
    for refined in per_ray {
        hits.extend(refined);
    }
    Ok(AllHits { offsets, hits, wide: true })
}

/// The number of hits of each ray, in f64 on the CPU, into `out`.
pub fn count_hits(
    scene: &Scene,
    rays: &Rays,
    filter: Filter,
    out: &mut [i32],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    in_blocks(rays.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            out[range].par_iter_mut().enumerate().with_min_len(256).for_each_init(Vec::new, |found, (k, count)| {
                found.clear();
                tracer.trace_every(&rays.ray64(start + k, scene.center), rays.mask.get(start + k), filter, found);
                *count = found.len() as i32;
            })
        });
    })
}

/// The direction of the one ray each point casts for `contains` by parity: fixed, unit, and
/// along no axis or diagonal (the exact test decides rays through edges anyway).
pub const PARITY_DIRECTION: DVec3 = DVec3::new(0.6, 0.48, 0.64);

/// `host_winding::winding_ray`'s end of a whole ray: no end, nothing beyond.
pub const WHOLE_RAY: (f64, i32) = (f64::INFINITY, 0);

/// Whether each point lies inside any instance of the scene: by the parity of the crossings of
/// one ray per point with each instance (exact: each crossing counted once), or by the
/// generalized winding number (>= 1/2). A point on a surface (to within `ON_SURFACE_ULPS`)
/// counts as inside, by either method.
pub fn contains(scene: &Scene, points: Vec3s, winding: bool, out: &mut [u8], interrupt: &dyn Interrupt) -> Result<()> {
    let tracer = scene.reference_tracer();
    if winding {
        if let Some(cap) = cap_geometry(&scene.placements) {
            return contains_by_winding_rays(scene, points, &cap, out, interrupt);
        }
        build_winding_trees(scene);
    }
    let point = |i: usize| DVec3::from_array(points.row_f64(i)) - scene.center;
    let any_triangles = scene.placements.iter().any(|x| !x.triangles.is_spheres());
    in_blocks(out.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            out[range].par_iter_mut().enumerate().with_min_len(64).for_each_init(Vec::new, |found, (k, inside)| {
                let p = point(start + k);
                *inside = u8::from(if beyond_the_scene(scene, p) {
                    false
                } else if tracer.on_surface(p, ON_SURFACE_ULPS) {
                    true
                } else if winding {
                    scene.placements.iter().any(|placement| winding_number(placement, p) >= 0.5)
                } else if inside_a_sphere(scene, p) {
                    true
                } else if !any_triangles {
                    false
                } else {
                    found.clear();
                    let ray = Ray64 { origin: p, direction: PARITY_DIRECTION, tmin: 0.0, tmax: f64::INFINITY };
                    tracer.trace_every(&ray, 0xFF, Filter::sides(Cull::None), found);
                    // Spheres, which overlap, are asked directly (the parity of one set's crossings
                    // would be the spheres' exclusive or).
                    let in_spheres = |h: &ReferenceHit| scene.placements[h.instance as usize].triangles.is_spheres();
                    found.retain(|h| !in_spheres(h));
                    odd_crossings(found, scene.placements.len())
                });
            })
        });
    })
}

/// Whether `p` (scene frame) lies outside the scene's bounds, past a margin far beyond the
/// rounding of the bounds and of an on-surface test: outside by either method of `contains`. A
/// plane parts such a point from every instance, so each instance's surface lies in a half-space
/// without it: no ray from it crosses a closed surface an odd number of times, and a surface's
/// solid angle about it is below 2π (a winding number below 1/2).
pub(super) fn beyond_the_scene(scene: &Scene, p: DVec3) -> bool {
    let bounds = scene.bounds();
    let scale = bounds.min.abs().max(bounds.max.abs()).max_element().max(p.abs().max_element());
    !bounds.padded(64.0 * f64::EPSILON * scale).contains(p)
}

/// `contains` by winding number in a scene of one instance whose holes `cap` closes: one ray a
/// point, its crossings and the caps' winding number (`host_winding`), the points whose sum lies
/// within the cap's band of 1/2 decided by the whole winding number. The same answers as the
/// whole winding number's everywhere, at about the cost of `contains` by parity.
fn contains_by_winding_rays(
    scene: &Scene,
    points: Vec3s,
    cap: &CapGeometry,
    out: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    let (placement, band) = (&scene.placements[0], cap.band());
    in_blocks(out.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            out[range].par_iter_mut().enumerate().with_min_len(64).for_each(|(k, inside)| {
                let p = DVec3::from_array(points.row_f64(start + k)) - scene.center;
                *inside = if beyond_the_scene(scene, p) {
                    0
                } else if tracer.on_surface(p, ON_SURFACE_ULPS) {
                    1
                } else {
                    let (crossings, cap_winding) =
                        winding_ray(&tracer, placement, cap, band, p, (PARITY_DIRECTION, WHOLE_RAY));
                    mark_by_crossings(crossings, cap_winding, band)
                };
            })
        });
    })?;
    decide_on_the_cpu(scene, points, out, interrupt)
}

/// `contains` by winding number from each point's largest winding number `winding` (the GPU's,
/// within `band` of the CPU's): inside at 1/2 + band or more; within the band, the CPU's own test
/// decides; below, inside only on a surface. The reference tier's answers.
pub fn inside_by_winding(
    scene: &Scene,
    points: Vec3s,
    winding: &[f64],
    band: f64,
    out: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    parallel::install(|| {
        out.par_iter_mut().zip(winding).with_min_len(4096).for_each(|(inside, &w)| {
            *inside = if w >= 0.5 + band {
                1
            } else if w < 0.5 - band {
                ONLY_ON_A_SURFACE
            } else {
                UNSURE
            };
        })
    });
    decide_on_the_cpu(scene, points, out, interrupt)
}

/// Whether each point lies inside the scene's one instance, from its winding query's answers
/// (`Query::Winding`): the signed crossings of its ray with the mesh less its cap (`counts`) and
/// the cap's winding number about it (`cap_winding`; NaN: unsure). Points on a surface are
/// inside; points whose winding number lies within `band` of 1/2 (or unsure) are decided on the
/// CPU (the reference tier's winding number).
pub fn inside_by_crossings(
    scene: &Scene,
    points: Vec3s,
    counts: &[i32],
    cap_winding: &[f64],
    band: f64,
    out: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    parallel::install(|| {
        out.par_iter_mut().zip(counts.par_iter().zip(cap_winding)).with_min_len(4096).for_each(|(inside, (&c, &w))| {
            *inside = mark_by_crossings(Crossings(c), w, band);
        })
    });
    decide_on_the_cpu(scene, points, out, interrupt)
}

/// The first pass's mark of a point from its winding query's answers (see `inside_by_crossings`):
/// inside (1), outside (0), or `UNSURE`.
pub fn mark_by_crossings(crossings: Crossings, cap_winding: f64, band: f64) -> u8 {
    let w = f64::from(crossings.sum()) + cap_winding;
    if crossings.on_surface() || w >= 0.5 + band {
        1
    } else if w < 0.5 - band {
        0
    } else {
        // Also where the cap's winding number is NaN.
        UNSURE
    }
}

/// Whether a point lies inside a scene's one closed instance, from its parity query's answer:
/// on a surface, or an odd number of crossings.
pub fn inside_by_parity(crossings: Crossings) -> bool {
    crossings.on_surface() || crossings.odd()
}

/// A first pass's mark of a point whose winding number the GPU could not tell from 1/2: the CPU
/// decides (on a surface, or its own winding number at least 1/2).
pub(super) const UNSURE: u8 = 2;
/// A first pass's mark of a point outside unless it lies on a surface, which the CPU tests.
const ONLY_ON_A_SURFACE: u8 = 3;

/// Replaces the marks of a first pass (`UNSURE`, `ONLY_ON_A_SURFACE`) by the reference tier's
/// answers, on all cores; the other points keep theirs.
pub fn decide_on_the_cpu(scene: &Scene, points: Vec3s, out: &mut [u8], interrupt: &dyn Interrupt) -> Result<()> {
    if !parallel::install(|| out.par_iter().any(|&x| x > 1)) {
        return Ok(());
    }
    let tracer = scene.reference_tracer();
    build_winding_trees(scene);
    let point = |i: usize| DVec3::from_array(points.row_f64(i)) - scene.center;
    in_blocks(out.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            out[range].par_iter_mut().enumerate().with_min_len(256).filter(|(_, x)| **x > 1).for_each(|(k, inside)| {
                let p = point(start + k);
                let mark = *inside;
                *inside = u8::from(
                    tracer.on_surface(p, ON_SURFACE_ULPS)
                        || (mark == UNSURE
                            && scene.placements.iter().any(|placement| winding_number(placement, p) >= 0.5)),
                );
            })
        });
    })
}

/// The surface point nearest to each point within `max_distance`, on the CPU in f64 (all cores):
/// the reference tier of `closest_points`, and the others' oracle.
pub fn closest_points(
    scene: &Scene,
    points: Vec3s,
    max_distance: f64,
    interrupt: &dyn Interrupt,
) -> Result<Vec<Option<ClosestHit>>> {
    let tracer = scene.reference_tracer();
    let n = points.rows();
    // Searched cell by cell along a Morton curve, each search started from the previous point's
    // nearest item: neighbours share their nearest (or nearly), so the first measure prunes
    // most of the hierarchy, and their nodes stay in cache.
    let bounds = scene.bounds();
    let order = morton::point_order(points, bounds.min + scene.center, bounds.max + scene.center);
    let mut sorted: Vec<Option<ClosestHit>> = try_vec(n, None, "the closest points")?;
    in_blocks(n, interrupt, |range| {
        let order = &order.as_slice()[range.clone()];
        parallel::install(|| {
            // The block's points gathered in the curve's order first: a pass whose reads overlap,
            // where each search would wait for its point's.
            let gathered: Vec<DVec3> = order
                .par_iter()
                .with_min_len(4096)
                .map(|&i| DVec3::from_array(points.row_f64(i as usize)) - scene.center)
                .collect();
            sorted[range].par_iter_mut().zip(gathered).with_min_len(64).for_each_init(
                || None,
                |hint, (hit, p)| {
                    *hit = tracer.closest_point_from(p, 0xFF, max_distance, *hint);
                    *hint = hit.map(|h| (h.instance, h.prim)).or(*hint);
                },
            )
        });
    })?;
    let mut hits: Vec<Option<ClosestHit>> = try_vec(n, None, "the closest points")?;
    order.scatter(&sorted, &mut hits);
    Ok(hits)
}

/// Writes the fields `sink` asks for of each point's closest surface point `hit(i)` (None: none
/// within reach): `t` is the distance, `position` the point (f64, world), the others as a hit's.
pub fn write_closest(scene: &Scene, sink: &mut HitSink, hit: impl Fn(usize) -> Option<(ReferenceHit, DVec3)> + Sync) {
    let position = sink.position.take();
    write_hit_fields(scene, sink, true, |i| hit(i).map(|(h, _)| h), |i| hit(i).map(|(_, p)| p - scene.center));
    if let Some(out) = position {
        parallel::install(|| {
            out.par_chunks_exact_mut(24).enumerate().with_min_len(1024).for_each(|(i, dst)| {
                put_f64s(dst, &hit(i).map_or(DVec3::NAN, |(_, point)| point).to_array());
            })
        });
    }
}

/// The reference tier's closest points as `write_closest` takes them.
pub fn closest_hit_record(scene: &Scene, hit: &Option<ClosestHit>) -> Option<(ReferenceHit, DVec3)> {
    hit.map(|h| {
        (ReferenceHit { t: h.distance, u: h.u, v: h.v, instance: h.instance, prim: h.prim }, h.point + scene.center)
    })
}

/// `contains` from each point's count of crossings (of a scene's one instance): inside where
/// the point is on the surface or the count is odd.
pub fn inside_by_counts(
    scene: &Scene,
    points: Vec3s,
    counts: &[i32],
    out: &mut [u8],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    let tracer = scene.reference_tracer();
    in_blocks(out.len(), interrupt, |range| {
        let start = range.start;
        parallel::install(|| {
            out[range].par_iter_mut().enumerate().with_min_len(256).for_each(|(k, inside)| {
                let p = DVec3::from_array(points.row_f64(start + k)) - scene.center;
                *inside = u8::from(counts[start + k] % 2 == 1 || tracer.on_surface(p, ON_SURFACE_ULPS));
            })
        });
    })
}

/// How close to a triangle a point counts as on it, in units in the last place of the
/// coordinates: the rounding of re-centring a point and of the distance's own arithmetic.
pub(super) const ON_SURFACE_ULPS: f64 = 8.0;

/// Whether any instance is crossed an odd number of times (the point is off every surface).
pub fn odd_crossings(hits: &[ReferenceHit], instances: usize) -> bool {
    let mut odd = vec![false; instances];
    for h in hits {
        odd[h.instance as usize] ^= true;
    }
    odd.into_iter().any(|o| o)
}

/// The generalized winding number of an instance's triangles about `p` (scene frame): the sum
/// of their signed solid angles over 4π (Jacobson et al. 2013), 1 inside a closed surface, 0
/// outside, in between near holes, summed over the mesh's hierarchy (`WindingTree`: exact, far
/// nodes by their boundaries); a mirroring placement turns its triangles inside out, so its sum
/// is negated.
fn winding_number(placement: &crate::scene::Placement, p: DVec3) -> f64 {
    let set = &placement.triangles;
    let w = set.winding_number(&placement.to_scene, p, placement.to_local.point(p));
    // A mirrored sphere is still a sphere, its inside inside.
    let mirrored = placement.to_scene.linear.determinant() < 0.0 && !set.is_spheres();
    if mirrored {
        -w
    } else {
        w
    }
}

/// Whether `p` (scene frame) lies inside (or on) a sphere of any sphere set.
fn inside_a_sphere(scene: &Scene, p: DVec3) -> bool {
    scene.placements.iter().filter(|x| x.triangles.is_spheres()).any(|x| winding_number(x, p) >= 0.5)
}

/// Builds every instance's winding tree before a parallel pass reads them: built lazily inside
/// it, a thread waiting on one under construction could be the one constructing it (rayon steals
/// work while it waits) and never wake.
pub fn build_winding_trees(scene: &Scene) {
    for placement in scene.placements.iter().filter(|p| !p.triangles.is_spheres()) {
        placement.triangles.winding_tree();
    }
}

/// The hit triangles of a batch: caller's prim, instance and geometry (int32, -1 on a miss),
/// barycentrics (2 f32, or 2 f64 when `wide`) and t (f32 or f64) per ray.
pub struct HitTriangles<'a> {
    pub prim: &'a [u8],
    pub instance: &'a [u8],
    pub geometry: &'a [u8],
    pub t: &'a [u8],
    pub uv: &'a [u8],
    pub wide: bool,
}

impl HitTriangles<'_> {
    fn t(&self, i: usize) -> f64 {
        if self.wide {
            f64::from_ne_bytes(self.t[8 * i..8 * i + 8].try_into().expect("8 bytes"))
        } else {
            f32::from_ne_bytes(self.t[4 * i..4 * i + 4].try_into().expect("4 bytes")) as f64
        }
    }

    fn uv(&self, i: usize) -> (f64, f64) {
        if self.wide {
            let at = |k: usize| f64::from_ne_bytes(self.uv[8 * k..8 * k + 8].try_into().expect("8 bytes"));
            (at(2 * i), at(2 * i + 1))
        } else {
            let at = |k: usize| f32::from_ne_bytes(self.uv[4 * k..4 * k + 4].try_into().expect("4 bytes")) as f64;
            (at(2 * i), at(2 * i + 1))
        }
    }
}

/// World-space hit points from each hit's triangle and barycentrics, interpolated in f64 in the
/// mesh's frame (so their error is relative to the triangle's size, not to the ray's length or
/// the origin's distance); on spheres, `origin + t * direction` in f64. 3 f64 per ray when
/// `hits.wide`, else 3 f32. NaN on a miss.
pub fn positions(scene: &Scene, rays: &Rays, hits: &HitTriangles, out: &mut [u8]) {
    let width = if hits.wide { 24 } else { 12 };
    parallel::install(|| {
        out.par_chunks_exact_mut(width).enumerate().with_min_len(1024).for_each(|(i, dst)| {
            let p = int_at(hits.prim, i);
            let placement = (p >= 0).then(|| &scene.placements[int_at(hits.instance, i) as usize]);
            let point = match placement {
                None => DVec3::NAN,
                Some(placement) if placement.mesh.kind == MeshKind::Spheres => {
                    let ray = rays.ray64(i, DVec3::ZERO);
                    ray.origin + hits.t(i) * ray.direction
                }
                Some(placement) => {
                    let global = placement.triangles.global(int_at(hits.geometry, i) as usize, p as usize);
                    let [a, b, c] = placement.triangles.triangle(global);
                    let (u, v) = hits.uv(i);
                    placement.to_scene.point(a + u * (b - a) + v * (c - a)) + scene.center
                }
            };
            if hits.wide {
                put_f64s(dst, &point.to_array());
            } else {
                put_f32s(dst, &point.as_vec3().to_array());
            }
        })
    });
}

/// Refuses a result of `hits` hits that would not fit in the host's memory, before storing any.
pub(crate) fn check_hits_fit(hits: usize, bytes_per_hit: usize) -> Result<()> {
    let needed = hits as u128 * bytes_per_hit as u128;
    match crate::gpu::memory::short_of_host_memory(needed) {
        Some(available) => Err(Error::OutOfMemory(format!(
            "the {hits} hits of this query need about {:.2} GB of host memory, more than the {:.2} GB \
             available: trace fewer rays at a time, set max_hits, or ask fewer outputs",
            needed as f64 / 1e9,
            available as f64 / 1e9
        ))),
        _ => Ok(()),
    }
}

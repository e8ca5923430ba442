//! The `"reference"` tier: a CPU tracer in f64 over two levels of bounding-volume hierarchies,
//! running the same watertight test and tie-break rules as the `"exact"` GPU tier, on all cores.
//! It needs no GPU and is the oracle the other tiers are measured against.

use std::sync::OnceLock;

use glam::DVec3;
use rayon::prelude::*;

use super::bvh::Bvh;
use super::parallel;
use super::wide_tree::{NearestQuery, RayQuery, WideTree};
use super::winding::{self, Triangles, WindingTree};

use crate::geometry::precision::{
    closest_point_on_triangle, length_scale, sphere_roots, watertight_edges, Aabb, Affine, Cull, Ray64, ShearedRay,
};

/// Triangles of one mesh in its own (re-centred) frame, in f64, with their hierarchy (built on
/// first use: only the reference tier needs it); or, for a sphere set, its spheres (and their
/// boxes' corners as `vertices`, no faces).
pub struct TriangleSet {
    pub vertices: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
    pub bounds: Aabb,
    /// Where each part (geometry) of a multi-part mesh starts among `faces`, and the end.
    pub part_offsets: Vec<u32>,
    /// A sphere set's spheres (centre, radius); empty for triangles.
    pub spheres: Vec<(DVec3, f64)>,
    bvh: OnceLock<Bvh>,
    wide: OnceLock<Option<WideTree>>,
    winding: OnceLock<WindingTree>,
    closed: OnceLock<bool>,
}

impl TriangleSet {
    /// `part_offsets`: first triangle of each part, then the total (`[0, faces.len()]` for one).
    pub fn new(vertices: Vec<DVec3>, faces: Vec<[u32; 3]>, part_offsets: Vec<u32>) -> TriangleSet {
        debug_assert_eq!(part_offsets.last().copied(), Some(faces.len() as u32));
        let bounds = Aabb::of_points(vertices.iter().copied());
        let spheres = Vec::new();
        TriangleSet {
            vertices,
            faces,
            bounds,
            part_offsets,
            spheres,
            bvh: OnceLock::new(),
            wide: OnceLock::new(),
            winding: OnceLock::new(),
            closed: OnceLock::new(),
        }
    }

    /// A sphere set (one part), its boxes' corners as vertices.
    pub fn of_spheres(spheres: Vec<(DVec3, f64)>) -> TriangleSet {
        let vertices = spheres.iter().flat_map(|&(c, r)| [c - DVec3::splat(r), c + DVec3::splat(r)]).collect();
        let part_offsets = vec![0, spheres.len() as u32];
        TriangleSet { spheres, part_offsets, ..TriangleSet::new(vertices, Vec::new(), vec![0, 0]) }
    }

    /// Whether this is a sphere set.
    pub fn is_spheres(&self) -> bool {
        !self.spheres.is_empty()
    }

    /// The box of item `prim` (a triangle, or a sphere).
    fn item_bounds(&self, prim: usize) -> Aabb {
        match self.spheres.get(prim) {
            Some(&(c, r)) => Aabb { min: c - DVec3::splat(r), max: c + DVec3::splat(r) },
            None => Aabb::of_points(self.triangle(prim)),
        }
    }

    /// How many spheres, where the set holds spheres, at `local` (inside 1, on the surface 1/2
    /// each): their winding number, under any placement.
    fn spheres_winding_number(&self, local: DVec3) -> f64 {
        let probe = Ray64 { origin: local, direction: DVec3::ONE, tmin: 0.0, tmax: 0.0 };
        let mut sum = 0.0;
        self.bvh().traverse(&probe, &mut 0.0, |prim, _| {
            let (c, r) = self.spheres[prim as usize];
            let (squared, r2) = ((local - c).length_squared(), r * r);
            sum += if squared < r2 {
                1.0
            } else if squared == r2 {
                0.5
            } else {
                0.0
            };
            true
        });
        sum
    }

    /// The index among all triangles of triangle `prim` of part `part`.
    pub fn global(&self, part: usize, prim: usize) -> usize {
        self.part_offsets[part] as usize + prim
    }

    /// (part, triangle within it) of a triangle's index among all.
    pub fn split(&self, global: usize) -> (usize, usize) {
        let part = self.part_offsets.partition_point(|&start| start as usize <= global) - 1;
        (part, global - self.part_offsets[part] as usize)
    }

    /// What each item's box grows by in the hierarchy: a hair of the mesh's size, so that f64
    /// rounding in the slab test cannot reject a triangle that lies on its own box's face.
    fn item_pad(&self) -> f64 {
        1e-9 * self.bounds.extent().max_element().max(f64::MIN_POSITIVE)
    }

    pub fn bvh(&self) -> &Bvh {
        self.bvh.get_or_init(|| {
            let pad = self.item_pad();
            let items = self.faces.len().max(self.spheres.len());
            let boxes: Vec<Aabb> =
                parallel::install(|| (0..items).into_par_iter().map(|p| self.item_bounds(p).padded(pad)).collect());
            Bvh::build(&boxes)
        })
    }

    /// The hierarchy's four-wide f32 form for nearest searches and rays (built on first use); None
    /// where its boxes lie beyond what f32 bounds take (`WideTree::build`).
    pub fn wide_tree(&self) -> Option<&WideTree> {
        self.wide
            .get_or_init(|| WideTree::build(self.bvh(), &|item| (!self.is_spheres()).then(|| self.triangle(item))))
            .as_ref()
    }

    /// The boundaries of the hierarchy's nodes, for winding numbers (built on first use).
    pub fn winding_tree(&self) -> &WindingTree {
        debug_assert!(!self.is_spheres(), "a sphere set has no winding tree");
        self.winding.get_or_init(|| WindingTree::build(self.bvh(), &self.faces))
    }

    /// The winding number about `p` (scene frame; `local`: the same point in the set's frame) of
    /// the set's triangles placed by `to_scene`, unsigned by any mirroring (`WindingTree`).
    pub fn winding_number(&self, to_scene: &Affine, p: DVec3, local: DVec3) -> f64 {
        if self.is_spheres() {
            return self.spheres_winding_number(local);
        }
        let triangles = Triangles { bvh: self.bvh(), vertices: &self.vertices, faces: &self.faces };
        self.winding_tree().winding_number(triangles, to_scene, p, local)
    }

    /// Whether the triangles close up: each oriented edge `(a, b)` run as often as `(b, a)` (a
    /// sphere set is closed). Then the signed count of a ray's crossings (and its parity) is the
    /// same from every point of a region the surface does not cut (computed once).
    pub fn is_closed(&self) -> bool {
        *self.closed.get_or_init(|| self.is_spheres() || winding::net_boundary_is_empty(&self.faces))
    }

    #[inline]
    pub fn triangle(&self, prim: usize) -> [DVec3; 3] {
        // Indexed one by one: `array::map` here stayed a call of its own (a tenth of a closest
        // point search's time).
        let [i, j, k] = self.faces[prim];
        [self.vertices[i as usize], self.vertices[j as usize], self.vertices[k as usize]]
    }
}

/// One placement of a triangle set, for the CPU tracer.
pub struct PlacedSet<'a> {
    pub triangles: &'a TriangleSet,
    /// From the scene's frame to the set's.
    pub to_local: Affine,
    pub custom_index: u32,
    pub mask: u8,
    /// The set's bounds in the scene's frame.
    pub bounds: Aabb,
    /// Front is the side opposite the object-space normal (a mirroring placement, or flipped).
    pub flip_facing: bool,
    /// Query culling does not apply to this set.
    pub cull_disable: bool,
    /// Opacity per triangle (among all parts), where the set has translucent triangles.
    pub opacity: Option<&'a [f32]>,
    /// From the set's frame to the scene's (the inverse of `to_local`).
    pub to_scene: Affine,
}

/// The surface point nearest to a query point: the distance and the point in the scene's frame,
/// the barycentrics (of vertices 1 and 2) of the point on its triangle, the instance and the
/// triangle among all parts of its mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClosestHit {
    pub distance: f64,
    pub point: DVec3,
    pub u: f64,
    pub v: f64,
    pub instance: u32,
    pub prim: u32,
}

impl ClosestHit {
    /// The order that decides between surface points: nearer first, then the lower (instance,
    /// prim), so that a point equally near several triangles (an edge, a vertex) gets the same
    /// one in every tier. (While searching, `distance` holds squared distances.)
    pub fn is_before(&self, other: &ClosestHit) -> bool {
        self.distance < other.distance
            || (self.distance == other.distance && (self.instance, self.prim) < (other.instance, other.prim))
    }
}

/// Where a placement only moves its set (a scene's usual one instance, less the scene's centre),
/// the offset: the map's linear part multiplies by ones and zeros, so adding its offset is the
/// same, bit for bit, in fewer operations.
fn moved_by(set: &PlacedSet) -> Option<DVec3> {
    (set.to_scene.linear == glam::DMat3::IDENTITY).then_some(set.to_scene.offset)
}

/// Item `prim` of `set` (instance `instance`) as a closest-point search measures it from `p`: its
/// nearest point (scene frame) and that point's squared distance after scaling by `scale`
/// (compared squared, exactly as computed, so that ties are ties in every tier); `moved`: the
/// placement's offset where it only moves the set (`moved_by`).
#[inline]
fn measure_item(set: &PlacedSet, instance: u32, prim: u32, p: DVec3, scale: f64, moved: Option<DVec3>) -> ClosestHit {
    let q = if set.triangles.is_spheres() {
        closest_point_on_sphere(set, prim as usize, p)
    } else {
        let triangle = set.triangles.triangle(prim as usize);
        let [a, b, c] = match moved {
            Some(offset) => triangle.map(|v| v + offset),
            None => triangle.map(|v| set.to_scene.point(v)),
        };
        closest_point_on_triangle(p, a, b, c)
    };
    ClosestHit { distance: ((q - p) * scale).length_squared(), point: q, u: 0.0, v: 0.0, instance, prim }
}

/// The barycentrics (of b and c) of a point `q` of triangle (a, b, c), in f64.
pub fn barycentrics(q: DVec3, a: DVec3, b: DVec3, c: DVec3) -> (f64, f64) {
    let (e1, e2, w) = (b - a, c - a, q - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (dw1, dw2) = (w.dot(e1), w.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if det == 0.0 {
        return (0.0, 0.0);
    }
    ((d22 * dw1 - d12 * dw2) / det, (d11 * dw2 - d12 * dw1) / det)
}

/// Which triangles a ray may hit: the sides `cull` keeps, whose opacity reaches `threshold`
/// (0: every triangle); with `contacts`, a ray through a shared edge or vertex meets every
/// triangle there (closed triangles) rather than one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Filter {
    pub cull: Cull,
    pub threshold: f32,
    pub contacts: bool,
}

impl Filter {
    /// Every triangle on the sides `cull` keeps, whatever its opacity.
    pub fn sides(cull: Cull) -> Filter {
        Filter { cull, threshold: 0.0, contacts: false }
    }
}

/// What the CPU tracer found for one ray: t and barycentrics (of vertices 1 and 2) in f64, the
/// instance and the triangle among all parts of its mesh. The exact tier's GPU stores its all-hits
/// records in this layout too (`gpu::records::ExactHit`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ReferenceHit {
    pub t: f64,
    pub u: f64,
    pub v: f64,
    pub instance: u32,
    pub prim: u32,
}

impl ReferenceHit {
    /// The order that decides between hits: nearer first, then the lower (instance, prim), so
    /// that every tier picks the same one of several triangles at the same distance.
    pub fn is_before(&self, other: &ReferenceHit) -> bool {
        self.t < other.t || (self.t == other.t && (self.instance, self.prim) < (other.instance, other.prim))
    }
}

/// Weights w such that Σ wᵢ gᵢ² bounds from below the squared scene distance between two local
/// points at least gᵢ apart along each local axis (a point and a box, g its gap), under
/// `to_scene`'s linear part A. Where A's columns are nearly orthogonal (a rotation of a
/// non-uniform scale: the bound is then tight), AᵀA's diagonal less its off-diagonal part O
/// (|vᵀOv| ≤ ‖O‖_F |v|² ≤ ‖O‖_F/min dᵢ · Σ dᵢvᵢ²); else the smallest stretch squared on every
/// axis (1 / `to_local`'s largest). A margin covers the rounding of AᵀA.
pub fn gap_weights(to_scene: &Affine, to_local: &Affine) -> [f64; 3] {
    let m = to_scene.linear;
    let a = m.transpose() * m;
    let diagonal = DVec3::new(a.x_axis.x, a.y_axis.y, a.z_axis.z);
    // Each entry of AᵀA is within 3 ε max dᵢ of its value.
    let rounding = 8.0 * f64::EPSILON * diagonal.max_element();
    let off = (2.0 * (a.y_axis.x.powi(2) + a.z_axis.x.powi(2) + a.z_axis.y.powi(2))).sqrt() + rounding;
    let smallest = diagonal.min_element();
    if smallest.is_finite() && smallest > 0.0 && off <= 0.25 * smallest {
        return (diagonal * ((1.0 - off / smallest) * (1.0 - 1e-9))).to_array();
    }
    let shrink = 1.0 / largest_stretch(to_local).max(f64::MIN_POSITIVE);
    [shrink * shrink; 3]
}

/// Σ wᵢ gᵢ², g the gap from `b` to `p` (0 inside) times `scale` (a power of two).
#[inline]
pub fn weighted_gap(b: &Aabb, p: DVec3, weights: DVec3, scale: f64) -> f64 {
    let gap = (b.min - p).max(p - b.max).max(DVec3::ZERO) * scale;
    (gap * gap).dot(weights)
}

/// An affine map's largest stretch (the spectral norm of its linear part), from above: the square
/// root of the largest eigenvalue of MᵀM (Smith's closed form for symmetric 3×3 matrices), with a
/// margin for its rounding; never above the Frobenius norm, which bounds it too.
pub fn largest_stretch(map: &Affine) -> f64 {
    let m = map.linear;
    let frobenius = (m.x_axis.length_squared() + m.y_axis.length_squared() + m.z_axis.length_squared()).sqrt();
    let a = m.transpose() * m;
    let q = (a.x_axis.x + a.y_axis.y + a.z_axis.z) / 3.0;
    let p1 = a.y_axis.x.powi(2) + a.z_axis.x.powi(2) + a.z_axis.y.powi(2);
    let p2 = (a.x_axis.x - q).powi(2) + (a.y_axis.y - q).powi(2) + (a.z_axis.z - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    let largest = if p == 0.0 {
        q
    } else {
        let b = (a - glam::DMat3::from_diagonal(DVec3::splat(q))) * (1.0 / p);
        let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
        q + 2.0 * p * (r.acos() / 3.0).cos()
    };
    (largest.max(0.0).sqrt() * (1.0 + 1e-9)).min(frobenius)
}

/// Two-level CPU tracer over placed triangle sets.
pub struct ReferenceTracer<'a> {
    sets: Vec<PlacedSet<'a>>,
    top: Bvh,
}

impl<'a> ReferenceTracer<'a> {
    pub fn new(sets: Vec<PlacedSet<'a>>) -> ReferenceTracer<'a> {
        // Build every hierarchy here, before tracing: built lazily inside the parallel trace, a
        // thread waiting on one under construction could be the thread constructing it (rayon
        // steals work while it waits: the builds run on all cores) and never wake. The four-wide
        // tree too (most of the tracer's queries walk it).
        for set in &sets {
            set.triangles.bvh();
            set.triangles.wide_tree();
        }
        let boxes: Vec<Aabb> = sets.iter().map(|s| s.bounds).collect();
        ReferenceTracer { top: Bvh::build(&boxes), sets }
    }

    /// The first hit of `ray` by the tie-break order among the sets its `mask` sees and the
    /// sides `cull` keeps; with `any`, the first one found.
    pub fn trace(&self, ray: &Ray64, mask: u8, filter: Filter, any: bool) -> Option<ReferenceHit> {
        let mut best: Option<ReferenceHit> = None;
        self.for_each_hit(ray, mask, filter, |candidate, _, tmax| {
            if best.is_none_or(|b| candidate.is_before(&b)) {
                best = Some(candidate);
                // Boxes are skipped past a little beyond the best t: their entry distances are
                // rounded to a few ulps of themselves (thousands of units from 1e20 away), and a
                // box holding a triangle at the same t may win the tie-break (the exact tier's
                // shaders commit as far: exact.glsl committed_distance).
                *tmax = candidate.t + 8.0 * f64::EPSILON * candidate.t.abs();
            }
            !any
        });
        best
    }

    /// Every hit of `ray` within [tmin, tmax] among the sets its `mask` sees and the sides `cull`
    /// keeps, appended to `hits` in the order `ReferenceHit::is_before` defines (by t, then by
    /// instance and triangle). The watertight test reports each crossing of a surface once: a ray
    /// through a shared edge or vertex hits exactly one of the triangles there, while distinct
    /// triangles at the same t (coplanar copies, instances in one place) are all reported.
    pub fn trace_every(&self, ray: &Ray64, mask: u8, filter: Filter, hits: &mut Vec<ReferenceHit>) {
        let first = hits.len();
        self.for_each_hit(ray, mask, filter, |hit, _, _| {
            hits.push(hit);
            true
        });
        hits[first..]
            .sort_unstable_by(|x, y| x.t.total_cmp(&y.t).then((x.instance, x.prim).cmp(&(y.instance, y.prim))));
    }

    /// The signed sum of `ray`'s crossings with every triangle (every side, whatever its
    /// opacity), each crossing once as `trace_every` finds them: +1 where the ray meets a
    /// triangle's back in its mesh's frame (it leaves an outward mesh), -1 its front; the exact
    /// tier's winding query counts the same (shaders/exact.glsl `exact_crossing`).
    pub fn signed_crossings(&self, ray: &Ray64) -> i32 {
        let mut sum = 0;
        self.for_each_hit(ray, 0xFF, Filter::sides(Cull::None), |_, front, _| {
            sum += if front { -1 } else { 1 };
            true
        });
        sum
    }

    /// Calls `found` with each hit of `ray` no farther than the `tmax` it keeps (which `found`
    /// may lower), among the sets `mask` sees and the sides `cull` keeps, until it returns false.
    fn for_each_hit(
        &self,
        ray: &Ray64,
        mask: u8,
        filter: Filter,
        mut found: impl FnMut(ReferenceHit, bool, &mut f64) -> bool,
    ) {
        let mut tmax = ray.tmax;
        self.top.traverse(ray, &mut tmax, |instance, tmax| {
            let set = &self.sets[instance as usize];
            if set.mask & mask == 0 {
                return true;
            }
            if set.triangles.is_spheres() {
                return for_each_sphere_hit(set, instance, ray, tmax, &mut found);
            }
            let local = ShearedRay::new(Ray64 { tmax: *tmax, ..ray.transformed(&set.to_local) });
            let mut go_on = true;
            let mut test = |prim: u32, tmax: &mut f64| {
                let [a, b, c] = set.triangles.triangle(prim as usize);
                let Some(hit) = watertight_edges(&local, a, b, c, filter.contacts) else { return true };
                if hit.t > *tmax || !(set.cull_disable || filter.cull.keeps(hit.front != set.flip_facing)) {
                    return true;
                }
                if set.opacity.is_some_and(|o| o[prim as usize] < filter.threshold) {
                    return true;
                }
                go_on = found(ReferenceHit { t: hit.t, u: hit.u, v: hit.v, instance, prim }, hit.front, tmax);
                go_on
            };
            // Through the four-wide f32 tree where it takes the ray (its boxes grown past
            // rounding: every triangle the binary f64 traversal meets, and a few more).
            let tree = set.triangles.wide_tree();
            match tree.and_then(|tree| Some((tree, RayQuery::new(tree, &local.ray)?))) {
                Some((tree, query)) => tree.traverse(&query, tmax, &mut test),
                None => set.triangles.bvh().traverse(&local.ray, tmax, &mut test),
            }
            go_on
        });
    }

    /// The surface point nearest to `p` (scene frame) within `max_distance`, among the sets
    /// `mask` sees: every triangle is measured in the scene's frame in f64 (so that rotation,
    /// non-uniform scale and mirroring of an instance keep distances exact); the hierarchies
    /// prune with bounds that hold under each placement's stretch. Lengths are compared squared
    /// after scaling by a power of two (`search_scale`), so that a point 1e155 away or a scene
    /// 1e-160 across neither overflows nor underflows them.
    pub fn closest_point(&self, p: DVec3, mask: u8, max_distance: f64) -> Option<ClosestHit> {
        self.closest_point_from(p, mask, max_distance, None)
    }

    /// `closest_point`, its search started from item `hint` (instance, item), where given: a
    /// neighbouring point's nearest is often this one's, or near it, and its distance prunes the
    /// search from the first node. The answer is the same (the nearest by `ClosestHit::is_before`,
    /// a total order, whatever the search meets first).
    pub fn closest_point_from(
        &self,
        p: DVec3,
        mask: u8,
        max_distance: f64,
        hint: Option<(u32, u32)>,
    ) -> Option<ClosestHit> {
        let scale = self.search_scale(p);
        let mut best: Option<ClosestHit> = None;
        let mut reach = max_distance * scale;
        let limit = reach * reach;
        if let Some((instance, prim)) = hint {
            let set = &self.sets[instance as usize];
            if set.mask & mask != 0 {
                let hit = measure_item(set, instance, prim, p, scale, moved_by(set));
                if hit.distance <= limit {
                    reach = hit.distance.sqrt();
                    best = Some(hit);
                }
            }
        }
        self.top.nearest(
            // Shrunk past rounding, as the meshes' own bounds are: a nearest point computed an
            // ulp outside its instance's box is still met, with or without a hint.
            |b| ((b.min - p).max(p - b.max).max(DVec3::ZERO) * scale).length() * (1.0 - 2e-12),
            &mut reach,
            |instance, reach| {
                let set = &self.sets[instance as usize];
                if set.mask & mask == 0 {
                    return;
                }
                let local = set.to_local.point(p);
                // Local box gaps, weighted per axis, bound world distances from below.
                let weights = DVec3::from_array(gap_weights(&set.to_scene, &set.to_local));
                let moved = moved_by(set);
                // Searched in squared lengths (no square root a node): the best's squared
                // distance so far, or the limit's.
                let mut reach_squared = best.map_or(limit, |b| b.distance);
                let before = reach_squared;
                let mut measure = |prim: u32, reach_squared: &mut f64| {
                    let hit = measure_item(set, instance, prim, p, scale, moved);
                    if hit.distance <= limit && best.is_none_or(|b| hit.is_before(&b)) {
                        best = Some(hit);
                        *reach_squared = hit.distance;
                    }
                };
                // Through the four-wide f32 tree where it takes the point (scale 1: lengths in
                // f32's range), else the binary f64 one; each item bounded by its own box first.
                let wide = (scale == 1.0).then(|| set.triangles.wide_tree()).flatten();
                match wide.and_then(|tree| Some((tree, NearestQuery::new(tree, local, weights)?))) {
                    Some((tree, query)) => tree.nearest(&query, &mut reach_squared, &mut measure),
                    None => set.triangles.bvh().nearest(
                        |b| weighted_gap(b, local, weights, scale) * (1.0 - 2e-12),
                        &mut reach_squared,
                        &mut measure,
                    ),
                }
                if reach_squared != before {
                    *reach = reach_squared.sqrt();
                }
            },
        );
        best.map(|hit| {
            let set = &self.sets[hit.instance as usize];
            if set.triangles.is_spheres() {
                // Barycentrics mean nothing on a sphere (NaN, as the fast tier's hits have).
                return ClosestHit { distance: hit.distance.sqrt() / scale, u: f64::NAN, v: f64::NAN, ..hit };
            }
            let [a, b, c] = set.triangles.triangle(hit.prim as usize).map(|v| set.to_scene.point(v));
            let (u, v) = barycentrics(hit.point, a, b, c);
            ClosestHit { distance: hit.distance.sqrt() / scale, u, v, ..hit }
        })
    }

    /// The power of two that closest-point searches from `p` scale lengths by before squaring
    /// them: `length_scale` of the largest coordinate of `p` and of the scene's bounds (the GPU's
    /// closest_point.comp takes the same).
    pub fn search_scale(&self, p: DVec3) -> f64 {
        let bounds = self.top.nodes().first().map_or(0.0, |n| n.bounds.min.abs().max(n.bounds.max.abs()).max_element());
        length_scale(p.abs().max_element().max(bounds))
    }

    /// Whether `p` (scene frame) lies on a triangle of any set, to within `ulps` units in the last
    /// place of the coordinates involved: the on-surface test of `contains`, which a ray from
    /// `p` cannot make (its t at the surface it starts on rounds to either side of 0).
    pub fn on_surface(&self, p: DVec3, ulps: f64) -> bool {
        self.sets.iter().any(|set| {
            let tolerance = |scale: f64| ulps * f64::EPSILON * scale.max(f64::MIN_POSITIVE);
            if !set.bounds.padded(tolerance(p.abs().max_element())).contains(p) {
                return false;
            }
            let local = set.to_local.point(p);
            // A zero-length probe enters exactly the (padded) boxes that hold the point.
            let probe = Ray64 { origin: local, direction: DVec3::ONE, tmin: 0.0, tmax: 0.0 };
            let mut found = false;
            set.triangles.bvh().traverse(&probe, &mut 0.0, |prim, _| {
                if let Some(&(c, r)) = set.triangles.spheres.get(prim as usize) {
                    let scale = local.abs().max_element().max(c.abs().max_element()).max(r);
                    found = ((local - c).length() - r).abs() <= tolerance(scale);
                    return !found;
                }
                let [a, b, c] = set.triangles.triangle(prim as usize);
                let scale = [local, a, b, c].iter().map(|v| v.abs().max_element()).fold(0.0, f64::max);
                found = (closest_point_on_triangle(local, a, b, c) - local).length() <= tolerance(scale);
                !found
            });
            found
        })
    }

    /// Traces every ray (and its mask) on all cores; `out[i]` gets ray i's hit.
    pub fn trace_all(
        &self,
        rays: impl Fn(usize) -> (Ray64, u8) + Sync,
        filter: Filter,
        any: bool,
        out: &mut [Option<ReferenceHit>],
    ) {
        parallel::install(|| {
            out.par_iter_mut().enumerate().with_min_len(256).for_each(|(i, slot)| {
                let (ray, mask) = rays(i);
                *slot = self.trace(&ray, mask, filter, any)
            })
        });
    }

    pub fn set(&self, instance: u32) -> &PlacedSet<'a> {
        &self.sets[instance as usize]
    }
}

/// `ReferenceTracer::for_each_hit` on a sphere set: each sphere the ray's line meets within
/// [tmin, tmax] is met where it enters (front) and where it leaves (back), the nearer first; a ray
/// from inside meets only where it leaves, a tangent one both at one t. Spheres are opaque and
/// have no side to cull (the fast tier's intersection shader reports them alike).
fn for_each_sphere_hit(
    set: &PlacedSet,
    instance: u32,
    ray: &Ray64,
    tmax: &mut f64,
    found: &mut impl FnMut(ReferenceHit, bool, &mut f64) -> bool,
) -> bool {
    let local = Ray64 { tmax: *tmax, ..ray.transformed(&set.to_local) };
    let mut go_on = true;
    set.triangles.bvh().traverse(&local, tmax, |prim, tmax| {
        let (center, radius) = set.triangles.spheres[prim as usize];
        let Some((near, far)) = sphere_roots(&local, center, radius) else { return true };
        for (t, front) in [(near, true), (far, false)] {
            if t >= local.tmin && t <= *tmax {
                let hit = ReferenceHit { t, u: f64::NAN, v: f64::NAN, instance, prim };
                go_on = found(hit, front, tmax);
                if !go_on {
                    return false;
                }
            }
        }
        true
    });
    go_on
}

/// The point of sphere `prim` of `set` nearest to `p` (scene frame), for a set placed by a
/// similarity (the tracer's `check_spheres_round`): its centre and radius in the scene's frame;
/// from the centre itself, the point along +x.
fn closest_point_on_sphere(set: &PlacedSet, prim: usize, p: DVec3) -> DVec3 {
    let (center, radius) = set.triangles.spheres[prim];
    let center = set.to_scene.point(center);
    let radius = radius * set.to_scene.linear.x_axis.length();
    let away = p - center;
    let length = away.length();
    if length == 0.0 || !length.is_finite() {
        let scale = length_scale(away.abs().max_element());
        let scaled = away * scale;
        if scaled.length() > 0.0 {
            return center + scaled * (radius / scaled.length());
        }
        return center + DVec3::X * radius;
    }
    center + away * (radius / length)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::precision::watertight;
    use glam::DMat3;

    /// The smallest scene distance squared from `p` (local) to points of `b` sampled on a grid
    /// over it, its faces included: an upper bound of the true minimum.
    fn sampled_min(a: DMat3, b: &Aabb, p: DVec3) -> f64 {
        let steps = 24;
        let mut best = f64::INFINITY;
        for i in 0..=steps {
            for j in 0..=steps {
                for k in 0..=steps {
                    let t = DVec3::new(i as f64, j as f64, k as f64) / steps as f64;
                    let x = b.min + (b.max - b.min) * t;
                    best = best.min((a * (x - p)).length_squared());
                }
            }
        }
        best
    }

    #[test]
    fn gap_weights_bound_scene_distances_and_are_tight_for_scaled_rotations() {
        let rotation = DMat3::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.7);
        let shear = DMat3::from_cols(DVec3::X, DVec3::new(0.9, 1.0, 0.0), DVec3::Z);
        let maps = [
            DMat3::IDENTITY,
            DMat3::from_diagonal(DVec3::new(-1.5, 1.0, 0.5)),
            rotation * DMat3::from_diagonal(DVec3::new(3.0, 0.2, 1.0)),
            rotation * shear,
        ];
        let b = Aabb { min: DVec3::new(0.0, 0.0, 0.0), max: DVec3::new(1.0, 2.0, 0.5) };
        for (k, &a) in maps.iter().enumerate() {
            let to_scene = Affine { linear: a, offset: DVec3::new(1e4, -2.0, 0.25) };
            let to_local = Affine { linear: a.inverse(), offset: DVec3::ZERO };
            let w = DVec3::from_array(gap_weights(&to_scene, &to_local));
            for p in [DVec3::new(3.0, 1.0, 0.2), DVec3::new(-1.0, -2.0, 2.0), DVec3::new(0.5, 5.0, -0.7)] {
                let bound = weighted_gap(&b, p, w, 1.0);
                let sampled = sampled_min(a, &b, p);
                assert!(bound <= sampled, "map {k}, {p}: {bound} > {sampled}");
                if k < 3 {
                    // A scaled rotation's nearest point of the box is p clamped to it: the bound is
                    // its distance, to within the margin.
                    let nearest = (a * (p.clamp(b.min, b.max) - p)).length_squared();
                    assert!(bound <= nearest && bound >= nearest * (1.0 - 1e-6), "map {k}, {p}: {bound}, {nearest}");
                }
            }
        }
    }

    /// A grid of `n`×`n` unit squares (two triangles each) in the plane z = 0.
    fn grid(n: u32) -> TriangleSet {
        let (vertices, faces) = crate::geometry::winding::grid_sheet(n, 1.0, |_, _| 0.0);
        let count = faces.len() as u32;
        TriangleSet::new(vertices, faces, vec![0, count])
    }

    #[test]
    fn every_grid_vertex_and_edge_is_hit_exactly_once() {
        let set = grid(8);
        let bounds = set.bounds;
        let tracer = ReferenceTracer::new(vec![PlacedSet {
            triangles: &set,
            to_local: Affine::IDENTITY,
            custom_index: 0,
            mask: 0xFF,
            bounds,
            flip_facing: false,
            cull_disable: false,
            opacity: None,
            to_scene: Affine::IDENTITY,
        }]);
        let brute = |ray: &Ray64| -> Vec<usize> {
            let sheared = ShearedRay::new(*ray);
            (0..set.faces.len())
                .filter(|&p| {
                    let [a, b, c] = set.triangle(p);
                    watertight(&sheared, a, b, c).is_some()
                })
                .collect()
        };
        for k in 0..=16 {
            for j in 0..=16 {
                let target = DVec3::new(k as f64 * 0.5, j as f64 * 0.5, 0.0);
                let origin = DVec3::new(3.3, -2.1, 5.0);
                let ray = Ray64 { origin, direction: target - origin, tmin: 0.0, tmax: f64::INFINITY };
                // Interior vertices, edges and faces: exactly one triangle; the border may miss.
                let interior = (1..16).contains(&k) && (1..16).contains(&j);
                let count = brute(&ray).len();
                if interior {
                    assert_eq!(count, 1, "target {target}");
                }
                let hit = tracer.trace(&ray, 0xFF, Filter::sides(Cull::None), false);
                assert_eq!(hit.is_some(), count == 1);
                if let Some(hit) = hit {
                    assert_eq!(vec![hit.prim as usize], brute(&ray));
                    assert!((hit.t - 1.0).abs() < 1e-15);
                }
            }
        }
    }

    #[test]
    fn parts_split_and_join_triangle_indices() {
        let set = TriangleSet::new(vec![DVec3::ZERO; 3], vec![[0, 1, 2]; 6], vec![0, 2, 2, 6]);
        assert_eq!(set.split(0), (0, 0));
        assert_eq!(set.split(1), (0, 1));
        assert_eq!(set.split(2), (2, 0)); // part 1 is empty
        assert_eq!(set.split(5), (2, 3));
        assert_eq!(set.global(2, 3), 5);
    }

    #[test]
    fn the_nearer_of_two_instances_wins() {
        let set = grid(2);
        let lifted = Affine { offset: DVec3::new(0.0, 0.0, -1.0), ..Affine::IDENTITY };
        let place = |to_local: Affine| PlacedSet {
            triangles: &set,
            to_local,
            custom_index: 0,
            mask: 0xFF,
            bounds: Aabb::of_points(set.vertices.iter().copied()).transformed(&to_local.inverse().unwrap()),
            flip_facing: false,
            cull_disable: false,
            opacity: None,
            to_scene: to_local.inverse().unwrap(),
        };
        let tracer = ReferenceTracer::new(vec![place(Affine::IDENTITY), place(lifted)]);
        let ray = Ray64 {
            origin: DVec3::new(0.3, 0.6, 5.0),
            direction: DVec3::new(0.0, 0.0, -1.0),
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        let hit = tracer.trace(&ray, 0xFF, Filter::sides(Cull::None), false).unwrap();
        assert_eq!((hit.instance, hit.t), (1, 4.0));
        assert!(tracer.trace(&Ray64 { tmax: 3.5, ..ray }, 0xFF, Filter::sides(Cull::None), true).is_none());
        // The grid faces +z and the ray comes from above: culling front faces leaves nothing.
        assert!(tracer.trace(&ray, 0xFF, Filter::sides(Cull::Front), false).is_none());
        assert_eq!(tracer.trace(&ray, 0xFF, Filter::sides(Cull::Back), false).unwrap().instance, 1);
    }

    #[test]
    fn closest_points_match_brute_force_under_stretching_placements() {
        let set = grid(6);
        // Stretched along x, turned about z, mirrored in y, moved: distances are the world's.
        let to_scene = Affine {
            linear: glam::DMat3::from_cols(
                DVec3::new(0.0, 3.0, 0.0),
                DVec3::new(0.5, 0.0, 0.0),
                DVec3::new(0.0, 0.0, -1.0),
            ),
            offset: DVec3::new(1.0, -2.0, 0.5),
        };
        let to_local = to_scene.inverse().unwrap();
        let tracer = ReferenceTracer::new(vec![PlacedSet {
            triangles: &set,
            to_local,
            custom_index: 0,
            mask: 0xFF,
            bounds: set.bounds.transformed(&to_scene),
            flip_facing: false,
            cull_disable: false,
            opacity: None,
            to_scene,
        }]);
        let mut seed = 7u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 12.0 - 4.0
        };
        for _ in 0..200 {
            let p = DVec3::new(next(), next(), next());
            let brute = (0..set.faces.len())
                .map(|t| {
                    let [a, b, c] = set.triangle(t).map(|v| to_scene.point(v));
                    (closest_point_on_triangle(p, a, b, c) - p).length()
                })
                .fold(f64::INFINITY, f64::min);
            let hit = tracer.closest_point(p, 0xFF, f64::INFINITY).unwrap();
            assert_eq!(hit.distance, brute, "at {p}");
            assert!(tracer.closest_point(p, 0xFF, 0.5 * brute).is_none() || brute == 0.0);
        }
    }
}

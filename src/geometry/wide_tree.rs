//! A four-wide tree of f32 boxes over a `Bvh`'s items, for the host's nearest-item searches
//! (closest points, distances) and its f64 tiers' rays: a node's four children bounded (or
//! entered) side by side, one vector of each bound, where the binary tree tests two in f64, one at
//! a time, each behind a branch; a leaf's items likewise, each triangle also bounded by its
//! planes for nearest searches. Built from the binary tree (its leaves kept, its inner levels
//! collapsed two into one), on a mesh's first such query.
//!
//! The f32 tests must keep every item the f64 ones keep (the answers stay the binary tree's, bit
//! for bit): every box is rounded outward; a nearest search's gaps are shrunk past the point's
//! rounding to f32 and the arithmetic's, and their sum past its own rounding; a ray's boxes are
//! grown past its origin's and direction's rounding, its entries and exits moved out past theirs. Lengths are scaled by a power of two (exactly) that brings the
//! tree's extent near 1, so that a tiny mesh's squared gaps do not underflow f32 (which would
//! leave nothing pruned) nor a large one's overflow; a tree beyond `EXTENTS` (or a point far
//! beyond its tree) is left to the f64 search.

use glam::DVec3;
use rayon::prelude::*;

use super::bvh::Bvh;
use super::parallel;
use super::precision::{round_outward, Ray64};

/// The extents (largest coordinate's magnitude) of trees that are built: their scale and its
/// square stay within f32's and f64's ranges.
const EXTENTS: (f64, f64) = (7.523_163_845_262_64e-37, 1.329_227_995_784_916e36); // 2^-120, 2^120

/// How far (in scaled lengths, the tree's extent being about 1) a searched point may lie: its
/// squared gaps and their weighted sums stay finite in f32.
const POINT_LIMIT: f64 = 1.152_921_504_606_847e18; // 2^60

/// A slot that holds nothing.
const EMPTY: u32 = u32::MAX;

/// A slot's bit that says it holds a leaf (its index among `leaves`), not a node.
const LEAF: u32 = 1 << 31;

/// Entries the search's stack holds: three a level at most (a node pushes up to four of which it
/// is one popped), over at most the binary tree's depth, with room to spare.
const STACK: usize = 192;

/// Four boxes, each bound as a vector over the four (an empty slot's box holds nothing).
#[derive(Clone, Copy)]
#[repr(C, align(16))]
struct Boxes4 {
    min: [[f32; 4]; 3],
    max: [[f32; 4]; 3],
}

impl Boxes4 {
    const EMPTY: Boxes4 = Boxes4 { min: [[f32::INFINITY; 4]; 3], max: [[f32::NEG_INFINITY; 4]; 3] };

    fn set(&mut self, slot: usize, min: [f32; 3], max: [f32; 3]) {
        for axis in 0..3 {
            self.min[axis][slot] = min[axis];
            self.max[axis][slot] = max[axis];
        }
    }
}

struct WideNode {
    boxes: Boxes4,
    /// Each child: a node's index, `LEAF | leaf index`, or `EMPTY`.
    slots: [u32; 4],
}

/// Four triangles, each held between two planes parallel to it and behind three planes through
/// its edges square to it (as vectors over the four). A point's distances past them bound its
/// distance to the triangle from below, tightly: the face's gap and an edge's are square to each
/// other, and each is the distance's own where its nearest point lies on the face or that edge
/// (a box bounds a tilted triangle by far less). A slot with no triangle (a sphere, a triangle
/// with no face) has zero planes: its bound is 0.
#[derive(Clone, Copy)]
#[repr(C, align(16))]
struct Planes4 {
    normal: [[f32; 4]; 3],
    /// `normal · x` over the triangle lies in [low, high].
    low: [f32; 4],
    high: [f32; 4],
    /// Edge e's outward normal (square to `normal`), and `edge · x` at most `reach` over the
    /// triangle.
    edge: [[[f32; 4]; 3]; 3],
    reach: [[f32; 4]; 3],
}

impl Planes4 {
    const ZERO: Planes4 = Planes4 {
        normal: [[0.0; 4]; 3],
        low: [0.0; 4],
        high: [0.0; 4],
        edge: [[[0.0; 4]; 3]; 3],
        reach: [[0.0; 4]; 3],
    };

    /// Slot `slot`'s planes.
    fn set(&mut self, slot: usize, planes: &TrianglePlanes) {
        for axis in 0..3 {
            self.normal[axis][slot] = planes.normal[axis];
            for e in 0..3 {
                self.edge[e][axis][slot] = planes.edge[e][axis];
            }
        }
        (self.low[slot], self.high[slot]) = (planes.low, planes.high);
        for e in 0..3 {
            self.reach[e][slot] = planes.reach[e];
        }
    }
}

/// One triangle's planes (`Planes4`), in f32: the normals rounded, each plane's offset then
/// taken over the triangle's corners in f64 and rounded outward, so that the triangle lies
/// between them whatever the normals' rounding.
struct TrianglePlanes {
    normal: [f32; 3],
    low: f32,
    high: f32,
    edge: [[f32; 3]; 3],
    reach: [f32; 3],
}

impl TrianglePlanes {
    /// Triangle `t`'s planes; None where it has no face, or its planes come out of f32's range.
    fn about(t: [DVec3; 3]) -> Option<TrianglePlanes> {
        let unit = |v: DVec3| {
            let v = v.normalize_or_zero();
            (v != DVec3::ZERO && v.is_finite()).then(|| v.to_array().map(|x| x as f32))
        };
        let normal = unit((t[1] - t[0]).cross(t[2] - t[0]))?;
        let n = DVec3::from_array(normal.map(f64::from));
        // The offsets' own rounding (relative to the terms of each dot product, below 2^-50).
        let pad = |m: DVec3| t.iter().map(|v| (m.abs() * v.abs()).element_sum()).fold(0.0, f64::max) * 2e-15;
        let dots = t.map(|v| n.dot(v));
        let (low, high) = (
            dots.iter().copied().fold(f64::INFINITY, f64::min),
            dots.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        );
        let mut planes = TrianglePlanes {
            normal,
            low: round_outward(low - pad(n), true),
            high: round_outward(high + pad(n), false),
            edge: [[0.0; 3]; 3],
            reach: [0.0; 3],
        };
        for e in 0..3 {
            let (a, b, opposite) = (t[e], t[(e + 1) % 3], t[(e + 2) % 3]);
            let mut m = n.cross(b - a);
            if m.dot(opposite - a) > 0.0 {
                m = -m;
            }
            let Some(edge) = unit(m) else { continue };
            let m = DVec3::from_array(edge.map(f64::from));
            planes.edge[e] = edge;
            planes.reach[e] =
                round_outward(t.iter().map(|v| m.dot(*v)).fold(f64::NEG_INFINITY, f64::max) + pad(m), false);
        }
        [planes.low, planes.high].iter().chain(&planes.reach).all(|x| x.is_finite()).then_some(planes)
    }
}

/// One leaf of the binary tree: its items' boxes and planes, and where its items lie in `items`.
struct WideLeaf {
    boxes: Boxes4,
    planes: Planes4,
    first: u32,
    count: u32,
}

pub struct WideTree {
    nodes: Vec<WideNode>,
    leaves: Vec<WideLeaf>,
    /// The items in leaf order (`Bvh::items`).
    items: Vec<u32>,
    /// The root's slot.
    root: u32,
    /// The power of two lengths are scaled by (the boxes and planes are stored scaled).
    scale: f64,
    /// The largest sum of a box corner's coordinates' magnitudes, scaled: what a plane's offset
    /// reaches.
    magnitude: f64,
}

/// A point to search from, as the f32 bounds take it: the point rounded to f32, what each of its
/// gaps is shrunk by (its rounding, and the gap's own), and the weights of the squared gaps.
pub struct NearestQuery {
    point: [f32; 3],
    slack: [f32; 3],
    weights: [f32; 3],
    /// What a distance past a plane is shrunk by (its computation's rounding in f32).
    plane_slack: f32,
    /// The least weight: the weighted squared distance is at least it times the squared.
    least_weight: f32,
}

/// What a gap is shrunk by, relatively: past its subtraction's rounding (2^-24) with room.
const GAP_SHRINK: f32 = 1.0 - 1.0 / (1u32 << 21) as f32;

/// What a sum of squared distances past planes is shrunk by: the planes' normals are unit and
/// square to each other to within f32's rounding (a few 2^-24), and the sum's own rounding.
const PLANE_SHRINK: f32 = 1.0 - 1.0 / (1u32 << 18) as f32;

/// What a weighted sum of squares is shrunk by: past the rounding of a square, a product and
/// two sums (2^-24 each) with room.
const SUM_SHRINK: f32 = 1.0 - 1.0 / (1u32 << 20) as f32;

impl NearestQuery {
    /// The query from `local` (the point in the tree's frame) with squared gaps weighted by
    /// `weights` (each at most what bounds the f64 search's, `reference::weighted_gap`); None
    /// where the point lies beyond what the f32 bounds take (the f64 search then runs).
    pub fn new(tree: &WideTree, local: DVec3, weights: DVec3) -> Option<NearestQuery> {
        let local = local * tree.scale;
        let within = local.abs().max_element() < POINT_LIMIT; // (false for NaN)
        if !within || !weights.is_finite() {
            return None;
        }
        let point = local.to_array().map(|x| x as f32);
        // |x - f32(x)| ≤ 2^-24 |x|; 2^-22 |x| covers it, and the least normal f32 covers a
        // subnormal's rounding.
        let slack = local.to_array().map(|x| (x.abs() as f32) * (1.0 / (1u32 << 22) as f32) + f32::MIN_POSITIVE);
        let weights = weights.to_array().map(|w| round_outward(w, true).max(0.0));
        // A plane's distance `n · p - offset` in f32: the point's rounding (2^-24 of each term),
        // the dot product's and the difference's (2^-24 of the sum of the terms' magnitudes,
        // a few times); 2^-20 of them all covers it.
        let plane_slack = ((local.abs().element_sum() + tree.magnitude) * (1.0 / f64::from(1u32 << 20))) as f32;
        let least_weight = weights[0].min(weights[1]).min(weights[2]);
        Some(NearestQuery { point, slack, weights, plane_slack, least_weight })
    }

    /// Lower bounds of the weighted squared distances from the point to each of four triangles
    /// by their planes (`Planes4`).
    #[inline(always)]
    fn plane_bounds(&self, planes: &Planes4) -> [f32; 4] {
        let [x, y, z] = self.point;
        let mut out = [0f32; 4];
        for k in 0..4 {
            let along = |n: &[[f32; 4]; 3]| n[0][k] * x + n[1][k] * y + n[2][k] * z;
            let t = along(&planes.normal);
            let face = (t - planes.high[k]).max(planes.low[k] - t).max(0.0);
            let mut edge = 0f32;
            for e in 0..3 {
                edge = edge.max(along(&planes.edge[e]) - planes.reach[e][k]);
            }
            let (face, edge) = ((face - self.plane_slack).max(0.0), (edge - self.plane_slack).max(0.0));
            out[k] = (face * face + edge * edge) * PLANE_SHRINK * self.least_weight;
        }
        out
    }

    /// Lower bounds of the weighted squared distances from the point to each of four boxes (an
    /// empty box's is infinite).
    #[inline(always)]
    fn bounds(&self, boxes: &Boxes4) -> [f32; 4] {
        let mut sum = [0f32; 4];
        for axis in 0..3 {
            let p = self.point[axis];
            for (k, sum) in sum.iter_mut().enumerate() {
                let gap = (boxes.min[axis][k] - p).max(p - boxes.max[axis][k]).max(0.0);
                let lower = (gap * GAP_SHRINK - self.slack[axis]).max(0.0);
                *sum += lower * lower * self.weights[axis];
            }
        }
        sum.map(|s| s * SUM_SHRINK)
    }
}

/// A ray to trace through the tree, as its f32 slab tests take it: the origin and the
/// direction rounded to f32 (scaled as the tree), the direction's inverse, what each box is grown
/// by on each axis (the origin's rounding, and the direction's over the farthest the ray can
/// reach within the tree), and the ray's interval.
pub struct RayQuery {
    origin: [f32; 3],
    inverse: [f32; 3],
    grow: [f32; 3],
    tmin: f32,
    tmax: f32,
}

/// The magnitudes a traced ray's direction's components lie within, scaled as the tree (2^-120 to
/// 2^120: they and their inverses stay normal f32s).
const DIRECTION_RANGE: (f64, f64) = EXTENTS;

/// What an entry or exit distance is moved out by, relatively: past the rounding of its
/// difference and product (2^-24 each) with room.
const SLAB_GROW: f32 = 1.0 / (1u32 << 18) as f32;

impl RayQuery {
    /// The query of `ray` (in the tree's frame); None where its origin lies far beyond the
    /// tree, a component of its direction is 0 or out of f32's comfortable range, or its
    /// interval is not a finite start and a later end (the f64 traversal then runs).
    pub fn new(tree: &WideTree, ray: &Ray64) -> Option<RayQuery> {
        // Scaling origin and direction alike keeps every point's t.
        let (o, d) = (ray.origin * tree.scale, ray.direction * tree.scale);
        let within = o.abs().max_element() < POINT_LIMIT; // (false for NaN)
                                                          // Each component and its inverse well within f32's normal range.
        let steep = d.abs().min_element() > DIRECTION_RANGE.0 && d.abs().max_element() < DIRECTION_RANGE.1;
        if !(within && steep && ray.tmin >= 0.0 && ray.tmin.is_finite() && ray.tmax >= ray.tmin) {
            return None;
        }
        // Within the tree's box every coordinate is at most `magnitude`: no t past this reaches
        // it.
        let farthest = ((tree.magnitude + o.abs().max_element()) / d.abs().max_element()) * (1.0 + 1e-9);
        let origin = o.to_array().map(|x| x as f32);
        let direction = d.to_array().map(|x| x as f32);
        let grow = std::array::from_fn(|axis| {
            let moved =
                (o[axis] - f64::from(origin[axis])).abs() + farthest * (d[axis] - f64::from(direction[axis])).abs();
            // And the rounding of `bound ∓ grow` (2^-24 of the coordinates' magnitudes), whose
            // difference with the origin may be far smaller than either: 2^-21 of them.
            let rounding = (tree.magnitude + o.abs().max_element()) * (1.0 / f64::from(1u32 << 21));
            up(moved * (1.0 + 1e-6) + rounding) + f32::MIN_POSITIVE
        });
        let tmin = round_outward(ray.tmin, true).max(0.0);
        let tmax = up(ray.tmax.min(farthest));
        Some(RayQuery { origin, inverse: direction.map(|x| 1.0 / x), grow, tmin, tmax })
    }

    /// Where the ray enters each of four boxes (grown by `grow`) before `reach` (infinite
    /// where it does not): at most where it enters the box itself.
    #[inline(always)]
    fn entries(&self, boxes: &Boxes4, reach: f32) -> [f32; 4] {
        let mut near = [self.tmin; 4];
        let mut far = [reach.min(self.tmax); 4];
        for axis in 0..3 {
            let (o, inverse, grow) = (self.origin[axis], self.inverse[axis], self.grow[axis]);
            for k in 0..4 {
                let a = (boxes.min[axis][k] - grow - o) * inverse;
                let b = (boxes.max[axis][k] + grow - o) * inverse;
                let (enter, exit) = (a.min(b), a.max(b));
                near[k] = near[k].max(enter - enter.abs() * SLAB_GROW);
                far[k] = far[k].min(exit + exit.abs() * SLAB_GROW);
            }
        }
        std::array::from_fn(|k| if near[k] <= far[k] { near[k] } else { f32::INFINITY })
    }
}

/// The f32 at or above `x` (infinite above f32's range).
#[inline]
fn up(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) < x {
        f.next_up()
    } else {
        f
    }
}

impl WideTree {
    /// The tree over `bvh`'s leaves and items, `triangle(item)` each item's corners (None: not
    /// a triangle); None where it has none, or its extent lies beyond `EXTENTS`.
    pub fn build(bvh: &Bvh, triangle: &(dyn Fn(usize) -> Option<[DVec3; 3]> + Sync)) -> Option<WideTree> {
        let root = &bvh.nodes().first()?.bounds;
        let extent = root.min.abs().max(root.max.abs()).max_element();
        if !(extent >= EXTENTS.0 && extent <= EXTENTS.1) {
            return None;
        }
        // 2^-e with the extent in [2^(e-1), 2^e): the scaled extent in [1/2, 1).
        let scale = 2f64.powi(-(extent.log2().floor() as i32 + 1));
        let magnitude = (root.min.abs().max(root.max.abs()) * scale).element_sum();
        let items = bvh.items().to_vec();
        let leaves = bvh.nodes().iter().filter(|n| n.count > 0).count();
        let (nodes, leaves) = (Vec::with_capacity(leaves / 2 + 1), Vec::with_capacity(leaves));
        let mut tree = WideTree { nodes, leaves, items, root: EMPTY, scale, magnitude };
        tree.root = tree.collapse(bvh, 0);
        // The leaves' planes, on all cores.
        let items = &tree.items;
        parallel::install(|| {
            tree.leaves.par_iter_mut().with_min_len(256).for_each(|leaf| {
                for k in 0..leaf.count as usize {
                    let item = items[leaf.first as usize + k] as usize;
                    if let Some(planes) = triangle(item).and_then(|t| TrianglePlanes::about(t.map(|v| v * scale))) {
                        leaf.planes.set(k, &planes);
                    }
                }
            })
        });
        Some(tree)
    }

    /// The slot of binary node `index`: a leaf of its items, or a wide node over up to four of
    /// the binary nodes below it (the largest opened first).
    fn collapse(&mut self, bvh: &Bvh, index: usize) -> u32 {
        let nodes = bvh.nodes();
        let node = &nodes[index];
        if node.count > 0 {
            let mut boxes = Boxes4::EMPTY;
            for k in 0..node.count as usize {
                let (min, max) = bvh.item_box(node.first as usize + k);
                boxes.set(k, self.scaled(min, true), self.scaled(max, false));
            }
            // (Its planes are made after, on all cores.)
            self.leaves.push(WideLeaf { boxes, planes: Planes4::ZERO, first: node.first, count: node.count });
            return LEAF | (self.leaves.len() - 1) as u32;
        }
        // (Up to four children in place: a node's list on the heap cost a tenth of the build.)
        let (mut children, mut count) = ([node.first as usize, node.first as usize + 1, 0, 0], 2);
        while count < 4 {
            let area = |i: usize| {
                let e = nodes[i].bounds.extent();
                e.x * e.y + e.y * e.z + e.z * e.x
            };
            let inner = children[..count].iter().enumerate().filter(|(_, &c)| nodes[c].count == 0);
            let Some((k, _)) = inner.max_by(|a, b| area(*a.1).total_cmp(&area(*b.1))) else { break };
            // As `Vec::swap_remove` then a push of the opened node's two children.
            let opened = children[k];
            children[k] = children[count - 1];
            (children[count - 1], children[count]) = (nodes[opened].first as usize, nodes[opened].first as usize + 1);
            count += 1;
        }
        let at = self.nodes.len();
        self.nodes.push(WideNode { boxes: Boxes4::EMPTY, slots: [EMPTY; 4] });
        for (k, &child) in children[..count].iter().enumerate() {
            let slot = self.collapse(bvh, child);
            let b = &nodes[child].bounds;
            let min = (b.min * self.scale).to_array().map(|x| round_outward(x, true));
            let max = (b.max * self.scale).to_array().map(|x| round_outward(x, false));
            let node = &mut self.nodes[at];
            node.boxes.set(k, min, max);
            node.slots[k] = slot;
        }
        at as u32
    }

    /// An f32 corner scaled, rounded outward (below for a lower corner) where the product is
    /// not exact (a tiny coordinate scaled into f32's subnormals).
    fn scaled(&self, corner: [f32; 3], lower: bool) -> [f32; 3] {
        corner.map(|x| round_outward(f64::from(x) * self.scale, lower))
    }

    /// `Bvh::nearest` through the wide tree: calls `visit` with every item whose box may hold
    /// something at `*best` or nearer (weighted squared distances, `query`'s), nearer boxes first;
    /// `visit` may lower `*best`.
    pub fn nearest(&self, query: &NearestQuery, best: &mut f64, mut visit: impl FnMut(u32, &mut f64)) {
        // The search's squared lengths, scaled as the tree's (exactly: a power of two).
        let squared_scale = self.scale * self.scale;
        let mut reach = up(*best * squared_scale);
        let mut stack = [(0u32, 0f32); STACK];
        stack[0] = (self.root, 0.0);
        let mut n = 1;
        while n > 0 {
            n -= 1;
            let (slot, bound) = stack[n];
            if bound > reach {
                continue;
            }
            if slot & LEAF != 0 {
                let leaf = &self.leaves[(slot & !LEAF) as usize];
                let (boxes, planes) = (query.bounds(&leaf.boxes), query.plane_bounds(&leaf.planes));
                for k in 0..leaf.count as usize {
                    if boxes[k].max(planes[k]) <= reach {
                        visit(self.items[(leaf.first as usize) + k], best);
                        reach = up(*best * squared_scale);
                    }
                }
                continue;
            }
            let node = &self.nodes[slot as usize];
            n = push_nearest_last(&mut stack, n, node, &query.bounds(&node.boxes), reach);
        }
    }
}

impl WideTree {
    /// `Bvh::traverse` through the wide tree: calls `visit` with every item whose box the ray
    /// may enter before `*tmax` (each box tested in f32, grown past every rounding: a superset
    /// of the f64 traversal's), nearer boxes first; `visit` may lower `*tmax` (a closer hit) or
    /// return false to stop.
    pub fn traverse(&self, query: &RayQuery, tmax: &mut f64, mut visit: impl FnMut(u32, &mut f64) -> bool) {
        // Finite (no t beyond the tree's box matters), so that a box missed (entered at
        // infinity) is never within reach.
        let mut reach = up(*tmax).min(query.tmax);
        let mut stack = [(0u32, 0f32); STACK];
        stack[0] = (self.root, query.tmin);
        let mut n = 1;
        while n > 0 {
            n -= 1;
            let (slot, entry) = stack[n];
            if entry > reach {
                continue;
            }
            if slot & LEAF != 0 {
                let leaf = &self.leaves[(slot & !LEAF) as usize];
                let entries = query.entries(&leaf.boxes, reach);
                for (k, &entry) in entries.iter().enumerate().take(leaf.count as usize) {
                    if entry <= reach {
                        if !visit(self.items[(leaf.first as usize) + k], tmax) {
                            return;
                        }
                        reach = up(*tmax).min(query.tmax);
                    }
                }
                continue;
            }
            let node = &self.nodes[slot as usize];
            n = push_nearest_last(&mut stack, n, node, &query.entries(&node.boxes, reach), reach);
        }
    }
}

/// Pushes the children of `node` whose `keys` (bounds, or entry distances) are within `reach`
/// onto the first `n` entries of `stack`, farthest first (so that the nearest is popped first);
/// returns the new length.
#[inline(always)]
fn push_nearest_last(
    stack: &mut [(u32, f32); STACK],
    mut n: usize,
    node: &WideNode,
    keys: &[f32; 4],
    reach: f32,
) -> usize {
    let start = n;
    for (&child, &key) in node.slots.iter().zip(keys) {
        if child != EMPTY && key <= reach {
            let mut at = n;
            while at > start && stack[at - 1].1 < key {
                stack[at] = stack[at - 1];
                at -= 1;
            }
            stack[at] = (child, key);
            n += 1;
        }
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::precision::{closest_point_on_triangle, Aabb};

    /// A fixed stream of numbers in [0, 1) (SplitMix64).
    struct Stream(u64);

    impl Stream {
        fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }

        fn vector(&mut self, scale: f64) -> DVec3 {
            DVec3::new(self.next() - 0.5, self.next() - 0.5, self.next() - 0.5) * scale
        }
    }

    /// Triangles of every shape about `centre`: plain, slivers, needles, collinear and
    /// coincident corners, at the size `size`.
    fn triangles(stream: &mut Stream, count: usize, centre: DVec3, size: f64) -> Vec<[DVec3; 3]> {
        (0..count)
            .map(|i| {
                let a = centre + stream.vector(size * 20.0);
                let (b, c) = (a + stream.vector(size), a + stream.vector(size));
                match i % 6 {
                    0 => [a, b, a + (b - a) * 0.37],                               // collinear
                    1 => [a, a, b],                                                // two corners coincide
                    2 => [a, b, b + (b - a) * 1e-9 + stream.vector(size * 1e-12)], // a needle
                    3 => [a, b, (a + b) * 0.5 + stream.vector(size * 1e-10)],      // a sliver
                    _ => [a, b, c],
                }
            })
            .collect()
    }

    fn tree_over(triangles: &[[DVec3; 3]]) -> (Bvh, WideTree) {
        let boxes: Vec<Aabb> = triangles.iter().map(|t| Aabb::of_points(t.iter().copied())).collect();
        let bvh = Bvh::build(&boxes);
        let tree = WideTree::build(&bvh, &|i| Some(triangles[i])).expect("a tree within f32's range");
        (bvh, tree)
    }

    /// Every bound the tree takes (a box's, a triangle's planes') is at most the squared distance
    /// the f64 search measures to the triangle, weighted, for points near and far, on the
    /// triangle, on its edges and at its corners; at the origin and 1e7 from it; for triangles
    /// of every shape.
    #[test]
    fn bounds_never_exceed_the_measured_distance() {
        let mut stream = Stream(7);
        let places = [
            (DVec3::ZERO, 1.0),
            (DVec3::new(1e7, -3e6, 2.5e6), 1.0),
            (DVec3::splat(0.25), 1e-6),
            (DVec3::splat(3e-30), 1e-31),
            (DVec3::new(-2e30, 1e30, 0.0), 1e27),
        ];
        for (centre, size) in places {
            let soup = triangles(&mut stream, 60, centre, size);
            let (_, tree) = tree_over(&soup);
            for weights in [DVec3::ONE, DVec3::new(0.25, 1.0, 4.0)] {
                for leaf in &tree.leaves {
                    for k in 0..leaf.count as usize {
                        let t = soup[tree.items[leaf.first as usize + k] as usize];
                        let probes = [
                            t[0],
                            (t[0] + t[1]) * 0.5,
                            (t[0] + t[1] + t[2]) / 3.0,
                            t[2] + stream.vector(size * 1e-9),
                            t[1] + stream.vector(size),
                            centre + stream.vector(size * 40.0),
                        ];
                        for p in probes {
                            let q = NearestQuery::new(&tree, p, weights).unwrap();
                            let d = closest_point_on_triangle(p, t[0], t[1], t[2]) - p;
                            let measured = (d * d).dot(weights) * tree.scale * tree.scale;
                            let (by_box, by_planes) = (q.bounds(&leaf.boxes)[k], q.plane_bounds(&leaf.planes)[k]);
                            assert!(f64::from(by_box) <= measured, "box {by_box} > {measured}: {t:?} from {p}");
                            assert!(
                                f64::from(by_planes) <= measured,
                                "planes {by_planes} > {measured}: {t:?} from {p}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// The nearest triangle through the tree (its boxes and planes pruning) equals a scan of
    /// every triangle, ties to the lower index, from points near the triangles and far; the
    /// tree prunes as much at 1e-30 and 1e30 as at 1.
    #[test]
    fn nearest_finds_what_a_scan_of_every_triangle_finds() {
        let mut stream = Stream(11);
        for (centre, size) in
            [(DVec3::ZERO, 1.0), (DVec3::new(-2e6, 7e6, 1e5), 1.0), (DVec3::ZERO, 1e-30), (DVec3::ZERO, 1e30)]
        {
            let soup = triangles(&mut stream, 3000, centre, size);
            let (_, tree) = tree_over(&soup);
            let mut pruned = 0;
            for k in 0..300 {
                let p = if k % 2 == 0 {
                    soup[k][0] + stream.vector(0.5 * size)
                } else {
                    centre + stream.vector(60.0 * size)
                };
                let distance = |i: u32| {
                    let t = soup[i as usize];
                    (closest_point_on_triangle(p, t[0], t[1], t[2]) - p).length_squared()
                };
                let scanned = (0..soup.len() as u32).map(|i| (distance(i), i)).min_by(|a, b| a.partial_cmp(b).unwrap());
                let mut best = f64::INFINITY;
                let mut found: Option<(f64, u32)> = None;
                let mut measured = 0;
                let query = NearestQuery::new(&tree, p, DVec3::ONE).unwrap();
                tree.nearest(&query, &mut best, |i, best| {
                    measured += 1;
                    let d = distance(i);
                    if found.is_none_or(|f| (d, i) < f) {
                        found = Some((d, i));
                        *best = d;
                    }
                });
                assert_eq!(found, scanned, "point {p}");
                pruned += soup.len() - measured;
            }
            assert!(pruned > 300 * soup.len() * 9 / 10, "the tree pruned little: {pruned}");
        }
    }

    /// The wide traversal meets every item the binary f64 traversal meets (a superset: its
    /// boxes are grown past rounding), and few more; rays from near and far, at the origin and
    /// 1e7 from it, at 1e-30 and 1e30.
    #[test]
    fn traversal_meets_what_the_binary_traversal_meets() {
        let mut stream = Stream(5);
        for (centre, size) in
            [(DVec3::ZERO, 1.0), (DVec3::new(1e7, -3e6, 2e6), 1.0), (DVec3::ZERO, 1e-30), (DVec3::ZERO, 1e30)]
        {
            let soup = triangles(&mut stream, 2000, centre, size);
            let (bvh, tree) = tree_over(&soup);
            let (mut wide_met, mut binary_met) = (0, 0);
            for k in 0..200 {
                let origin =
                    if k % 2 == 0 { soup[k][0] + stream.vector(size) } else { centre + stream.vector(80.0 * size) };
                let direction = DVec3::new(0.6, 0.48, 0.64) * if k % 3 == 0 { 1.0 } else { -1.0 } + stream.vector(0.1);
                let ray =
                    Ray64 { origin, direction, tmin: 0.0, tmax: if k % 4 == 0 { 10.0 * size } else { f64::INFINITY } };
                let mut binary = Vec::new();
                bvh.traverse(&ray, &mut ray.tmax.clone(), |item, _| {
                    binary.push(item);
                    true
                });
                let mut wide = Vec::new();
                let query = RayQuery::new(&tree, &ray).expect("a ray the tree takes");
                tree.traverse(&query, &mut ray.tmax.clone(), |item, _| {
                    wide.push(item);
                    true
                });
                wide.sort_unstable();
                assert!(wide.windows(2).all(|w| w[0] < w[1]), "an item met twice");
                // The binary traversal meets a leaf's items together; the wide one tests each
                // item's box: it must meet every item whose own box the ray enters.
                let inverse = ray.direction.recip();
                let entered =
                    |i: &&u32| Aabb::of_points(soup[**i as usize].iter().copied()).entry(&ray, inverse).is_some();
                let expected: Vec<u32> = binary.iter().filter(entered).copied().collect();
                assert!(
                    expected.iter().all(|i| wide.binary_search(i).is_ok()),
                    "ray {ray:?}: the wide traversal missed an item"
                );
                (wide_met, binary_met) = (wide_met + wide.len(), binary_met + binary.len());
            }
            // f32 boxes 1e7 from the origin are grown by f32's step there (about a unit: the
            // triangles' size), which prunes little; a mesh's own frame is centred on it.
            if centre == DVec3::ZERO {
                assert!(wide_met <= binary_met + binary_met / 10, "{size}: met {wide_met} against {binary_met}");
            }
        }
    }

    /// Trees beyond `EXTENTS` leave the f64 search in charge; so does a point far beyond its
    /// tree.
    #[test]
    fn far_boxes_and_points_are_left_to_the_f64_search() {
        for size in [1e40, 1e-40] {
            let far = [[DVec3::splat(size), DVec3::new(size, 0.0, 0.0), DVec3::new(0.0, size, size)]];
            let boxes: Vec<Aabb> = far.iter().map(|t| Aabb::of_points(t.iter().copied())).collect();
            assert!(WideTree::build(&Bvh::build(&boxes), &|i| Some(far[i])).is_none(), "{size}");
        }
        let near = [[DVec3::ZERO, DVec3::X, DVec3::Y]];
        let (_, tree) = tree_over(&near);
        assert!(NearestQuery::new(&tree, DVec3::splat(1e30), DVec3::ONE).is_none());
        assert!(NearestQuery::new(&tree, DVec3::splat(f64::NAN), DVec3::ONE).is_none());
        assert!(NearestQuery::new(&tree, DVec3::ONE, DVec3::ONE).is_some());
    }
}

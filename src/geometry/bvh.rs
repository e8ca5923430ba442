//! A binary bounding-volume hierarchy over boxes, in f64: the reference tier's, closest points'
//! and winding numbers' (each mesh's and the one over a scene's instances).

use glam::DVec3;

use crate::geometry::precision::{Aabb, Ray64};

/// Items one leaf holds at most.
const LEAF_ITEMS: usize = 4;

pub struct Node {
    pub bounds: Aabb,
    /// Leaf: first item in `Bvh::items`; inner node: index of the left child (the right follows).
    pub first: u32,
    /// Items of a leaf; 0 for an inner node.
    pub count: u32,
}

/// A binary BVH over boxes, split by the surface area heuristic over binned centroids (at the
/// median where that finds no split, or where the tree would grow deeper than `MAX_DEPTH`).
pub struct Bvh {
    nodes: Vec<Node>,
    items: Vec<u32>,
    /// Each item's box in leaf order (`items`' order), in f32 rounded outward: `nearest` bounds
    /// an item by it before visiting it, read beside its neighbours' rather than made from the
    /// item (a triangle's three corners fetched through its indices), at half an f64 box's bytes.
    item_boxes: Vec<ItemBox>,
}

/// An item's box in f32, every bound rounded outward (it holds the f64 box it was made from).
#[derive(Clone, Copy)]
struct ItemBox {
    min: [f32; 3],
    max: [f32; 3],
}

impl ItemBox {
    fn around(b: &Aabb) -> ItemBox {
        // The nearest f32, moved one step out where it rounded inward (NaN stays NaN).
        let down = |x: f64| {
            let f = x as f32;
            if f64::from(f) > x {
                f.next_down()
            } else {
                f
            }
        };
        let up = |x: f64| {
            let f = x as f32;
            if f64::from(f) < x {
                f.next_up()
            } else {
                f
            }
        };
        ItemBox { min: b.min.to_array().map(down), max: b.max.to_array().map(up) }
    }

    fn aabb(&self) -> Aabb {
        Aabb { min: DVec3::from_array(self.min.map(f64::from)), max: DVec3::from_array(self.max.map(f64::from)) }
    }
}

/// The deepest a leaf lies: the GPU's closest-point and winding shaders walk these trees with
/// stacks of 40 entries (closest_point.comp MESH_STACK, winding.comp STACK).
const MAX_DEPTH: u32 = 36;

/// Bins per axis of the SAH split search.
const SAH_BINS: usize = 16;

/// Entries a traversal's stack holds: one per level at most (`MAX_DEPTH`), with room to spare.
const STACK: usize = 64;

impl Bvh {
    /// `boxes` must be conservative: the traversal trusts them to hold every hit.
    pub fn build(boxes: &[Aabb]) -> Bvh {
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * boxes.len() / LEAF_ITEMS + 1),
            items: Vec::new(),
            item_boxes: Vec::new(),
        };
        let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
        if boxes.is_empty() {
            return bvh;
        }
        let centers: Vec<DVec3> = boxes.iter().map(Aabb::center).collect();
        bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
        // (node, its depth, range of `items`) still to split.
        let mut todo = vec![(0usize, 0u32, 0usize, items.len())];
        while let Some((node, depth, lo, hi)) = todo.pop() {
            let slice = &mut items[lo..hi];
            let bounds = slice.iter().fold(Aabb::EMPTY, |b, &i| b.union(&boxes[i as usize]));
            bvh.nodes[node].bounds = bounds;
            if slice.len() <= LEAF_ITEMS {
                bvh.nodes[node].first = lo as u32;
                bvh.nodes[node].count = slice.len() as u32;
                continue;
            }
            // Median splits keep `depth + levels_below(n)` as it is: SAH only while that has room.
            let room = depth + levels_below(slice.len()) + 2 < MAX_DEPTH;
            let mid = room
                .then(|| sah_split(slice, boxes, &centers))
                .flatten()
                .unwrap_or_else(|| median_split(slice, &centers));
            let left = bvh.nodes.len();
            bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            bvh.nodes[node].first = left as u32;
            todo.push((left, depth + 1, lo, lo + mid));
            todo.push((left + 1, depth + 1, lo + mid, hi));
        }
        bvh.item_boxes = items.iter().map(|&i| ItemBox::around(&boxes[i as usize])).collect();
        bvh.items = items;
        bvh
    }

    /// Calls `visit` with every item whose box may hold something nearer than `*best`, by
    /// `lower_bound` of its box (a distance no item in the box can beat; the item's own box, in
    /// f32 rounded outward, last), nearer boxes first; `visit` may lower `*best`.
    pub fn nearest(&self, lower_bound: impl Fn(&Aabb) -> f64, best: &mut f64, mut visit: impl FnMut(u32, &mut f64)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = [(0u32, 0f64); STACK];
        stack[0] = (0, lower_bound(&self.nodes[0].bounds));
        let mut n = 1;
        while n > 0 {
            n -= 1;
            let (index, bound) = stack[n];
            if bound > *best {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                let leaf = node.first as usize..(node.first + node.count) as usize;
                for (&item, own) in self.items[leaf.clone()].iter().zip(&self.item_boxes[leaf]) {
                    // Most of a leaf's items end here, by their own boxes.
                    if lower_bound(&own.aabb()) <= *best {
                        visit(item, best);
                    }
                }
                continue;
            }
            let (left, right) = (node.first, node.first + 1);
            let (lb, rb) =
                (lower_bound(&self.nodes[left as usize].bounds), lower_bound(&self.nodes[right as usize].bounds));
            // The nearer child is popped first; a child beyond `best` is not pushed at all.
            let (near, far) = if lb <= rb { ((left, lb), (right, rb)) } else { ((right, rb), (left, lb)) };
            for child in [far, near] {
                if child.1 <= *best {
                    stack[n] = child;
                    n += 1;
                }
            }
        }
    }

    /// The nodes, the root first (none for no boxes).
    pub fn nodes(&self) -> &[Node] {
        &self.nodes
    }

    /// The box of the `k`th item in leaf order (`items()[k]`'s), in f32 rounded outward: its
    /// lower corner, its upper.
    pub fn item_box(&self, k: usize) -> ([f32; 3], [f32; 3]) {
        (self.item_boxes[k].min, self.item_boxes[k].max)
    }

    /// The boxes' indices in leaf order: a leaf holds `items[first..first + count]`.
    pub fn items(&self) -> &[u32] {
        &self.items
    }

    /// Calls `visit` with every item whose box the ray enters before `*tmax`, nearer boxes first;
    /// `visit` may lower `*tmax` (a closer hit) or return false to stop (an occlusion query's
    /// first hit).
    pub fn traverse(&self, ray: &Ray64, tmax: &mut f64, mut visit: impl FnMut(u32, &mut f64) -> bool) {
        if self.nodes.is_empty() {
            return;
        }
        let inverse_direction = ray.direction.recip();
        let entry = |index: u32, tmax: f64| {
            let bounded = Ray64 { tmax, ..*ray };
            self.nodes[index as usize].bounds.entry(&bounded, inverse_direction)
        };
        let Some(root) = entry(0, *tmax) else { return };
        // Nodes still to visit, with where the ray enters them (skipped once a hit comes before).
        let mut stack = [(0u32, 0f64); STACK];
        stack[0] = (0, root);
        let mut n = 1;
        while n > 0 {
            n -= 1;
            let (index, enter) = stack[n];
            if enter > *tmax {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                for &item in &self.items[node.first as usize..(node.first + node.count) as usize] {
                    if !visit(item, tmax) {
                        return;
                    }
                }
                continue;
            }
            let (left, right) = (node.first, node.first + 1);
            match (entry(left, *tmax), entry(right, *tmax)) {
                (Some(l), Some(r)) => {
                    let (near, far) = if l <= r { ((left, l), (right, r)) } else { ((right, r), (left, l)) };
                    stack[n] = far;
                    stack[n + 1] = near;
                    n += 2;
                }
                (Some(l), None) => {
                    stack[n] = (left, l);
                    n += 1;
                }
                (None, Some(r)) => {
                    stack[n] = (right, r);
                    n += 1;
                }
                (None, None) => {}
            }
        }
    }
}

/// Levels of median splits below a node of `n` items before its leaves.
fn levels_below(n: usize) -> u32 {
    n.div_ceil(LEAF_ITEMS).next_power_of_two().trailing_zeros()
}

/// Splits `slice` at the median centroid along the widest axis of its centroids: the items of
/// the left child come first; returns their number.
fn median_split(slice: &mut [u32], centers: &[DVec3]) -> usize {
    let extent = Aabb::of_points(slice.iter().map(|&i| centers[i as usize])).extent();
    let axis = widest_axis(extent);
    let mid = slice.len() / 2;
    slice.select_nth_unstable_by(mid, |&a, &b| centers[a as usize][axis].total_cmp(&centers[b as usize][axis]));
    mid
}

fn widest_axis(extent: DVec3) -> usize {
    if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    }
}

/// The surface area heuristic's best split of `slice` among `SAH_BINS` bins of its centroids'
/// extent on each axis, partitioned in place (left items first; returns their number), or None
/// where every candidate leaves a side empty.
fn sah_split(slice: &mut [u32], boxes: &[Aabb], centers: &[DVec3]) -> Option<usize> {
    let cb = Aabb::of_points(slice.iter().map(|&i| centers[i as usize]));
    let extent = cb.extent();
    let bin_of = |axis: usize, c: DVec3| -> usize {
        let x = (c[axis] - cb.min[axis]) / extent[axis] * SAH_BINS as f64;
        (x as usize).min(SAH_BINS - 1)
    };
    let mut best: Option<(f64, usize, usize)> = None;
    for axis in 0..3 {
        if extent[axis] <= 0.0 || !extent[axis].is_finite() {
            continue;
        }
        let mut counts = [0usize; SAH_BINS];
        let mut bins = [Aabb::EMPTY; SAH_BINS];
        for &i in slice.iter() {
            let b = bin_of(axis, centers[i as usize]);
            counts[b] += 1;
            bins[b] = bins[b].union(&boxes[i as usize]);
        }
        // Right-hand sweeps: the area and count of bins k.. for each k.
        let mut right_area = [0.0f64; SAH_BINS];
        let mut right_count = [0usize; SAH_BINS];
        let (mut acc, mut count) = (Aabb::EMPTY, 0);
        for k in (1..SAH_BINS).rev() {
            acc = acc.union(&bins[k]);
            count += counts[k];
            right_area[k] = half_area(&acc);
            right_count[k] = count;
        }
        let (mut acc, mut count) = (Aabb::EMPTY, 0);
        for k in 1..SAH_BINS {
            acc = acc.union(&bins[k - 1]);
            count += counts[k - 1];
            if count == 0 || right_count[k] == 0 {
                continue;
            }
            let cost = half_area(&acc) * count as f64 + right_area[k] * right_count[k] as f64;
            if cost.is_finite() && best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, k));
            }
        }
    }
    let (_, axis, split) = best?;
    let mut left = 0;
    for k in 0..slice.len() {
        if bin_of(axis, centers[slice[k] as usize]) < split {
            slice.swap(k, left);
            left += 1;
        }
    }
    (left > 0 && left < slice.len()).then_some(left)
}

fn half_area(b: &Aabb) -> f64 {
    let e = b.extent();
    e.x * e.y + e.y * e.z + e.z * e.x
}

#[cfg(test)]
mod tests {
    use super::*;

    fn depth_and_items(bvh: &Bvh, node: usize, depth: u32, seen: &mut Vec<u32>) -> u32 {
        let n = &bvh.nodes()[node];
        if n.count > 0 {
            assert!(n.count as usize <= LEAF_ITEMS);
            seen.extend(&bvh.items()[n.first as usize..(n.first + n.count) as usize]);
            return depth;
        }
        let left = depth_and_items(bvh, n.first as usize, depth + 1, seen);
        left.max(depth_and_items(bvh, n.first as usize + 1, depth + 1, seen))
    }

    /// Boxes strung out so that SAH splits would peel one off at a time (each twice the last):
    /// the tree still holds every item once and stays within the GPU's stacks.
    #[test]
    fn sah_trees_hold_every_item_once_within_the_depth_bound() {
        let boxes: Vec<Aabb> = (0..5000)
            .map(|i| {
                let x = if i < 60 { 2f64.powi(i) } else { f64::from(i) };
                Aabb { min: DVec3::new(x, 0.0, 0.0), max: DVec3::new(x + 0.5, 1.0, 1.0) }
            })
            .collect();
        let bvh = Bvh::build(&boxes);
        let mut seen = Vec::new();
        let depth = depth_and_items(&bvh, 0, 0, &mut seen);
        assert!(depth <= MAX_DEPTH, "depth {depth}");
        seen.sort_unstable();
        assert_eq!(seen, (0..5000).collect::<Vec<u32>>());
    }

    /// Ordered traversal meets every box a ray enters (a test of every box is the oracle), each
    /// item once (a leaf's items come together, so some it meets the ray misses).
    #[test]
    fn traversal_meets_every_box_the_ray_enters() {
        let boxes: Vec<Aabb> = (0..2000)
            .map(|i| {
                let c = DVec3::new((i * 37 % 101) as f64, (i * 53 % 97) as f64, (i * 71 % 89) as f64);
                Aabb { min: c, max: c + DVec3::splat(3.0) }
            })
            .collect();
        let bvh = Bvh::build(&boxes);
        let ray =
            Ray64 { origin: DVec3::new(-5.0, 1.0, 2.0), direction: DVec3::new(1.0, 0.8, 0.7), tmin: 0.0, tmax: 1e9 };
        let inverse = ray.direction.recip();
        let mut expected: Vec<u32> =
            (0..boxes.len() as u32).filter(|&i| boxes[i as usize].entry(&ray, inverse).is_some()).collect();
        let mut met = Vec::new();
        bvh.traverse(&ray, &mut 1e9, |item, _| {
            met.push(item);
            true
        });
        expected.sort_unstable();
        met.sort_unstable();
        assert!(!expected.is_empty());
        assert!(met.windows(2).all(|w| w[0] < w[1]), "an item met twice");
        assert!(expected.iter().all(|i| met.binary_search(i).is_ok()), "a box the ray enters was not met");
        assert!(met.len() < boxes.len() / 4, "the hierarchy pruned little: {} of {}", met.len(), boxes.len());
    }

    /// An item's f32 box holds its f64 box, one f32 step at most beyond each bound, at any
    /// magnitude and sign (values f32 holds exactly stay as they are).
    #[test]
    fn item_boxes_hold_their_boxes_rounded_outward() {
        let values = [0.0, -0.0, 1.0, 0.1, -0.1, 1e7 + 0.3, -1e7 - 0.3, 3.4e38, -3.4e38, 1e-40, 1.5, 2f64.powi(-149)];
        for &lo in &values {
            for &extent in &[0.0, 1e-12, 0.25, 1e6] {
                let b = Aabb { min: DVec3::splat(lo), max: DVec3::splat(lo + extent) };
                let own = ItemBox::around(&b).aabb();
                assert!(own.min.cmple(b.min).all() && own.max.cmpge(b.max).all(), "{lo} {extent}: not held");
                let within_a_step = |f: f64, x: f64, outward: fn(f32) -> f32| {
                    let exact = (x as f32) as f64 == x;
                    if exact {
                        f == x
                    } else {
                        f64::from(outward(f as f32)) != f && (f - x).abs() <= (f - f64::from(outward(f as f32))).abs()
                    }
                };
                assert!(
                    within_a_step(own.min.x, b.min.x, f32::next_down),
                    "{lo} {extent}: min {} for {}",
                    own.min.x,
                    b.min.x
                );
                assert!(
                    within_a_step(own.max.x, b.max.x, f32::next_up),
                    "{lo} {extent}: max {} for {}",
                    own.max.x,
                    b.max.x
                );
            }
        }
    }

    /// The nearest item by distance from points, through `nearest` (its boxes and the items' own
    /// boxes pruning), equals a scan of every item: spheres about scattered centres.
    #[test]
    fn nearest_finds_what_a_scan_of_every_item_finds() {
        let centres: Vec<DVec3> = (0..3000)
            .map(|i| DVec3::new((i * 37 % 101) as f64 * 0.31, (i * 53 % 97) as f64 * 0.29, (i * 71 % 89) as f64 * 0.37))
            .collect();
        let radius = 0.05;
        let boxes: Vec<Aabb> = centres.iter().map(|&c| Aabb { min: c - radius, max: c + radius }).collect();
        let bvh = Bvh::build(&boxes);
        let gap = |b: &Aabb, p: DVec3| (b.min - p).max(p - b.max).max(DVec3::ZERO).length();
        for k in 0..200 {
            let p = DVec3::new(k as f64 * 0.17 % 31.0, k as f64 * 0.23 % 29.0, k as f64 * 0.41 % 33.0) - 1.0;
            let distance = |i: u32| ((p - centres[i as usize]).length() - radius).max(0.0);
            let scanned = (0..centres.len() as u32).map(|i| (distance(i), i)).min_by(|a, b| a.partial_cmp(b).unwrap());
            let mut best = f64::INFINITY;
            let mut found = None;
            bvh.nearest(
                |b| gap(b, p),
                &mut best,
                |i, best| {
                    let d = distance(i);
                    if found.is_none_or(|f| (d, i) < f) {
                        found = Some((d, i));
                        *best = d;
                    }
                },
            );
            assert_eq!(found, scanned, "point {p}");
        }
    }
}

//! A binary bounding-volume hierarchy over boxes, in f64: the reference tier's, closest points'
//! and winding numbers' (each mesh's and the one over a scene's instances).

use glam::DVec3;
use rayon::prelude::*;

use super::parallel;
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
    ///
    /// The splits are found on all cores (`plan_subtree`: the two sides of a split are disjoint runs of
    /// the items, split on their own), then laid out in one pass in the order a single-threaded
    /// top-down build takes them (the same nodes, numbered the same: `lay_out`).
    pub fn build(boxes: &[Aabb]) -> Bvh {
        let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
        if boxes.is_empty() {
            return Bvh { nodes: Vec::new(), items, item_boxes: Vec::new() };
        }
        let (nodes, items) = parallel::install(|| {
            let centers: Vec<DVec3> = boxes.par_iter().with_min_len(4096).map(Aabb::center).collect();
            let inputs = SplitInputs { boxes, centers: &centers };
            let plan = plan_subtree(inputs, &mut items, 0);
            (lay_out(&plan, items.len()), items)
        });
        let item_boxes = parallel::install(|| {
            items.par_iter().with_min_len(4096).map(|&i| ItemBox::around(&boxes[i as usize])).collect()
        });
        Bvh { nodes, items, item_boxes }
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

/// What every split of one build reads: the items' boxes and their centres.
#[derive(Clone, Copy)]
struct SplitInputs<'a> {
    boxes: &'a [Aabb],
    centers: &'a [DVec3],
}

/// A node as `plan_subtree` found it: its box, and where its run of items splits (0: a leaf).
struct PlannedNode {
    bounds: Aabb,
    split: u32,
}

/// Runs of items at least this long are split with their two sides on two cores (and their
/// boxes and bins summed on all cores); shorter ones on one.
const PARALLEL_ITEMS: usize = 1 << 14;

/// The nodes of the subtree over `items` (at `depth`), each node before its right subtree and
/// that before its left (the order `lay_out` takes them in), in pieces: the two sides of a split
/// found on two cores are joined without copying each other's nodes. `items` is left in leaf
/// order.
fn plan_subtree(inputs: SplitInputs, items: &mut [u32], depth: u32) -> Vec<Vec<PlannedNode>> {
    if items.len() < PARALLEL_ITEMS {
        let mut nodes = Vec::new();
        plan_nodes(inputs, items, depth, &mut nodes);
        return vec![nodes];
    }
    let bounds = fold_items(items, Aabb::EMPTY, |b, i| *b = b.union(&inputs.boxes[i]), |a, b| a.union(&b));
    let split = split_items(inputs, items, depth);
    let (left, right) = items.split_at_mut(split);
    let (right, left) =
        rayon::join(|| plan_subtree(inputs, right, depth + 1), || plan_subtree(inputs, left, depth + 1));
    let mut pieces = vec![vec![PlannedNode { bounds, split: split as u32 }]];
    pieces.extend(right);
    pieces.extend(left);
    pieces
}

/// `plan_subtree` on one core, into `nodes`.
fn plan_nodes(inputs: SplitInputs, items: &mut [u32], depth: u32, nodes: &mut Vec<PlannedNode>) {
    let bounds = items.iter().fold(Aabb::EMPTY, |b, &i| b.union(&inputs.boxes[i as usize]));
    if items.len() <= LEAF_ITEMS {
        nodes.push(PlannedNode { bounds, split: 0 });
        return;
    }
    let split = split_items(inputs, items, depth);
    nodes.push(PlannedNode { bounds, split: split as u32 });
    let (left, right) = items.split_at_mut(split);
    plan_nodes(inputs, right, depth + 1, nodes);
    plan_nodes(inputs, left, depth + 1, nodes);
}

/// Splits a run of more than `LEAF_ITEMS` items at `depth` in place (the left child's first);
/// returns the left child's count. Median splits keep `depth + levels_below(n)` as it is: SAH
/// only while that has room.
fn split_items(inputs: SplitInputs, items: &mut [u32], depth: u32) -> usize {
    let room = depth + levels_below(items.len()) + 2 < MAX_DEPTH;
    room.then(|| sah_split(items, inputs.boxes, inputs.centers))
        .flatten()
        .unwrap_or_else(|| median_split(items, inputs.centers))
}

/// The planned nodes as the hierarchy's array: each inner node's two children side by side,
/// numbered as a single-threaded top-down build numbers them (it splits the node taken last
/// from its stack and puts its left child, then its right, on the stack).
fn lay_out(plan: &[Vec<PlannedNode>], items: usize) -> Vec<Node> {
    let mut nodes = Vec::with_capacity(2 * items / LEAF_ITEMS + 1);
    nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
    let mut planned = plan.iter().flatten();
    // (node, range of the items) still to lay out.
    let mut todo = vec![(0usize, 0usize, items)];
    while let Some((node, lo, hi)) = todo.pop() {
        let next = planned.next().expect("a planned node for every node laid out");
        nodes[node].bounds = next.bounds;
        if next.split == 0 {
            (nodes[node].first, nodes[node].count) = (lo as u32, (hi - lo) as u32);
            continue;
        }
        let left = nodes.len();
        nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
        nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
        nodes[node].first = left as u32;
        let mid = lo + next.split as usize;
        todo.push((left, lo, mid));
        todo.push((left + 1, mid, hi));
    }
    nodes
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
    let cb = fold_items(slice, Aabb::EMPTY, |b, i| *b = b.union(&Aabb::of_points([centers[i]])), |a, b| a.union(&b));
    let extent = cb.extent();
    // Bins per unit length on each axis (a product a bin, not a quotient: the builds' hot loop).
    let scale = DVec3::splat(SAH_BINS as f64) / extent;
    let bin_of = |axis: usize, c: DVec3| -> usize {
        let x = (c[axis] - cb.min[axis]) * scale[axis];
        (x as usize).min(SAH_BINS - 1)
    };
    // Every axis's bins in one pass over the items (each box read once).
    let binned = fold_items(
        slice,
        [Bins::default(); 3],
        |bins, i| {
            let item = &boxes[i];
            for (axis, bins) in bins.iter_mut().enumerate() {
                let b = bin_of(axis, centers[i]);
                bins.counts[b] += 1;
                bins.boxes[b] = bins.boxes[b].union(item);
            }
        },
        |a, b| std::array::from_fn(|axis| a[axis].join(&b[axis])),
    );
    let mut best: Option<(f64, usize, usize)> = None;
    for (axis, Bins { counts, boxes: bins }) in binned.iter().enumerate() {
        if extent[axis] <= 0.0 || !extent[axis].is_finite() {
            continue;
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

/// One axis's bins of a SAH split: each bin's item count and their boxes' union.
#[derive(Clone, Copy)]
struct Bins {
    counts: [usize; SAH_BINS],
    boxes: [Aabb; SAH_BINS],
}

impl Default for Bins {
    fn default() -> Bins {
        Bins { counts: [0; SAH_BINS], boxes: [Aabb::EMPTY; SAH_BINS] }
    }
}

impl Bins {
    fn join(&self, other: &Bins) -> Bins {
        Bins {
            counts: std::array::from_fn(|k| self.counts[k] + other.counts[k]),
            boxes: std::array::from_fn(|k| self.boxes[k].union(&other.boxes[k])),
        }
    }
}

/// `items` folded into `empty` by `add` (in place: the bins are kilobytes): on all cores (pieces
/// joined by `join`, which must be associative and exact: unions of boxes, sums of counts) for
/// runs of `PARALLEL_ITEMS` or more.
fn fold_items<T: Copy + Send + Sync>(
    items: &[u32],
    empty: T,
    add: impl Fn(&mut T, usize) + Sync,
    join: impl Fn(T, T) -> T + Sync,
) -> T {
    let fold = |chunk: &[u32]| {
        let mut acc = empty;
        for &i in chunk {
            add(&mut acc, i as usize);
        }
        acc
    };
    if items.len() < PARALLEL_ITEMS {
        return fold(items);
    }
    items.par_chunks(PARALLEL_ITEMS / 4).map(fold).reduce(|| empty, &join)
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

    /// The single-threaded top-down build `Bvh::build` replaces (its splits, one node at a time
    /// off a stack): the oracle of the parallel build's layout.
    fn build_on_one_thread(boxes: &[Aabb]) -> (Vec<Node>, Vec<u32>) {
        let centers: Vec<DVec3> = boxes.iter().map(Aabb::center).collect();
        let inputs = SplitInputs { boxes, centers: &centers };
        let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
        let mut nodes = vec![Node { bounds: Aabb::EMPTY, first: 0, count: 0 }];
        let mut todo = vec![(0usize, 0u32, 0usize, items.len())];
        while let Some((node, depth, lo, hi)) = todo.pop() {
            let slice = &mut items[lo..hi];
            nodes[node].bounds = slice.iter().fold(Aabb::EMPTY, |b, &i| b.union(&boxes[i as usize]));
            if slice.len() <= LEAF_ITEMS {
                (nodes[node].first, nodes[node].count) = (lo as u32, slice.len() as u32);
                continue;
            }
            let mid = split_items(inputs, slice, depth);
            let left = nodes.len();
            nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            nodes[node].first = left as u32;
            todo.push((left, depth + 1, lo, lo + mid));
            todo.push((left + 1, depth + 1, lo + mid, hi));
        }
        (nodes, items)
    }

    /// The parallel build lays out the nodes and items the single-threaded one does, bit for bit:
    /// boxes of a surface (long runs split on many cores), of points in a line (median splits
    /// past the depth's room) and a few (one core).
    #[test]
    fn parallel_builds_equal_the_single_threaded_build() {
        let surface: Vec<Aabb> = (0..150_000)
            .map(|i| {
                let (u, v) = (f64::from(i % 400) * 0.01, f64::from(i / 400) * 0.013);
                let c = DVec3::new(u, v, (u * 3.0).sin() * (v * 2.0).cos());
                Aabb { min: c, max: c + DVec3::new(0.011, 0.014, 0.002 * f64::from(i % 7)) }
            })
            .collect();
        let line: Vec<Aabb> = (0..70_000)
            .map(|i| {
                let x = if i < 60 { 2f64.powi(i) } else { f64::from(i) };
                Aabb { min: DVec3::new(x, 0.0, 0.0), max: DVec3::new(x + 0.5, 1.0, 1.0) }
            })
            .collect();
        for boxes in [surface, line, (0..9).map(|i| Aabb::of_points([DVec3::splat(f64::from(i))])).collect()] {
            let bvh = Bvh::build(&boxes);
            let (nodes, items) = build_on_one_thread(&boxes);
            assert_eq!(bvh.items(), &items[..]);
            assert_eq!(bvh.nodes().len(), nodes.len());
            for (a, b) in bvh.nodes().iter().zip(&nodes) {
                assert_eq!((a.first, a.count), (b.first, b.count));
                assert!(a.bounds.min == b.bounds.min && a.bounds.max == b.bounds.max);
            }
        }
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

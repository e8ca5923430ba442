//! A binary bounding-volume hierarchy over boxes, in f64: the reference tier's, closest points'
//! and winding numbers' (each mesh's and the one over a scene's instances).

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

/// A binary BVH over boxes, split at the median centroid along the widest axis.
pub struct Bvh {
    nodes: Vec<Node>,
    items: Vec<u32>,
}

impl Bvh {
    /// `boxes` must be conservative: the traversal trusts them to hold every hit.
    pub fn build(boxes: &[Aabb]) -> Bvh {
        let mut bvh = Bvh { nodes: Vec::with_capacity(2 * boxes.len() / LEAF_ITEMS + 1), items: Vec::new() };
        let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
        if boxes.is_empty() {
            return bvh;
        }
        bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
        // (node, range of `items`) still to split.
        let mut todo = vec![(0usize, 0usize, items.len())];
        while let Some((node, lo, hi)) = todo.pop() {
            let slice = &mut items[lo..hi];
            let bounds = slice.iter().fold(Aabb::EMPTY, |b, &i| b.union(&boxes[i as usize]));
            bvh.nodes[node].bounds = bounds;
            if slice.len() <= LEAF_ITEMS {
                bvh.nodes[node].first = lo as u32;
                bvh.nodes[node].count = slice.len() as u32;
                continue;
            }
            let centroids = Aabb::of_points(slice.iter().map(|&i| boxes[i as usize].center()));
            let extent = centroids.extent();
            let axis = if extent.x >= extent.y && extent.x >= extent.z {
                0
            } else if extent.y >= extent.z {
                1
            } else {
                2
            };
            let mid = slice.len() / 2;
            slice.select_nth_unstable_by(mid, |&a, &b| {
                boxes[a as usize].center()[axis].total_cmp(&boxes[b as usize].center()[axis])
            });
            let left = bvh.nodes.len();
            bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            bvh.nodes.push(Node { bounds: Aabb::EMPTY, first: 0, count: 0 });
            bvh.nodes[node].first = left as u32;
            todo.push((left, lo, lo + mid));
            todo.push((left + 1, lo + mid, hi));
        }
        bvh.items = items;
        bvh
    }

    /// Calls `visit` with every item whose box may hold something nearer than `*best`, by
    /// `lower_bound` of its box (a distance no item in the box can beat), nearer boxes first;
    /// `visit` may lower `*best`.
    pub fn nearest(&self, lower_bound: impl Fn(&Aabb) -> f64, best: &mut f64, mut visit: impl FnMut(u32, &mut f64)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = Vec::with_capacity(64);
        stack.push((0u32, lower_bound(&self.nodes[0].bounds)));
        while let Some((index, bound)) = stack.pop() {
            if bound > *best {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                for &item in &self.items[node.first as usize..(node.first + node.count) as usize] {
                    visit(item, best);
                }
                continue;
            }
            let (left, right) = (node.first, node.first + 1);
            let (lb, rb) =
                (lower_bound(&self.nodes[left as usize].bounds), lower_bound(&self.nodes[right as usize].bounds));
            // The nearer child is popped first.
            if lb <= rb {
                stack.push((right, rb));
                stack.push((left, lb));
            } else {
                stack.push((left, lb));
                stack.push((right, rb));
            }
        }
    }

    /// The nodes, the root first (none for no boxes).
    pub fn nodes(&self) -> &[Node] {
        &self.nodes
    }

    /// The boxes' indices in leaf order: a leaf holds `items[first..first + count]`.
    pub fn items(&self) -> &[u32] {
        &self.items
    }

    /// Calls `visit` with every item whose box the ray enters before `*tmax`; `visit` may lower
    /// `*tmax` (a closer hit) or return false to stop (an occlusion query's first hit).
    pub fn traverse(&self, ray: &Ray64, tmax: &mut f64, mut visit: impl FnMut(u32, &mut f64) -> bool) {
        if self.nodes.is_empty() {
            return;
        }
        let inverse_direction = ray.direction.recip();
        let mut stack = Vec::with_capacity(64);
        stack.push(0u32);
        while let Some(index) = stack.pop() {
            let node = &self.nodes[index as usize];
            let bounded = Ray64 { tmax: *tmax, ..*ray };
            if node.bounds.entry(&bounded, inverse_direction).is_none() {
                continue;
            }
            if node.count > 0 {
                for &item in &self.items[node.first as usize..(node.first + node.count) as usize] {
                    if !visit(item, tmax) {
                        return;
                    }
                }
            } else {
                stack.push(node.first);
                stack.push(node.first + 1);
            }
        }
    }
}

//! Generalized winding numbers (Jacobson et al. 2013) summed over a mesh's hierarchy, exactly.
//!
//! The winding number of a set of triangles S about a point p is the sum of their signed solid
//! angles over 4π. Where p lies outside a convex region holding all of S, that sum equals the sum
//! over S's boundary alone: close S with the fan of triangles (o, u, v) from a point o of the
//! region over each boundary edge u → v (the oriented edges of S's triangles that no other
//! triangle of S cancels); S less the fan has no boundary, so its winding number is an integer,
//! 0 outside the region, and S's number is the fan's. This is exact, not a far-field
//! approximation (Barill et al. 2018 approximate it): a node of the hierarchy whose box p lies
//! well outside contributes its boundary's few edges instead of its many triangles, and a closed
//! part contributes nothing. A node keeps its boundary only where it has fewer edges than
//! triangles; otherwise its children (or its triangles) are summed.

use glam::DVec3;

use super::bvh::Bvh;
use super::precision::{Aabb, Affine};

/// A node's boundary among `WindingTree::edges`; `count == NO_CAP`: none kept (sum below it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Span {
    pub first: u32,
    pub count: u32,
}

/// `Span::count` of a node whose boundary is not kept.
pub const NO_CAP: u32 = u32::MAX;

/// How far outside its box (the box's largest side over this) a point must lie for a node's
/// boundary to stand in for its triangles: the fan's triangles then keep that distance from the
/// point, and their solid angles are well conditioned. winding.comp's specialization constant.
pub const CAP_MARGIN_DIVISOR: u32 = 8;

/// A mesh's triangles as winding numbers read them: `faces` over `vertices`, and the hierarchy
/// over the faces' boxes.
#[derive(Clone, Copy)]
pub struct Triangles<'a> {
    pub bvh: &'a Bvh,
    pub vertices: &'a [DVec3],
    pub faces: &'a [[u32; 3]],
}

/// The boundaries of every node of a mesh's hierarchy (`TriangleSet::bvh`).
pub struct WindingTree {
    /// Per node of the hierarchy.
    spans: Vec<Span>,
    /// Oriented edges (vertex indices) of the nodes' boundaries, each node's together.
    edges: Vec<[u32; 2]>,
}

/// An edge keyed by its lower vertex first, and how many times it runs from the lower vertex to
/// the higher, less the other way.
type NetEdge = (u32, u32, i32);

impl WindingTree {
    /// `bvh`: the hierarchy over `faces`' boxes.
    pub fn build(bvh: &Bvh, faces: &[[u32; 3]]) -> WindingTree {
        let (nodes, items) = (bvh.nodes(), bvh.items());
        let mut boundaries: Vec<Vec<NetEdge>> = (0..nodes.len()).map(|_| Vec::new()).collect();
        let mut triangles = vec![0usize; nodes.len()];
        let mut spans = vec![Span { first: 0, count: NO_CAP }; nodes.len()];
        let mut edges = Vec::new();
        // Children come after their parent (Bvh::build): the reverse order visits them first.
        for i in (0..nodes.len()).rev() {
            let node = &nodes[i];
            let first = node.first as usize;
            let boundary = if node.count > 0 {
                triangles[i] = node.count as usize;
                let mut own = Vec::with_capacity(3 * node.count as usize);
                for &prim in &items[first..first + node.count as usize] {
                    let [a, b, c] = faces[prim as usize];
                    own.extend([net_edge(a, b), net_edge(b, c), net_edge(c, a)]);
                }
                own.sort_unstable();
                cancel(own)
            } else {
                triangles[i] = triangles[first] + triangles[first + 1];
                let left = std::mem::take(&mut boundaries[first]);
                let right = std::mem::take(&mut boundaries[first + 1]);
                merge(left, right)
            };
            let count: usize = boundary.iter().map(|e| e.2.unsigned_abs() as usize).sum();
            if count < triangles[i] {
                spans[i] = Span { first: edges.len() as u32, count: count as u32 };
                for &(lo, hi, net) in &boundary {
                    let edge = if net > 0 { [lo, hi] } else { [hi, lo] };
                    edges.extend(std::iter::repeat_n(edge, net.unsigned_abs() as usize));
                }
            }
            boundaries[i] = boundary;
        }
        WindingTree { spans, edges }
    }

    /// Per node of the set's hierarchy, its boundary among `edges` (or `NO_CAP`).
    pub fn spans(&self) -> &[Span] {
        &self.spans
    }

    /// The boundaries' oriented edges, as vertex indices of the set.
    pub fn edges(&self) -> &[[u32; 2]] {
        &self.edges
    }

    /// The winding number about `p` (scene frame; `local`: the same point in the mesh's frame) of
    /// the triangles (`faces` over `vertices`, under `bvh`, the hierarchy this tree was built
    /// over) placed by `to_scene`, unsigned by any mirroring.
    pub fn winding_number(&self, triangles: Triangles, to_scene: &Affine, p: DVec3, local: DVec3) -> f64 {
        let Triangles { bvh, vertices, faces } = triangles;
        let (nodes, items) = (bvh.nodes(), bvh.items());
        if nodes.is_empty() {
            return 0.0;
        }
        let corner = |v: DVec3| to_scene.point(v) - p;
        let vertex = |i: u32| corner(vertices[i as usize]);
        let mut sum = 0.0;
        let mut stack = Vec::with_capacity(64);
        stack.push(0usize);
        while let Some(i) = stack.pop() {
            let node = &nodes[i];
            let span = self.spans[i];
            if span.count != NO_CAP && beyond_margin(&node.bounds, local) {
                let apex = corner(node.bounds.center());
                let range = span.first as usize..(span.first + span.count) as usize;
                for &[u, v] in &self.edges[range] {
                    sum += twice_solid_angle(apex, vertex(u), vertex(v));
                }
            } else if node.count > 0 {
                for &prim in &items[node.first as usize..(node.first + node.count) as usize] {
                    let [a, b, c] = faces[prim as usize].map(vertex);
                    sum += twice_solid_angle(a, b, c);
                }
            } else {
                stack.push(node.first as usize + 1);
                stack.push(node.first as usize);
            }
        }
        sum / (4.0 * std::f64::consts::PI)
    }
}

/// A boundary's oriented edges (vertex indices) grouped into its loops: the edges of each
/// connected component, in the order given. A boundary is a cycle (at each vertex as many edges
/// arrive as leave), and so is each component, since every edge at a vertex lies in the vertex's
/// component: a fan from any point over one group's edges has that group as its boundary, and so
/// closes that hole alone.
pub fn boundary_loops(edges: &[[u32; 2]]) -> Vec<Vec<[u32; 2]>> {
    let mut parent: std::collections::HashMap<u32, u32> = std::collections::HashMap::new();
    fn root(parent: &mut std::collections::HashMap<u32, u32>, mut v: u32) -> u32 {
        while let Some(&up) = parent.get(&v).filter(|&&up| up != v) {
            // Path halving keeps the trees shallow.
            let grand = parent.get(&up).copied().unwrap_or(up);
            parent.insert(v, grand);
            v = grand;
        }
        v
    }
    for &[a, b] in edges {
        parent.entry(a).or_insert(a);
        parent.entry(b).or_insert(b);
        let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
        if ra != rb {
            parent.insert(ra.max(rb), ra.min(rb));
        }
    }
    let mut loops: Vec<Vec<[u32; 2]>> = Vec::new();
    let mut index_of: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
    for &edge in edges {
        let r = root(&mut parent, edge[0]);
        let k = *index_of.entry(r).or_insert_with(|| {
            loops.push(Vec::new());
            loops.len() - 1
        });
        loops[k].push(edge);
    }
    loops
}

/// Whether `p` lies outside `bounds` grown by its largest side over `CAP_MARGIN_DIVISOR`.
pub fn beyond_margin(bounds: &Aabb, p: DVec3) -> bool {
    let margin = DVec3::splat(bounds.extent().max_element() / CAP_MARGIN_DIVISOR as f64);
    p.cmplt(bounds.min - margin).any() || p.cmpgt(bounds.max + margin).any()
}

/// Twice the signed solid angle of the triangle (a, b, c) seen from the origin (the corners
/// relative to the point), by Van Oosterom and Strackee's formula.
pub fn twice_solid_angle(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    let terms = SolidAngleTerms::of(a, b, c, a.length());
    2.0 * terms.numerator.atan2(terms.denominator)
}

/// Van Oosterom and Strackee's numerator and denominator of the triangle (a, b, c) about the
/// origin (half its solid angle is their `atan2`), and the product of the corners' distances.
pub struct SolidAngleTerms {
    pub numerator: f64,
    pub denominator: f64,
    pub lengths: f64,
}

impl SolidAngleTerms {
    /// The terms of (a, b, c), `a`'s length given (a fan's apex shares it).
    #[inline]
    pub fn of(a: DVec3, b: DVec3, c: DVec3, la: f64) -> SolidAngleTerms {
        let (lb, lc) = (b.length(), c.length());
        let lengths = la * lb * lc;
        let numerator = a.dot(b.cross(c));
        let denominator = lengths + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
        SolidAngleTerms { numerator, denominator, lengths }
    }

    /// Whether the origin lies on the triangle or within 1e-10 of its size of its inside, where
    /// its solid angle jumps by 4π (shaders/solid_angle.glsl `near_inside`).
    #[inline]
    pub fn near_inside(&self) -> bool {
        self.denominator <= 0.0 && self.numerator.abs() <= 1e-10 * self.lengths
    }
}

/// A sum of `atan2(y, x)` over many (y, x) with one arctangent: the product of the complex
/// numbers x + iy (its argument is the sum's, modulo 2π), and the turns the sum made past ±π,
/// counted as each factor is taken. The libm arctangent of each term was most of the caps'
/// solid angles (a fan of a hundred triangles about each point near a hole).
///
/// The product's size is kept near 1 by a power of two a factor (no rounding). A turn is
/// counted where two factors on one side of the real axis (by the sign bit, as `atan2` reads
/// it) make a product on the other: their arguments' sum passed ±π. The result differs from
/// the sum of the terms' own arctangents by rounding alone (a few ulps a term).
#[derive(Clone, Copy, Debug)]
pub struct ArgumentSum {
    x: f64,
    y: f64,
    turns: i32,
}

impl Default for ArgumentSum {
    fn default() -> ArgumentSum {
        ArgumentSum { x: 1.0, y: 0.0, turns: 0 }
    }
}

impl ArgumentSum {
    /// Adds `atan2(y, x)` (nothing for y = x = 0, whose `atan2` is ±0 or ±π by the zeros' signs:
    /// the callers treat such a term, a point on a triangle's edge or corner, as unsure).
    #[inline]
    pub fn add(&mut self, y: f64, x: f64) {
        if x == 0.0 && y == 0.0 {
            return;
        }
        let (px, py) = (self.x * x - self.y * y, self.x * y + self.y * x);
        let (was_upper, term_upper, upper) = (self.y.is_sign_positive(), y.is_sign_positive(), py.is_sign_positive());
        if was_upper == term_upper && upper != was_upper {
            self.turns += if was_upper { 1 } else { -1 };
        }
        let scale = power_of_two_below(px.abs().max(py.abs()));
        (self.x, self.y) = (px * scale, py * scale);
    }

    /// The sum of the arguments added (NaN where a term was NaN or infinite).
    pub fn total(&self) -> f64 {
        self.y.atan2(self.x) + std::f64::consts::TAU * f64::from(self.turns)
    }
}

/// The power of two that brings `m` (finite, above zero) into [1, 2); 1 for zero, subnormals,
/// infinities and NaN (whose product `total` reports).
#[inline]
fn power_of_two_below(m: f64) -> f64 {
    let exponent = (m.to_bits() >> 52) & 0x7ff;
    if exponent == 0 || exponent == 0x7ff {
        return 1.0;
    }
    // 2^-(exponent - 1023): its biased exponent is 2046 - exponent, within [1, 2045].
    f64::from_bits((2046 - exponent) << 52)
}

fn net_edge(u: u32, v: u32) -> NetEdge {
    if u < v {
        (u, v, 1)
    } else {
        (v, u, -1)
    }
}

/// Whether the oriented edges of `faces` cancel: each `(a, b)` run as often as `(b, a)` (no
/// boundary: a closed surface, whose winding number is an integer off it).
pub fn net_boundary_is_empty(faces: &[[u32; 3]]) -> bool {
    use rayon::prelude::*;
    super::parallel::install(|| {
        let mut edges: Vec<NetEdge> =
            faces.par_iter().flat_map_iter(|&[a, b, c]| [net_edge(a, b), net_edge(b, c), net_edge(c, a)]).collect();
        edges.par_sort_unstable();
        cancel(edges).is_empty()
    })
}

/// Sums the counts of equal edges of a sorted list, dropping those that cancel.
fn cancel(sorted: Vec<NetEdge>) -> Vec<NetEdge> {
    let mut out: Vec<NetEdge> = Vec::with_capacity(sorted.len());
    for (lo, hi, net) in sorted {
        match out.last_mut() {
            Some(last) if last.0 == lo && last.1 == hi => last.2 += net,
            _ => out.push((lo, hi, net)),
        }
        if out.last().is_some_and(|e| e.2 == 0) {
            out.pop();
        }
    }
    out
}

/// Two sorted, cancelled boundaries' sum, sorted and cancelled.
fn merge(left: Vec<NetEdge>, right: Vec<NetEdge>) -> Vec<NetEdge> {
    let mut both = Vec::with_capacity(left.len() + right.len());
    let (mut l, mut r) = (left.into_iter().peekable(), right.into_iter().peekable());
    loop {
        let next = match (l.peek(), r.peek()) {
            (Some(a), Some(b)) => {
                if (a.0, a.1) <= (b.0, b.1) {
                    l.next()
                } else {
                    r.next()
                }
            }
            (Some(_), None) => l.next(),
            (None, Some(_)) => r.next(),
            (None, None) => break,
        };
        both.extend(next);
    }
    cancel(both)
}

/// A sheet of `n`×`n` squares of side `side` (two triangles each, counter-clockwise seen from +z)
/// at heights `height(x, y)`: the tests' open meshes.
#[cfg(test)]
pub(crate) fn grid_sheet(n: u32, side: f64, height: impl Fn(f64, f64) -> f64) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let mut vertices = Vec::new();
    for y in 0..=n {
        for x in 0..=n {
            let (fx, fy) = (x as f64 * side, y as f64 * side);
            vertices.push(DVec3::new(fx, fy, height(fx, fy)));
        }
    }
    let at = |x: u32, y: u32| y * (n + 1) + x;
    let mut faces = Vec::new();
    for y in 0..n {
        for x in 0..n {
            faces.push([at(x, y), at(x + 1, y), at(x + 1, y + 1)]);
            faces.push([at(x, y), at(x + 1, y + 1), at(x, y + 1)]);
        }
    }
    (vertices, faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mesh with its hierarchy, as `reference::TriangleSet` holds them.
    struct TestMesh {
        vertices: Vec<DVec3>,
        faces: Vec<[u32; 3]>,
        bvh: Bvh,
    }

    impl TestMesh {
        fn new(vertices: Vec<DVec3>, faces: Vec<[u32; 3]>) -> TestMesh {
            let boxes: Vec<Aabb> = faces.iter().map(|f| Aabb::of_points(f.map(|i| vertices[i as usize]))).collect();
            TestMesh { bvh: Bvh::build(&boxes), vertices, faces }
        }

        fn triangles(&self) -> Triangles<'_> {
            Triangles { bvh: &self.bvh, vertices: &self.vertices, faces: &self.faces }
        }

        fn tree(&self) -> WindingTree {
            WindingTree::build(&self.bvh, &self.faces)
        }

        fn triangle(&self, t: usize) -> [DVec3; 3] {
            self.faces[t].map(|i| self.vertices[i as usize])
        }
    }

    /// A unit cube's 12 triangles (outward), with the two on the top face left out when `open`.
    fn cube(open: bool) -> TestMesh {
        let vertices: Vec<DVec3> =
            (0..8).map(|k| DVec3::new((k & 1) as f64, ((k >> 1) & 1) as f64, ((k >> 2) & 1) as f64)).collect();
        let mut faces = vec![
            [0, 2, 1],
            [1, 2, 3],
            [0, 1, 5],
            [0, 5, 4],
            [1, 3, 7],
            [1, 7, 5],
            [3, 2, 6],
            [3, 6, 7],
            [2, 0, 4],
            [2, 4, 6],
        ];
        if !open {
            faces.extend([[4, 5, 7], [4, 7, 6]]);
        }
        TestMesh::new(vertices, faces)
    }

    /// A wavy open sheet of `n`×`n` squares over the unit square: many nodes, each with a
    /// boundary.
    fn sheet(n: u32) -> TestMesh {
        let (vertices, faces) = grid_sheet(n, 1.0 / n as f64, |x, y| 0.2 * (6.0 * x).sin() * (5.0 * y).cos());
        TestMesh::new(vertices, faces)
    }

    fn brute_force(set: &TestMesh, to_scene: &Affine, p: DVec3) -> f64 {
        let total: f64 = (0..set.faces.len())
            .map(|t| {
                let [a, b, c] = set.triangle(t).map(|v| to_scene.point(v) - p);
                twice_solid_angle(a, b, c)
            })
            .sum();
        total / (4.0 * std::f64::consts::PI)
    }

    fn points() -> Vec<DVec3> {
        // A deterministic scatter around the unit cube, near and far.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..400).map(|_| DVec3::new(next(), next(), next()) * 3.0 - DVec3::splat(1.0)).collect()
    }

    #[test]
    fn boundary_loops_are_the_components_and_each_is_a_cycle() {
        // Two squares' boundaries, interleaved, and a vertex of degree 4 (a figure eight) in the third.
        let edges = [
            [0, 1],
            [10, 11],
            [1, 2],
            [11, 12],
            [2, 3],
            [12, 10],
            [3, 0],
            [20, 21],
            [21, 22],
            [22, 20],
            [20, 23],
            [23, 24],
            [24, 20],
        ];
        let loops = boundary_loops(&edges);
        assert_eq!(
            loops,
            vec![
                vec![[0, 1], [1, 2], [2, 3], [3, 0]],
                vec![[10, 11], [11, 12], [12, 10]],
                vec![[20, 21], [21, 22], [22, 20], [20, 23], [23, 24], [24, 20]],
            ]
        );
        // The open cube's one hole, and a sheet's: one loop each, as many edges arriving as leaving.
        for set in [cube(true), sheet(6)] {
            let tree = set.tree();
            let span = tree.spans()[0];
            let root = &tree.edges()[span.first as usize..(span.first + span.count) as usize];
            let loops = boundary_loops(root);
            assert_eq!(loops.len(), 1);
            let mut balance = std::collections::HashMap::new();
            for &[a, b] in &loops[0] {
                *balance.entry(a).or_insert(0) += 1;
                *balance.entry(b).or_insert(0) -= 1;
            }
            assert!(balance.values().all(|&d| d == 0));
        }
    }

    #[test]
    fn a_closed_part_adds_nothing_and_the_tree_matches_brute_force() {
        for set in [cube(false), cube(true), sheet(24)] {
            let tree = set.tree();
            for p in points() {
                let (fast, brute) = (
                    tree.winding_number(set.triangles(), &Affine::IDENTITY, p, p),
                    brute_force(&set, &Affine::IDENTITY, p),
                );
                assert!((fast - brute).abs() < 1e-12, "{p}: {fast} against {brute}");
            }
        }
        // Inside and outside the closed cube: 1 and 0.
        let closed = cube(false);
        let tree = closed.tree();
        let w = |p: DVec3| tree.winding_number(closed.triangles(), &Affine::IDENTITY, p, p);
        assert!((w(DVec3::splat(0.5)) - 1.0).abs() < 1e-12);
        assert!(w(DVec3::splat(3.0)).abs() < 1e-12);
        // The closed cube's root has an empty boundary: a far point sums no term at all.
        assert_eq!(tree.spans()[0], Span { first: tree.spans()[0].first, count: 0 });
    }

    #[test]
    fn large_sheets_keep_boundaries_shorter_than_their_triangles() {
        let set = sheet(64);
        let tree = set.tree();
        let root = tree.spans()[0];
        assert_ne!(root.count, NO_CAP);
        // The sheet's rim: 4 · 64 edges, against 8192 triangles.
        assert_eq!(root.count, 4 * 64);
        let placed = Affine::from_rows(&[0.0, 2.0, 0.0, 5.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 3.0, -2.0]);
        let to_local = placed.inverse().expect("invertible");
        for p in points() {
            let scene = placed.point(p);
            let fast = tree.winding_number(set.triangles(), &placed, scene, to_local.point(scene));
            let brute = brute_force(&set, &placed, scene);
            assert!((fast - brute).abs() < 1e-11, "{p}: {fast} against {brute}");
        }
    }

    /// A fixed stream of numbers in [0, 1) (SplitMix64).
    fn stream(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    #[test]
    fn argument_sums_equal_sums_of_arctangents() {
        let mut next = stream(7);
        // Terms of every kind: anywhere, on and near both axes (±0 included), and of sizes from
        // 1e-200 to 1e200 (the product's scaling).
        let mut term = |k: usize| -> (f64, f64) {
            let (y, x) = (next() - 0.5, next() - 0.5);
            let size = 10f64.powf(next() * 400.0 - 200.0);
            let (y, x) = match k % 9 {
                0 => (0.0, x),
                1 => (-0.0, x),
                2 => (y, 0.0),
                3 => (y * 1e-17, -1.0),
                4 => (-y.abs() * 1e-17, -1.0),
                5 => (y * 1e-17, 1.0),
                _ => (y, x),
            };
            (y * size, x * size)
        };
        for length in [1, 2, 3, 10, 100, 1000] {
            for trial in 0..200 {
                let terms: Vec<(f64, f64)> = (0..length).map(|k| term(k * 31 + trial)).collect();
                let mut sum = ArgumentSum::default();
                for &(y, x) in &terms {
                    sum.add(y, x);
                }
                let expected: f64 = terms.iter().map(|&(y, x)| y.atan2(x)).sum();
                let error = (sum.total() - expected).abs();
                assert!(error <= 1e-14 * length as f64 + 1e-15, "{length} terms: {} against {expected}", sum.total());
            }
        }
    }

    #[test]
    fn argument_sums_count_every_turn() {
        // n equal steps of an angle just below π (and just above -π): the sum turns many times.
        for (angle, n) in [(3.0, 1000), (-3.1, 777), (std::f64::consts::PI - 1e-12, 64), (2.0, 3)] {
            let mut sum = ArgumentSum::default();
            for _ in 0..n {
                sum.add(angle.sin(), angle.cos());
            }
            let expected = angle * n as f64;
            assert!((sum.total() - expected).abs() < 1e-12 * n as f64, "{} against {expected}", sum.total());
        }
    }
}

//! The caps that close the holes of a one-instance scene's mesh, in f64 on the host: what the
//! GPU's exact winding query uploads (`closest::WindingCap`) and what the host's winding rays
//! (`trace::host_winding`) sum.

use glam::DVec3;

use super::instance::Placement;
use crate::geometry::winding::{boundary_loops, twice_solid_angle, NO_CAP};
use crate::gpu::records::{WindingCapEdge, WindingCapHole};

/// The most boundary edges a cap may have: a ray of the exact tier's winding query near every
/// hole tests and sums them all, where the hierarchy (`WindingScene`) sums a few nodes' boundaries.
pub const MAX_CAP_EDGES: usize = 4096;

/// How far one triangle's term of a winding number on the GPU may be from the CPU's: its f32
/// arctangent (an ulp of π, and the rounding of its arguments), over 4π, with a margin.
pub const WINDING_TERM_ERROR: f64 = 2e-7;
/// Added to the terms' bound: winding numbers on the GPU within this (and the terms' bound) of
/// 1/2 are decided on the CPU.
pub const WINDING_MARGIN: f64 = 1e-4;

/// A cap's holes (each its fan from the hole's mean corner over its edges) and their edges,
/// corners in the mesh's frame and the scene's; `mirrored` where the placement mirrors (the
/// mesh's winding number is then the negated sum of the caps' solid angles).
pub struct CapGeometry {
    pub holes: Vec<WindingCapHole>,
    pub edges: Vec<WindingCapEdge>,
    pub mirrored: bool,
}

impl CapGeometry {
    /// Winding numbers within this of 1/2 (the mesh's crossings plus the caps') are decided by
    /// the whole winding number instead.
    pub fn band(&self) -> f64 {
        band_of(self.edges.len())
    }

    /// Whether the caps' winding number about every point within `reach` of `center` (the
    /// scene's frame) that a straight segment from `center` meeting no fan joins stays at most
    /// `limit` in size (the caller's to know which points those are: across a fan the winding
    /// number jumps by 1; a convex box no fan meets holds only such points). Each hole adds the
    /// smaller of two bounds: its fan's area over the least squared distance to it
    /// (`fan_winding_bound`'s), or its winding number about `center` and how far it can move
    /// within `reach`. The solid angle of a surface is harmonic off it, its gradient the
    /// Biot–Savart integral over the surface's boundary (the hole's loop of edges; the fan's
    /// spokes cancel): at most the loop's length over the least squared distance to it, over 4π
    /// for the winding number.
    pub fn winding_stays_within(&self, center: DVec3, reach: f64, limit: f64) -> bool {
        let four_pi = 4.0 * std::f64::consts::PI;
        let mut total = 0.0;
        for hole in &self.holes {
            let apex = DVec3::from_array(hole.apex_scene);
            let gap = apex.distance(center) - reach - hole.radius_scene;
            let from_area = if gap > 0.0 { hole.area_scene / (four_pi * gap * gap) } else { f64::INFINITY };
            if from_area > 0.01 {
                let edges = &self.edges[hole.first as usize..(hole.first + hole.count) as usize];
                let corners = |e: &WindingCapEdge| (DVec3::from_array(e.a_scene), DVec3::from_array(e.b_scene));
                let (length, nearest) =
                    edges.iter().map(corners).fold((0.0, f64::INFINITY), |(length, nearest), (a, b)| {
                        (length + a.distance(b), nearest.min(segment_distance(center, a, b)))
                    });
                let gap = nearest - reach;
                let moved = if gap > 0.0 { reach * length / (four_pi * gap * gap) } else { f64::INFINITY };
                if total + from_area.min(moved) > limit {
                    // The arctangents would not bring it within (most boxes near a fan).
                    return false;
                }
                let twice_angle: f64 = edges
                    .iter()
                    .map(corners)
                    .map(|(a, b)| twice_solid_angle(apex - center, a - center, b - center))
                    .sum();
                // The winding number at `center` to within its rounding (f64: far below 1e-9).
                total += from_area.min(twice_angle.abs() / four_pi + moved + 1e-9);
            } else {
                total += from_area;
            }
            if total > limit {
                return false;
            }
        }
        true
    }
}

/// The distance from `p` to the segment a–b.
fn segment_distance(p: DVec3, a: DVec3, b: DVec3) -> f64 {
    let ab = b - a;
    let along = ab.length_squared();
    let t = if along > 0.0 { ((p - a).dot(ab) / along).clamp(0.0, 1.0) } else { 0.0 };
    p.distance(a + t * ab)
}

/// The cap of the scene's one instance, or None: several instances (a ray's crossings would
/// need telling apart), an instance no ray meets (mask 0), or a boundary of more than
/// `MAX_CAP_EDGES` edges (the root keeps none, or too many to sum per ray).
pub fn cap_geometry(placements: &[Placement]) -> Option<CapGeometry> {
    let [placement] = placements else { return None };
    // Spheres have no holes (and no winding tree).
    if placement.mask == 0 || placement.triangles.is_spheres() {
        return None;
    }
    let set = &placement.triangles;
    let tree = set.winding_tree();
    let span = tree.spans().first()?;
    if span.count == NO_CAP || span.count as usize > MAX_CAP_EDGES {
        return None;
    }
    let first = span.first as usize;
    let loops = boundary_loops(&tree.edges()[first..first + span.count as usize]);
    let in_scene = |v: DVec3| placement.to_scene.point(v);
    let mut holes = Vec::with_capacity(loops.len());
    let mut edges = Vec::with_capacity(span.count as usize);
    for edge_loop in &loops {
        let corners = |[u, v]: [u32; 2]| (set.vertices[u as usize], set.vertices[v as usize]);
        let apex = edge_loop.iter().map(|&e| corners(e).0).sum::<DVec3>() / edge_loop.len() as f64;
        let apex_scene = in_scene(apex);
        let (mut radius, mut radius_scene, mut area_scene) = (0.0f64, 0.0f64, 0.0f64);
        holes.push(WindingCapHole { first: edges.len() as u32, count: edge_loop.len() as u32, ..Default::default() });
        for &e in edge_loop {
            let (a, b) = corners(e);
            let (a_scene, b_scene) = (in_scene(a), in_scene(b));
            radius = radius.max(a.distance(apex)).max(b.distance(apex));
            radius_scene = radius_scene.max(a_scene.distance(apex_scene)).max(b_scene.distance(apex_scene));
            area_scene += 0.5 * (a_scene - apex_scene).cross(b_scene - apex_scene).length();
            edges.push(WindingCapEdge {
                a: a.to_array(),
                b: b.to_array(),
                a_scene: a_scene.to_array(),
                b_scene: b_scene.to_array(),
            });
        }
        // Grown past their rounding: a ray trusts them to pass a fan over.
        let grow = 1.0 + 1e-9;
        let hole = holes.last_mut().expect("pushed");
        hole.apex = apex.to_array();
        hole.apex_scene = apex_scene.to_array();
        (hole.radius, hole.radius_scene, hole.area_scene) = (radius * grow, radius_scene * grow, area_scene * grow);
    }
    let mirrored = placement.to_scene.linear.determinant() < 0.0;
    Some(CapGeometry { holes, edges, mirrored })
}

pub fn band_of(edge_count: usize) -> f64 {
    WINDING_TERM_ERROR * edge_count as f64 + WINDING_MARGIN
}

#[cfg(test)]
mod tests {
    use super::{twice_solid_angle, CapGeometry};
    use crate::gpu::records::{WindingCapEdge, WindingCapHole};
    use glam::DVec3;

    /// A cap over a hole: a regular `sides`-gon of `radius` in the plane z = `z` about (x, 0, z).
    fn polygon(sides: usize, radius: f64, [x, z]: [f64; 2]) -> (WindingCapHole, Vec<WindingCapEdge>) {
        let corner = |k: usize| {
            let a = k as f64 * std::f64::consts::TAU / sides as f64;
            [x + radius * a.cos(), radius * a.sin(), z]
        };
        let edges = (0..sides)
            .map(|k| WindingCapEdge { a: corner(k), b: corner(k + 1), a_scene: corner(k), b_scene: corner(k + 1) })
            .collect();
        let area = sides as f64 * 0.5 * radius * radius * (std::f64::consts::TAU / sides as f64).sin();
        let hole = WindingCapHole {
            apex: [x, 0.0, z],
            apex_scene: [x, 0.0, z],
            radius,
            radius_scene: radius,
            area_scene: area,
            first: 0,
            count: sides as u32,
        };
        (hole, edges)
    }

    /// Two holes: a 12-gon of radius 1 about the origin, and a small square (radius 0.1) at
    /// (3, 0, 0.5), whose area's bound alone serves at a distance.
    fn two_holes() -> CapGeometry {
        let (first, mut edges) = polygon(12, 1.0, [0.0, 0.0]);
        let (mut second, more) = polygon(4, 0.1, [3.0, 0.5]);
        second.first = edges.len() as u32;
        edges.extend(more);
        CapGeometry { holes: vec![first, second], edges, mirrored: false }
    }

    fn winding(cap: &CapGeometry, p: DVec3) -> f64 {
        let sum: f64 = cap
            .holes
            .iter()
            .flat_map(|hole| {
                let apex = DVec3::from_array(hole.apex);
                cap.edges[hole.first as usize..(hole.first + hole.count) as usize]
                    .iter()
                    .map(move |e| twice_solid_angle(apex - p, DVec3::from_array(e.a) - p, DVec3::from_array(e.b) - p))
            })
            .sum();
        sum / (4.0 * std::f64::consts::PI)
    }

    /// Wherever the bound says the winding number stays within a limit about a ball off the
    /// fans, it does at every sampled point of the ball's surface (where a harmonic function
    /// takes its extremes: the points nearest each apex and corner, and random ones) and inside;
    /// and it says so for many balls away from the fans. It fails where either distance in the
    /// bound forgets the ball's reach, where the gradient's term is dropped, or where the area's
    /// bound alone serves near a hole.
    #[test]
    fn the_caps_winding_stays_within_where_the_bound_says() {
        let cap = two_holes();
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let off_fans = |c: DVec3, reach: f64| {
            let off_first = c.z.abs() > reach || c.truncate().length() > 1.0 + reach;
            let off_second =
                (c.z - 0.5).abs() > reach || (c.truncate() - glam::DVec2::new(3.0, 0.0)).length() > 0.1 + reach;
            off_first && off_second
        };
        for limit in [0.02, 0.05, 0.1, 0.2, 0.3, 0.45] {
            let (mut said, mut asked) = (0, 0);
            for _ in 0..3000 {
                let center = DVec3::new(8.0 * uniform() - 3.0, 6.0 * uniform() - 3.0, 4.0 * uniform() - 2.0);
                let reach = 0.02 + 1.5 * uniform();
                if !off_fans(center, reach) {
                    continue;
                }
                asked += 1;
                if !cap.winding_stays_within(center, reach, limit) {
                    continue;
                }
                said += 1;
                // The ball's points nearest each hole's apex and each corner of its loop, then
                // random ones on its surface and inside.
                let toward = cap.holes.iter().map(|h| h.apex).chain(cap.edges.iter().map(|e| e.a));
                let toward: Vec<DVec3> = toward.map(|q| (DVec3::from_array(q) - center).normalize_or_zero()).collect();
                for k in 0..toward.len() + 60 {
                    let d = toward.get(k).copied().unwrap_or_else(|| {
                        DVec3::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5).normalize_or_zero()
                    });
                    let p = center + d * reach * if k % 3 == 0 && k >= toward.len() { uniform() } else { 1.0 };
                    let w = winding(&cap, p).abs();
                    assert!(w <= limit, "{w} > {limit} at {p} in the ball about {center} of {reach}");
                }
            }
            // Useful: most balls at the grid's limit, some even at the smallest.
            let share = if limit == 0.45 { 0.5 } else { 0.05 };
            assert!(said as f64 > share * asked as f64, "limit {limit}: the bound held for {said} of {asked} balls");
        }
    }
}

//! The caps that close the holes of a one-instance scene's mesh, in f64 on the host: what the
//! GPU's exact winding query uploads (`closest::WindingCap`) and what the host's winding rays
//! (`trace::host_winding`) sum.

use glam::DVec3;

use super::instance::Placement;
use crate::geometry::winding::{boundary_loops, NO_CAP};
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

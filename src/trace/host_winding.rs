//! `contains` by winding number on the host through one ray a point, as the GPU's exact winding
//! query does it (shaders/exact.glsl `add_cap`): the mesh less the caps that close its holes has
//! no boundary, so its winding number about a point is the signed count of a ray's crossings
//! with it, and the mesh's is that plus the caps' solid angles. A ray and a few fans cost far less
//! than the whole winding number (the hierarchy's sum, `WindingTree`), which then decides only the
//! points whose sum lies near 1/2.

use std::f64::consts::PI;

use glam::DVec3;

use crate::geometry::precision::{watertight_edges, Ray64, ShearedRay};
use crate::geometry::reference::ReferenceTracer;
use crate::geometry::winding::{ArgumentSum, SolidAngleTerms};
use crate::gpu::records::{WindingCapEdge, WindingCapHole};
use crate::scene::{CapGeometry, Placement};
use crate::trace::request::Crossings;

/// A hole whose winding number's bound is at most this is passed over at first (the GPU's
/// CAP_SKIP_BOUND): its bound is summed instead, and its fan only where the bounds passed over
/// could bring the sum within the band about 1/2.
const CAP_SKIP_BOUND: f64 = 0.08;

/// The winding query of the point `p` (scene frame) of the scene's one instance `placement`,
/// closed by `cap`: its ray's crossings (signed sum and whether `p` lies on a surface, as the
/// GPU's `Crossings`) and the caps' winding number about `p` (NaN where `p` lies within
/// rounding of a fan); `trace::host_tiers::mark_by_crossings` decides from them. The ray runs
/// to `ray_end`'s distance, past which `ray_end`'s count of crossings is known (infinity and 0:
/// the whole ray).
pub fn winding_ray(
    tracer: &ReferenceTracer,
    placement: &Placement,
    cap: &CapGeometry,
    band: f64,
    p: DVec3,
    (direction, ray_end): (DVec3, (f64, i32)),
) -> (Crossings, f64) {
    let count = signed_crossings_with_caps(tracer, placement, cap, p, (direction, ray_end));
    (Crossings(count << 1), caps_winding(cap, band, p, count))
}

/// The signed count of crossings of the ray from `p` along `direction` with the instance
/// `placement` less the fans of `cap`, to `ray_end`'s distance, plus `ray_end`'s count beyond.
pub fn signed_crossings_with_caps(
    tracer: &ReferenceTracer,
    placement: &Placement,
    cap: &CapGeometry,
    p: DVec3,
    (direction, (tmax, beyond)): (DVec3, (f64, i32)),
) -> i32 {
    let ray = Ray64 { origin: p, direction, tmin: 0.0, tmax };
    let mut count = tracer.signed_crossings(&ray) + beyond;
    // The mesh's own sheared ray, as the tracer tests its triangles: a ray through a boundary
    // edge meets either the mesh or the fan.
    let local = ShearedRay::new(ray.transformed(&placement.to_local));
    for hole in cap.holes.iter().filter(|hole| may_cross_fan(&local.ray, hole)) {
        count -= fan_crossings(&local, hole, edges_of(cap, hole));
    }
    count
}

fn edges_of<'a>(cap: &'a CapGeometry, hole: &WindingCapHole) -> &'a [WindingCapEdge] {
    &cap.edges[hole.first as usize..(hole.first + hole.count) as usize]
}

/// The caps' winding number about `p` (scene frame) where the count of crossings from it is
/// `count` (NaN where `p` lies within rounding of a fan). The holes whose bound is small are
/// summed only where they could bring the sum within `band` of 1/2.
pub fn caps_winding(cap: &CapGeometry, band: f64, p: DVec3, count: i32) -> f64 {
    let sign = if cap.mirrored { -1.0 } else { 1.0 };
    let (mut twice_angle, mut unsure, mut passed_over) = (0.0, false, 0.0);
    for hole in &cap.holes {
        let bound = fan_winding_bound(p, hole);
        if bound <= CAP_SKIP_BOUND {
            passed_over += bound;
            continue;
        }
        let (angle, near) = fan_angle(p, hole, edges_of(cap, hole));
        (twice_angle, unsure) = (twice_angle + angle, unsure || near);
    }
    let near_half = (f64::from(count) + sign * twice_angle / (4.0 * PI) - 0.5).abs();
    if passed_over > 0.0 && near_half <= band + passed_over {
        // The holes passed over (their bounds are the same again), summed after all.
        for hole in cap.holes.iter().filter(|hole| fan_winding_bound(p, hole) <= CAP_SKIP_BOUND) {
            let (angle, near) = fan_angle(p, hole, edges_of(cap, hole));
            (twice_angle, unsure) = (twice_angle + angle, unsure || near);
        }
    }
    if unsure {
        f64::NAN
    } else {
        sign * twice_angle / (4.0 * PI)
    }
}

/// Whether the ray (the mesh's frame) may cross the fan of `hole`: the fan lies within its
/// radius of its apex, so a line passing farther (past a margin far beyond rounding) cannot.
fn may_cross_fan(ray: &Ray64, hole: &WindingCapHole) -> bool {
    let apex = DVec3::from_array(hole.apex);
    let gap = (apex - ray.origin).cross(ray.direction).length() / ray.direction.length();
    let reach = hole.radius * (1.0 + 1e-6) + 1e-9 * (apex.length() + ray.origin.length());
    // NaN (a degenerate ray or hole) may cross.
    gap <= reach || gap.is_nan()
}

/// The signed crossings of the fan from `hole`'s apex over its `edges` (as `signed_crossings`
/// counts the mesh's: +1 through a triangle's back).
fn fan_crossings(ray: &ShearedRay, hole: &WindingCapHole, edges: &[WindingCapEdge]) -> i32 {
    let apex = DVec3::from_array(hole.apex);
    edges
        .iter()
        .filter_map(|e| watertight_edges(ray, apex, DVec3::from_array(e.a), DVec3::from_array(e.b), false))
        .map(|hit| if hit.front { -1 } else { 1 })
        .sum()
}

/// A bound on the size of `hole`'s winding number about `p`: every point of its fan lies at
/// least (distance to the apex - radius) away, so each triangle's solid angle is at most its
/// area over that squared. Infinite where `p` lies within the radius.
pub fn fan_winding_bound(p: DVec3, hole: &WindingCapHole) -> f64 {
    let gap = DVec3::from_array(hole.apex_scene).distance(p) - hole.radius_scene;
    if gap > 0.0 {
        hole.area_scene / (4.0 * PI * gap * gap)
    } else {
        f64::INFINITY
    }
}

/// Twice the solid angle of `hole`'s fan about `p` (scene frame), and whether `p` lies within
/// rounding of one of its triangles' insides (where the angle jumps by 4π). The triangles'
/// arctangents are summed as one (`ArgumentSum`).
fn fan_angle(p: DVec3, hole: &WindingCapHole, edges: &[WindingCapEdge]) -> (f64, bool) {
    let apex = DVec3::from_array(hole.apex_scene) - p;
    let apex_length = apex.length();
    let (mut sum, mut near) = (ArgumentSum::default(), false);
    for e in edges {
        let (a, b) = (DVec3::from_array(e.a_scene) - p, DVec3::from_array(e.b_scene) - p);
        let terms = SolidAngleTerms::of(apex, a, b, apex_length);
        sum.add(terms.numerator, terms.denominator);
        near |= terms.near_inside();
    }
    (2.0 * sum.total(), near)
}

//! Double-precision ray–triangle geometry shared by the f64 tiers: the watertight test with its
//! tie-break rule (the `"exact"` tier evaluates the same arithmetic in `shaders/exact.glsl`), the
//! plane solve that refines f32 hits, and instance transforms in f64.
//!
//! The watertight test is Woop, Benthin and Wald, "Watertight Ray/Triangle Intersection" (JCGT
//! 2013), evaluated in f64 from the start, so its f32-to-f64 fallback is already taken. Its edge
//! functions depend on the two vertices of an edge alone, and the two triangles sharing an edge
//! compute exact negations of each other's value (products commute, `a - b == -(b - a)` in IEEE
//! arithmetic), so no ray slips between them. A ray exactly on an edge or vertex makes some edge
//! functions zero in both neighbours; a half-plane rule on the edge's projected direction (the
//! top-left rule of rasterizers) gives each such edge to exactly one side, so the ray reports one
//! triangle, never two.

use glam::{DMat3, DVec2, DVec3};

/// Which triangles a query ignores by the side the ray meets. "Front" is the side the hit's
/// `normal` points to (right-handed in the triangle's winding, flipped by mirroring instances).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Cull {
    #[default]
    None,
    Back,
    Front,
}

impl Cull {
    pub fn parse(name: Option<&str>) -> crate::error::Result<Cull> {
        match name {
            None => Ok(Cull::None),
            Some("back") => Ok(Cull::Back),
            Some("front") => Ok(Cull::Front),
            Some(other) => {
                Err(crate::error::invalid_value(format!("cull must be 'back', 'front' or None, got {other:?}")))
            }
        }
    }

    /// Whether a hit on the `front` (or back) side survives this culling.
    pub fn keeps(self, front: bool) -> bool {
        match self {
            Cull::None => true,
            Cull::Back => front,
            Cull::Front => !front,
        }
    }
}

/// An affine map `p -> linear * p + offset`, in f64.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Affine {
    pub linear: DMat3,
    pub offset: DVec3,
}

impl Affine {
    pub const IDENTITY: Affine = Affine { linear: DMat3::IDENTITY, offset: DVec3::ZERO };

    /// From a row-major 3×4 matrix acting on column vectors.
    pub fn from_rows(m: &[f64; 12]) -> Affine {
        Affine {
            linear: DMat3::from_cols(
                DVec3::new(m[0], m[4], m[8]),
                DVec3::new(m[1], m[5], m[9]),
                DVec3::new(m[2], m[6], m[10]),
            ),
            offset: DVec3::new(m[3], m[7], m[11]),
        }
    }

    /// Row-major 3×4, as Vulkan's instance transform holds it.
    pub fn to_rows_f32(&self) -> [f32; 12] {
        let (l, o) = (self.linear, self.offset);
        let rows = [l.row(0), l.row(1), l.row(2)];
        let mut out = [0f32; 12];
        for r in 0..3 {
            out[4 * r] = rows[r].x as f32;
            out[4 * r + 1] = rows[r].y as f32;
            out[4 * r + 2] = rows[r].z as f32;
            out[4 * r + 3] = o[r] as f32;
        }
        out
    }

    pub fn point(&self, p: DVec3) -> DVec3 {
        self.linear * p + self.offset
    }

    pub fn vector(&self, v: DVec3) -> DVec3 {
        self.linear * v
    }

    /// The inverse map, or None when the linear part is singular (or nearly: its determinant is
    /// zero or not finite).
    pub fn inverse(&self) -> Option<Affine> {
        let det = self.linear.determinant();
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let linear = self.linear.inverse();
        Some(Affine { linear, offset: -(linear * self.offset) })
    }
}

/// A ray in f64: `origin + t * direction` for t in [tmin, tmax].
#[derive(Clone, Copy, Debug)]
pub struct Ray64 {
    pub origin: DVec3,
    pub direction: DVec3,
    pub tmin: f64,
    pub tmax: f64,
}

impl Ray64 {
    /// This ray in the frame that `to_local` maps to; `t` keeps its meaning.
    pub fn transformed(&self, to_local: &Affine) -> Ray64 {
        Ray64 { origin: to_local.point(self.origin), direction: to_local.vector(self.direction), ..*self }
    }
}

/// A ray prepared for Woop's test: the axis permutation and shear that map it to +z.
#[derive(Clone, Copy, Debug)]
pub struct ShearedRay {
    pub ray: Ray64,
    k: [usize; 3],
    shear: DVec3,
}

impl ShearedRay {
    pub fn new(ray: Ray64) -> ShearedRay {
        let d = ray.direction;
        let abs = d.abs();
        let kz = if abs.x >= abs.y && abs.x >= abs.z {
            0
        } else if abs.y >= abs.z {
            1
        } else {
            2
        };
        let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
        // Keep the winding: a negative dominant axis mirrors the projection.
        if d[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        ShearedRay { ray, k: [kx, ky, kz], shear: DVec3::new(d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]) }
    }

    /// A vertex relative to the origin, sheared: (x, y) in the ray's projection plane, z along it.
    fn project(&self, v: DVec3) -> DVec3 {
        let p = v - self.ray.origin;
        let [kx, ky, kz] = self.k;
        DVec3::new(p[kx] - self.shear.x * p[kz], p[ky] - self.shear.y * p[kz], self.shear.z * p[kz])
    }
}

/// A hit on one triangle: `t` along the ray and barycentrics (u weights b, v weights c).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleHit {
    pub t: f64,
    pub u: f64,
    pub v: f64,
    /// Whether the ray meets the side `cross(b - a, c - a)` points to (a positive determinant).
    pub front: bool,
}

/// Whether an edge whose edge function is exactly zero belongs to this triangle: its projected
/// direction, in the triangle's normalized winding, must point into the upper half-plane (or along
/// +x). The neighbour across the edge sees the opposite direction and so the opposite answer.
fn owns_edge(direction: DVec2) -> bool {
    direction.y > 0.0 || (direction.y == 0.0 && direction.x > 0.0)
}

/// The watertight test with its tie-break: a hit when the ray meets the closed triangle (a, b, c)
/// within [tmin, tmax], rays through shared edges and vertices reporting exactly one of the
/// triangles there. Degenerate triangles and rays in the triangle's plane never hit.
pub fn watertight(ray: &ShearedRay, a: DVec3, b: DVec3, c: DVec3) -> Option<TriangleHit> {
    watertight_edges(ray, a, b, c, false)
}

/// `watertight`, or with `closed` edges: a ray through a shared edge or vertex meets every
/// triangle there (contacts, the exact shader's CLOSED_EDGES).
pub fn watertight_edges(ray: &ShearedRay, a: DVec3, b: DVec3, c: DVec3, closed: bool) -> Option<TriangleHit> {
    let (pa, pb, pc) = (ray.project(a), ray.project(b), ray.project(c));
    // Edge functions: u for edge b→c, v for c→a, w for a→b.
    let u = pc.x * pb.y - pc.y * pb.x;
    let v = pa.x * pc.y - pa.y * pc.x;
    let w = pb.x * pa.y - pb.y * pa.x;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let sign = if det > 0.0 { 1.0 } else { -1.0 };
    let edges = [(u, pb, pc), (v, pc, pa), (w, pa, pb)];
    for (f, from, to) in edges {
        if f == 0.0 && !closed && !owns_edge(sign * (to.truncate() - from.truncate())) {
            return None;
        }
    }
    let t = (u * pa.z + v * pb.z + w * pc.z) / det;
    if !(t >= ray.ray.tmin && t <= ray.ray.tmax) {
        return None;
    }
    Some(TriangleHit { t, u: v / det, v: w / det, front: det > 0.0 })
}

/// Where the ray meets the plane of (a, b, c), with barycentrics of that point, whether or not it
/// lies inside; None for a ray parallel to the plane or a degenerate triangle. Refines a hit that
/// f32 traversal already found.
pub fn plane_hit(ray: &Ray64, a: DVec3, b: DVec3, c: DVec3) -> Option<TriangleHit> {
    let (e1, e2) = (b - a, c - a);
    let p = ray.direction.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let s = ray.origin - a;
    let q = s.cross(e1);
    // det = -dot(direction, cross(e1, e2)): positive when the ray meets the normal's side.
    Some(TriangleHit { t: e2.dot(q) / det, u: s.dot(p) / det, v: ray.direction.dot(q) / det, front: det > 0.0 })
}

/// Unit geometric normal of the triangle as placed in the world, right-handed in its winding
/// (`to_local` maps world to the triangle's frame). `cross(M e1, M e2) = det(M) M^-T cross(e1, e2)`,
/// so a mirroring placement flips the normal with the winding, as on the GPU.
pub fn world_normal(to_local: &Affine, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let sign = to_local.linear.determinant().signum();
    (sign * (to_local.linear.transpose() * (b - a).cross(c - a))).normalize()
}

/// The two roots (near, far) of `ray`'s line with the sphere (`center`, `radius`), in f64, or
/// None where the line misses it: Haines et al.'s form (Ray Tracing Gems, ch. 7), as the fast
/// tier's shaders take it in f32 (common.glsl `sphere_hit`): the discriminant from the line's
/// closest point to the centre, the nearer root from the farther. A tangent line has one root
/// twice.
pub fn sphere_roots(ray: &Ray64, center: DVec3, radius: f64) -> Option<(f64, f64)> {
    let f = ray.origin - center;
    let d = ray.direction;
    let a = d.dot(d);
    let b = -f.dot(d);
    let closest = f + (b / a) * d;
    let r2 = radius * radius;
    let discriminant = r2 - closest.dot(closest);
    if discriminant.is_nan() || discriminant < 0.0 {
        return None;
    }
    let q = b + if b >= 0.0 { 1.0 } else { -1.0 } * (a * discriminant).sqrt();
    let t0 = if q != 0.0 { (f.dot(f) - r2) / q } else { 0.0 };
    let t1 = q / a;
    Some((t0.min(t1), t0.max(t1)))
}

/// The outward unit normal, in the scene's frame, of the sphere (`center`, `radius`) of a set
/// placed by `to_local`'s inverse, at `local` (a point of it in the set's frame).
pub fn sphere_normal(to_local: &Affine, center: DVec3, radius: f64, local: DVec3) -> DVec3 {
    (to_local.linear.transpose() * ((local - center) / radius)).normalize()
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb { min: DVec3::INFINITY, max: DVec3::NEG_INFINITY };

    pub fn of_points(points: impl IntoIterator<Item = DVec3>) -> Aabb {
        points.into_iter().fold(Aabb::EMPTY, |b, p| Aabb { min: b.min.min(p), max: b.max.max(p) })
    }

    /// The box of a triangle's three corners.
    #[inline]
    pub fn of_corners([a, b, c]: [DVec3; 3]) -> Aabb {
        Aabb { min: a.min(b).min(c), max: a.max(b).max(c) }
    }

    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.min(other.min), max: self.max.max(other.max) }
    }

    pub fn center(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }

    pub fn extent(&self) -> DVec3 {
        (self.max - self.min).max(DVec3::ZERO)
    }

    /// This box grown by `pad` on every side.
    /// Whether `p` lies in the box (its faces included).
    /// The distance from `p` to the box (0 inside it).
    pub fn distance_to(&self, p: DVec3) -> f64 {
        (self.min - p).max(p - self.max).max(DVec3::ZERO).length()
    }

    pub fn contains(&self, p: DVec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }

    pub fn padded(&self, pad: f64) -> Aabb {
        Aabb { min: self.min - DVec3::splat(pad), max: self.max + DVec3::splat(pad) }
    }

    /// The box in f32, rounded outward (`round_outward`) so that it holds this one whole: min xyz,
    /// then max xyz (the layout of `VkAabbPositionsKHR`).
    pub fn outward_f32(&self) -> [f32; 6] {
        let (lo, hi) =
            (self.min.to_array().map(|v| round_outward(v, true)), self.max.to_array().map(|v| round_outward(v, false)));
        [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]]
    }

    /// The box holding this one after an affine map.
    pub fn transformed(&self, map: &Affine) -> Aabb {
        Aabb::of_points((0..8).map(|k| {
            map.point(DVec3::new(
                if k & 1 == 0 { self.min.x } else { self.max.x },
                if k & 2 == 0 { self.min.y } else { self.max.y },
                if k & 4 == 0 { self.min.z } else { self.max.z },
            ))
        }))
    }

    /// Entry distance of the ray into the box within [tmin, tmax], or None. A NaN slab (0 * inf:
    /// an origin on one of the box's faces with a direction along it) counts as inside that
    /// slab: conservative (`f64::min` would drop the NaN and take the other side's infinity).
    pub fn entry(&self, ray: &Ray64, inverse_direction: DVec3) -> Option<f64> {
        let t0 = (self.min - ray.origin) * inverse_direction;
        let t1 = (self.max - ray.origin) * inverse_direction;
        let (mut enter, mut exit) = (ray.tmin, ray.tmax);
        for axis in 0..3 {
            let (a, b) = (t0[axis], t1[axis]);
            if !(a.is_nan() || b.is_nan()) {
                enter = enter.max(a.min(b));
                exit = exit.min(a.max(b));
            }
        }
        (enter <= exit).then_some(enter)
    }
}

/// A power of two `s` that brings `m` (> 0) within [2^-250, 2^250] (1 where it already is):
/// Ericson's test multiplies four lengths, which overflows past 2^256 (a point 1e155 from a unit
/// triangle) and underflows below 2^-256 (a triangle 1e-80 across); squared distances of a
/// search scaled so stay within f64 too. Scaling by a power of two is exact, so where nothing
/// overflowed the answer is the same bit for bit (shaders/point_triangle.glsl `length_scale` is
/// the same loop). Points farther than about 2^250 times a triangle's size keep their distance
/// to f64's precision, but the products of four then lose the point's offset along the triangle.
pub fn length_scale(m: f64) -> f64 {
    const BIG: f64 = 1.809_251_394_333_065_6e75; // 2^250
    const SMALL: f64 = 5.527_147_875_260_445e-76; // 2^-250
    let mut s = 1.0;
    if !m.is_finite() {
        return s;
    }
    while m * s > BIG {
        s *= SMALL;
    }
    while m * s > 0.0 && m * s < SMALL {
        s *= BIG;
    }
    s
}

/// `n / d` for `0 <= n <= d`, 0 where `d` is 0: the parameter along an edge whose two end tests
/// both came out 0 (a point far off it, perpendicular, rounded), where every point of it is as near.
fn fraction(n: f64, d: f64) -> f64 {
    if d > 0.0 {
        n / d
    } else {
        0.0
    }
}

/// The point of segment (a, b) closest to `p`, with its squared distance (in units scaled by `s`).
fn closest_on_segment(p: DVec3, a: DVec3, b: DVec3, s: f64) -> (DVec3, f64) {
    let (ab, ap) = ((b - a) * s, (p - a) * s);
    let t = fraction(ab.dot(ap).max(0.0), ab.dot(ab)).min(1.0);
    let q = a + (b - a) * t;
    (q, ((q - p) * s).length_squared())
}

/// The point of a triangle without area (a repeated corner, or corners on one line) closest to
/// `p`: the nearest of its edges' (the first of equals). Ericson's regions assume a face: on a
/// segment they divide 0 by 0 or pick the wrong corner.
fn closest_on_edges(p: DVec3, a: DVec3, b: DVec3, c: DVec3, s: f64) -> DVec3 {
    let mut best = closest_on_segment(p, a, b, s);
    for (from, to) in [(b, c), (c, a)] {
        let candidate = closest_on_segment(p, from, to, s);
        if candidate.1 < best.1 {
            best = candidate;
        }
    }
    best.0
}

/// The point of triangle (a, b, c) closest to `p` (Ericson, "Real-Time Collision Detection",
/// 5.1.5: by the Voronoi region of `p` among the triangle's vertices, edges and face), its lengths
/// scaled by a power of two (`length_scale`) so that its products of four neither overflow nor
/// underflow; a triangle without area by its edges.
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let m = ab.abs().max(ac.abs()).max(ap.abs()).max_element();
    let s = length_scale(m);
    let (sab, sac, sap) = (ab * s, ac * s, ap * s);
    if sab.cross(sac) == DVec3::ZERO {
        return closest_on_edges(p, a, b, c, s);
    }
    let (d1, d2) = (sab.dot(sap), sac.dot(sap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = (p - b) * s;
    let (d3, d4) = (sab.dot(bp), sac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * fraction(d1, d1 - d3);
    }
    let cp = (p - c) * s;
    let (d5, d6) = (sab.dot(cp), sac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * fraction(d2, d2 - d6);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * fraction(d4 - d3, (d4 - d3) + (d5 - d6));
    }
    let sum = va + vb + vc;
    if !(sum > 0.0 && sum.is_finite()) {
        // A sliver whose face rounds away: its edges are as near as anything of it.
        return closest_on_edges(p, a, b, c, s);
    }
    let denominator = 1.0 / sum;
    a + ab * (vb * denominator) + ac * (vc * denominator)
}

/// The f32 nearest to `v` on the outside of a box: below it for a minimum, above for a maximum.
pub fn round_outward(v: f64, is_min: bool) -> f32 {
    let f = v as f32;
    match (is_min, (f as f64).partial_cmp(&v)) {
        (true, Some(std::cmp::Ordering::Greater)) => f.next_down(),
        (false, Some(std::cmp::Ordering::Less)) => f.next_up(),
        _ => f,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(o: [f64; 3], d: [f64; 3]) -> ShearedRay {
        ShearedRay::new(Ray64 {
            origin: DVec3::from_array(o),
            direction: DVec3::from_array(d),
            tmin: 0.0,
            tmax: f64::INFINITY,
        })
    }

    fn v(x: f64, y: f64, z: f64) -> DVec3 {
        DVec3::new(x, y, z)
    }

    #[test]
    fn hits_the_inside_with_vulkan_barycentrics() {
        let (a, b, c) = (v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0));
        let hit = watertight(&ray([0.25, 0.5, 2.0], [0.0, 0.0, -1.0]), a, b, c).unwrap();
        assert_eq!(hit, TriangleHit { t: 2.0, u: 0.25, v: 0.5, front: true });
        // Back faces too, with the same barycentrics.
        let back = watertight(&ray([0.25, 0.5, -2.0], [0.0, 0.0, 1.0]), a, b, c).unwrap();
        assert_eq!(back, TriangleHit { front: false, ..hit });
        assert!(watertight(&ray([0.75, 0.5, 2.0], [0.0, 0.0, -1.0]), a, b, c).is_none());
    }

    #[test]
    fn shared_edges_and_vertices_report_one_triangle() {
        // A closed fan of six triangles around the origin, and the two triangles of a square.
        let ring: Vec<DVec3> = (0..6)
            .map(|k| {
                let a = k as f64 * std::f64::consts::PI / 3.0;
                v(a.cos(), a.sin(), 0.0)
            })
            .collect();
        let fan: Vec<[DVec3; 3]> = (0..6).map(|k| [DVec3::ZERO, ring[k], ring[(k + 1) % 6]]).collect();
        let targets = [[0.0, 0.0], [0.5, 0.0], [-0.25, -0.25 * 3f64.sqrt()], [0.25, 0.25 * 3f64.sqrt()]];
        for (dx, dy) in [(0.0, 0.0), (0.3, -0.2), (-0.7, 0.9)] {
            for z in [1.0, -1.0] {
                for [x, y] in targets {
                    let r = ray([x + dx, y + dy, z], [-dx, -dy, -z]);
                    let count = fan.iter().filter(|[a, b, c]| watertight(&r, *a, *b, *c).is_some()).count();
                    assert_eq!(count, 1, "target ({x}, {y}) from offset ({dx}, {dy}, {z})");
                    // Reversing the winding of every triangle changes nothing.
                    let count = fan.iter().filter(|[a, b, c]| watertight(&r, *a, *c, *b).is_some()).count();
                    assert_eq!(count, 1);
                }
            }
        }
    }

    #[test]
    fn degenerate_and_in_plane_rays_miss() {
        let (a, b) = (v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0));
        assert!(watertight(&ray([0.5, 0.0, 1.0], [0.0, 0.0, -1.0]), a, b, b).is_none());
        assert!(watertight(&ray([0.5, 0.0, 1.0], [0.0, 0.0, -1.0]), a, b, v(2.0, 0.0, 0.0)).is_none());
        assert!(watertight(&ray([-1.0, 0.2, 0.0], [1.0, 0.0, 0.0]), a, b, v(0.0, 1.0, 0.0)).is_none());
    }

    #[test]
    fn plane_hit_refines_and_affine_inverts() {
        let (a, b, c) = (v(0.0, 0.0, 1e7), v(1.0, 0.0, 1e7), v(0.0, 1.0, 1e7));
        let r = Ray64 { origin: v(0.2, 0.3, 0.0), direction: v(0.0, 0.0, 1.0), tmin: 0.0, tmax: f64::INFINITY };
        let hit = plane_hit(&r, a, b, c).unwrap();
        assert_eq!((hit.t, hit.u, hit.v, hit.front), (1e7, 0.2, 0.3, false));
        let m = Affine::from_rows(&[0.0, -2.0, 0.0, 5.0, 2.0, 0.0, 0.0, 6.0, 0.0, 0.0, 2.0, 1e6]);
        let p = v(1.0, 2.0, 3.0);
        assert!((m.inverse().unwrap().point(m.point(p)) - p).length() < 1e-9);
        assert!(Affine::from_rows(&[0.0; 12]).inverse().is_none());
        // Normals follow the mirror: a reflection flips the winding's normal.
        let mirror = Affine::from_rows(&[-1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        let n = world_normal(&mirror.inverse().unwrap(), DVec3::ZERO, DVec3::X, DVec3::Y);
        assert_eq!(n, DVec3::new(0.0, 0.0, -1.0));
    }

    #[test]
    fn closest_points_of_degenerate_triangles_and_far_points_are_finite_and_right() {
        let (a, b) = (v(1.0, 0.0, 0.0), v(-1.0, 0.0, 0.0));
        let p = v(0.0, 0.0, 0.5);
        // A repeated corner (0 * (0 / 0) before), three corners on a line, one point.
        for [x, y, z] in [[a, a, b], [a, b, b], [b, a, a], [a, b, v(0.25, 0.0, 0.0)]] {
            assert_eq!(closest_point_on_triangle(p, x, y, z), v(0.0, 0.0, 0.0), "{x} {y} {z}");
        }
        assert_eq!(closest_point_on_triangle(p, a, a, a), a);
        // Products of four lengths overflow f64 from 1e155 on, underflow below 1e-80.
        let (c, d, e) = (v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0));
        for far in [1e100, 1e154, 1e155, 1e300] {
            let q = closest_point_on_triangle(v(0.25, 0.25, far), c, d, e);
            assert!(q.z == 0.0 && q.x >= 0.0 && q.y >= 0.0 && q.x + q.y <= 1.0, "{q}");
            // On the nearest edge (x = 0); where along it is below f64's precision of the distance.
            let q = closest_point_on_triangle(v(-far, 0.5, 0.0), c, d, e);
            assert!(q.x == 0.0 && (0.0..=1.0).contains(&q.y), "{q}");
        }
        assert_eq!(closest_point_on_triangle(v(-1e70, 0.5, 0.0), c, d, e), v(0.0, 0.5, 0.0));
        assert_eq!(closest_point_on_triangle(v(0.25, 0.25, 1e70), c, d, e), v(0.25, 0.25, 0.0));
        let tiny = 1e-100;
        let q = closest_point_on_triangle(v(0.25, 0.25, 1.0) * tiny, c * tiny, d * tiny, e * tiny);
        assert_eq!(q, v(0.25, 0.25, 0.0) * tiny);
        assert_eq!(length_scale(1.0), 1.0);
        assert_eq!(length_scale(1e300), 2f64.powi(-750));
        assert_eq!(length_scale(1e-300), 2f64.powi(750));
        assert_eq!((length_scale(2f64.powi(250)), length_scale(2f64.powi(-250))), (1.0, 1.0));
    }

    #[test]
    fn box_entry_is_conservative_for_flat_boxes() {
        let flat = Aabb { min: v(0.0, 0.0, 1.0), max: v(1.0, 1.0, 1.0) };
        let r = Ray64 { origin: v(0.5, 0.5, 0.0), direction: v(0.0, 0.0, 1.0), tmin: 0.0, tmax: 5.0 };
        assert_eq!(flat.entry(&r, r.direction.recip()), Some(1.0));
        // Along the face of a flat box: 0 * inf is NaN, which must not reject.
        let along = Ray64 { origin: v(-1.0, 0.5, 1.0), direction: v(1.0, 0.0, 0.0), tmin: 0.0, tmax: 5.0 };
        assert_eq!(flat.entry(&along, along.direction.recip()), Some(1.0));
    }
}

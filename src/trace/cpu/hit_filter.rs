//! What the CPU engine's queries decide about each candidate hit Embree meets: culling by the
//! instance's facing, opacity against the query's threshold, and, for the queries that meet
//! every hit (counts, all hits, transmittance), keeping the hit and going on.

use glam::DVec3;

use crate::embree::api::{RtcArguments, RtcFilterArguments, RtcRayQueryContext, FEATURE_FLAGS_ALL, INVALID_ID};
use crate::embree::api::{RAY_QUERY_FLAG_COHERENT, RAY_QUERY_FLAG_INCOHERENT, RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER};
use crate::geometry::precision::Cull;
use crate::scene::{MeshKind, Scene};

/// A hit Embree met, as the filter saw it: `prim` within its part (`geometry`), f32 values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    pub t: f32,
    pub u: f32,
    pub v: f32,
    pub instance: u32,
    pub geometry: u32,
    pub prim: u32,
    /// The ray's `id` as traced: its lane in a packet (0 for a ray traced alone).
    pub ray: u32,
}

impl Candidate {
    /// The order of every-hit answers, a ray's together: nearer first, then the lower
    /// (instance, geometry, prim).
    fn order(&self, other: &Candidate) -> std::cmp::Ordering {
        let ids = |c: &Candidate| (c.instance, c.geometry, c.prim);
        self.ray.cmp(&other.ray).then(self.t.total_cmp(&other.t)).then(ids(self).cmp(&ids(other)))
    }

    fn same_triangle(&self, other: &Candidate) -> bool {
        (self.ray, self.instance, self.geometry, self.prim) == (other.ray, other.instance, other.geometry, other.prim)
    }
}

/// What a query's filter decides with: Embree's context first (Embree hands its address to the
/// filter, which finds the rest behind it), then the query's choices and the ray's state.
#[repr(C)]
pub struct QueryContext<'a> {
    embree: RtcRayQueryContext,
    scene: &'a Scene,
    cull: Cull,
    /// Triangles whose opacity is below this let the ray through (0: every triangle counts).
    threshold: f32,
    /// Keep every hit in `found` and go on (counts, all hits, transmittance).
    every: bool,
    /// Whether every hit counts (no culling, nothing translucent): the filter then asks nothing.
    keeps_all: bool,
    /// Whether the filter runs at all (`needs_filter`), decided once: a query asks it a ray.
    filtered: bool,
    /// The traced ray's direction in the scene's frame (for facing).
    pub direction: DVec3,
    /// The hits met so far, where `every`.
    pub found: Vec<Candidate>,
}

impl<'a> QueryContext<'a> {
    pub fn new(scene: &'a Scene, cull: Cull, threshold: f32, every: bool) -> QueryContext<'a> {
        let keeps_all = cull == Cull::None && !(threshold > 0.0 && scene.has_opacity());
        QueryContext {
            embree: RtcRayQueryContext::default(),
            scene,
            cull,
            threshold,
            every,
            keeps_all,
            filtered: every || !keeps_all,
            direction: DVec3::ZERO,
            found: Vec::new(),
        }
    }

    /// The scene the query traces.
    pub fn scene(&self) -> &'a Scene {
        self.scene
    }

    /// Whether this query needs the filter at all: plain closest hits and occlusion in a scene
    /// with nothing translucent and no culling need none (Embree's fastest path).
    pub fn needs_filter(&self) -> bool {
        self.filtered
    }

    /// What the filter does for this query, by name (none: no filter runs).
    pub fn effects(&self) -> Vec<&'static str> {
        let mut effects = Vec::new();
        if self.every {
            effects.push("every hit");
        }
        if self.cull != Cull::None {
            effects.push("culling");
        }
        if self.threshold > 0.0 && self.scene.has_opacity() {
            effects.push("opacity");
        }
        effects
    }

    /// The arguments of a query through this context (`coherent`: rays from one point, a
    /// camera's).
    pub fn arguments(&mut self, coherent: bool) -> RtcArguments {
        let needs = self.needs_filter();
        let order = if coherent { RAY_QUERY_FLAG_COHERENT } else { RAY_QUERY_FLAG_INCOHERENT };
        RtcArguments {
            flags: order | if needs { RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER } else { 0 },
            feature_mask: FEATURE_FLAGS_ALL,
            // The whole context's address (its first field's): the filter reads all of it.
            context: self as *mut QueryContext as *mut RtcRayQueryContext,
            filter: if needs { Some(filter_hit) } else { None },
            intersect: std::ptr::null_mut(),
            min_width_distance_factor: 0.0,
        }
    }

    /// Whether the hit on triangle `prim` of part `geometry` of instance `instance` counts.
    fn keeps(&self, instance: u32, geometry: u32, prim: u32) -> bool {
        let Some(placement) = self.scene.placements.get(instance as usize) else { return true };
        if placement.mesh.kind == MeshKind::Spheres {
            return true;
        }
        let global = placement.triangles.global(geometry as usize, prim as usize);
        if !placement.flags.force_opaque {
            if let Some(opacity) = &placement.mesh.opacity {
                if opacity[global] < self.threshold {
                    return false;
                }
            }
        }
        if self.cull == Cull::None || placement.flags.cull_disable {
            return true;
        }
        // Front: the side `cross(b - a, c - a)` points to in the mesh's frame, met by a ray going
        // against it (the reference tier's convention; mirrored placements swap it).
        let [a, b, c] = placement.triangles.triangle(global);
        let front = (b - a).cross(c - a).dot(placement.to_local.vector(self.direction)) < 0.0;
        self.cull.keeps(front != placement.flip_facing)
    }

    /// Drops repeats of one triangle (a ray meeting an edge can be handed the same triangle
    /// twice) and sorts the hits met into the answers' order (a packet's rays one after another).
    pub fn sorted_found(&mut self) -> &[Candidate] {
        self.found.sort_by(Candidate::order);
        self.found.dedup_by(|a, b| a.same_triangle(b));
        &self.found
    }
}

/// Embree's filter for the CPU engine's queries: rejects the candidates the query does not keep;
/// where the query meets every hit, records each kept one and rejects it too, so that traversal
/// goes on.
///
/// # Safety
/// Embree calls it with `args.context` the address of a `QueryContext`'s first field (the queries
/// pass no other), and `args.ray`/`args.hit` holding `args.n` lanes.
unsafe extern "C" fn filter_hit(args: *const RtcFilterArguments) {
    // SAFETY: see above: the context is a live `QueryContext` owned by the tracing thread, which
    // waits in Embree for this call.
    unsafe {
        let args = &*args;
        let context = &mut *(args.context as *mut QueryContext);
        let n = args.n as usize;
        let hits = args.hit as *const u32;
        for i in 0..n {
            let valid = args.valid.add(i);
            if *valid == 0 {
                continue;
            }
            let (prim, geometry) = (*hits.add(5 * n + i), *hits.add(6 * n + i));
            // No instance id: a one-instance scene traced without its instance level.
            let instance = match *hits.add(7 * n + i) {
                INVALID_ID => 0,
                id => id,
            };
            if !context.keeps_all && !context.keeps(instance, geometry, prim) {
                *valid = 0;
                continue;
            }
            if context.every {
                let t = *args.ray.add(8 * n + i);
                let (u, v) = (*args.hit.add(3 * n + i), *args.hit.add(4 * n + i));
                // The ray's `id` (RTCRayN's eleventh member): its lane where traced in a packet.
                let ray = *(args.ray as *const u32).add(10 * n + i);
                context.found.push(Candidate { t, u, v, instance, geometry, prim, ray });
                *valid = 0;
            }
        }
    }
}

//! What a query asks: which question, at which precision tier, culling which side; and the batch
//! of rays or points it asks it of, as the dispatcher, an engine and its paths pass it on.

pub use crate::geometry::precision::Cull;

use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::rays::Rays;
use crate::scene::Scene;

/// What a query asks of each ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Query {
    /// The closest hit in [tmin, tmax].
    Closest,
    /// Whether anything is hit in [tmin, tmax]; traversal stops at the first hit.
    Occluded,
    /// How many hits lie in [tmin, tmax] (each crossing once in the exact tiers); none is stored.
    Count,
    /// Every hit in [tmin, tmax] (the nearest `max_hits`), in order.
    All,
    /// For `contains`, exact tier: the signed sum of the ray's crossings, and whether its origin
    /// lies on a surface, into one int32 (`Crossings`).
    Parity,
    /// The product of (1 - opacity) over every crossing in [tmin, tmax]: the light a ray keeps.
    Transmit,
    /// For `contains` by winding number, exact tier, one instance: `Parity`'s sum less the
    /// crossings of the cap that closes the mesh's holes (`scene::WindingCap`), and the cap's
    /// winding number about the ray's origin in `t` (NaN where it lies within rounding of the
    /// cap): the mesh's winding number is their sum.
    Winding,
}

/// What `Query::Parity` and `Query::Winding` write into one int32 a ray (QUERY_PARITY in
/// shaders/common.glsl): 2 per crossing, + where the ray meets a triangle's back in its mesh's
/// frame (it leaves an outward mesh there), - its front; plus 1 where the origin lies on a
/// surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crossings(pub i32);

impl Crossings {
    /// The signed sum of the crossings (for a closed mesh: its winding number about the origin).
    pub fn sum(self) -> i32 {
        self.0 >> 1
    }

    /// Whether the crossings are odd in number.
    pub fn odd(self) -> bool {
        self.sum() & 1 == 1
    }

    /// Whether the ray's origin lies on a surface (within 8 ulps: `ReferenceTracer::on_surface`).
    pub fn on_surface(self) -> bool {
        self.0 & 1 == 1
    }
}

impl Query {
    /// Whether traversal must meet every hit: counts, all hits, parities, transmittance.
    pub fn meets_every_hit(self) -> bool {
        matches!(self, Query::Count | Query::All | Query::Parity | Query::Transmit | Query::Winding)
    }

    /// Whether the shaders write per-ray counts (and lists) rather than hit fields.
    pub fn counts_hits(self) -> bool {
        matches!(self, Query::Count | Query::All | Query::Parity | Query::Winding)
    }

    /// The shaders' QUERY constant: QUERY_CLOSEST (0), QUERY_ALL (1), QUERY_PARITY (2),
    /// QUERY_TRANSMIT (3) or QUERY_WINDING (4).
    pub fn shader_query(self) -> u32 {
        match self {
            Query::Closest | Query::Occluded => 0,
            Query::Count | Query::All => 1,
            Query::Parity => 2,
            Query::Transmit => 3,
            Query::Winding => 4,
        }
    }

    /// The name `Scene.explain` and errors use.
    pub fn name(self) -> &'static str {
        match self {
            Query::Closest => "closest",
            Query::Occluded => "occluded",
            Query::Count => "count",
            Query::All => "all",
            Query::Parity => "contains",
            Query::Transmit => "transmittance",
            Query::Winding => "contains by winding number",
        }
    }
}

impl Query {
    pub fn parse(name: &str) -> crate::error::Result<Query> {
        match name {
            "closest" => Ok(Query::Closest),
            "occluded" => Ok(Query::Occluded),
            "count" => Ok(Query::Count),
            "all" => Ok(Query::All),
            "contains" => Ok(Query::Parity),
            "transmittance" => Ok(Query::Transmit),
            other => Err(crate::error::invalid_value(format!(
                "query must be 'closest', 'occluded', 'count', 'all', 'contains' or 'transmittance', got {other:?}"
            ))),
        }
    }
}

/// Everything a trace asks besides its rays: which query, at which precision, culling which side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Request {
    pub query: Query,
    pub precision: Precision,
    pub cull: Cull,
    /// Exact tier only: report contacts (a ray touching an edge or vertex hits every triangle
    /// that has it: closed triangles) rather than crossings (each shared edge or vertex belongs
    /// to one triangle). For the trimesh drop-in, whose users expect a ray grazing a silhouette
    /// to hit.
    pub contacts: bool,
    /// Triangles whose opacity is below this let rays through (in (0, 1]; see `DEFAULT_THRESHOLD`).
    pub opacity_threshold: f32,
}

/// The opacity from which a triangle stops rays, unless a query says otherwise.
pub const DEFAULT_THRESHOLD: f32 = 0.5;

impl Request {
    pub fn new(query: Query, precision: Precision, cull: Cull) -> Request {
        Request { query, precision, cull, contacts: false, opacity_threshold: DEFAULT_THRESHOLD }
    }

    /// Which triangles the host's tracer may hit for this request.
    pub fn filter(&self) -> crate::geometry::reference::Filter {
        crate::geometry::reference::Filter {
            cull: self.cull,
            threshold: self.opacity_threshold,
            contacts: self.contacts,
        }
    }

    /// Checks the opacity threshold: in (0, 1].
    pub fn check(&self) -> crate::error::Result<()> {
        let t = self.opacity_threshold;
        if !(t > 0.0 && t <= 1.0) {
            return Err(crate::error::invalid_value(format!(
                "opacity_threshold must be in (0, 1] (a triangle stops rays where its opacity reaches it), got {t}"
            )));
        }
        Ok(())
    }
}

/// Which of several precision tiers answers a query.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    /// f32 hits straight from traversal.
    Fast,
    /// f32 traversal of the re-centred scene, each hit re-intersected in f64 on the host.
    Refined,
    /// The f64 watertight test on the GPU, through conservative per-triangle boxes.
    Exact,
    /// The f64 watertight test on the CPU, on all cores: the other tiers' oracle.
    Reference,
}

impl Precision {
    pub fn parse(name: &str) -> crate::error::Result<Precision> {
        match name {
            "fast" => Ok(Precision::Fast),
            "refined" => Ok(Precision::Refined),
            "exact" => Ok(Precision::Exact),
            "reference" => Ok(Precision::Reference),
            other => Err(crate::error::invalid_value(format!(
                "precision must be 'fast', 'refined', 'exact' or 'reference', got {other:?}"
            ))),
        }
    }

    /// Whether `t` and `uv` come back as f64.
    pub fn is_f64(self) -> bool {
        self != Precision::Fast
    }
}

/// What a signed distance asks: the distances' limit and tier, and how `contains` signs them (its
/// tier; by winding number or by parity).
#[derive(Clone, Copy, Debug)]
pub struct SignedDistance {
    pub max_distance: f64,
    pub precision: Precision,
    pub contains_precision: Precision,
    pub winding: bool,
}

/// A ray query's batch: the scene, the rays, what is asked of them, and what may stop it (asked
/// between chunks).
#[derive(Clone, Copy)]
pub struct RayBatch<'a> {
    pub scene: &'a Scene,
    pub rays: &'a Rays<'a>,
    pub request: Request,
    pub interrupt: &'a dyn Interrupt,
}

impl<'a> RayBatch<'a> {
    /// The same rays and scene, asked `request`.
    pub fn asking(self, request: Request) -> RayBatch<'a> {
        RayBatch { request, ..self }
    }
}

/// A point query's batch: the scene, the points (f64 or f32 rows of three), and what may stop it.
#[derive(Clone, Copy)]
pub struct PointBatch<'a> {
    pub scene: &'a Scene,
    pub points: Vec3s<'a>,
    pub interrupt: &'a dyn Interrupt,
}

/// Whether a query on `scene` runs on the host because of its spheres: the GPU traces spheres
/// for closest hits and occlusion in the fast tier; every f64 tier of a scene with spheres is the
/// reference tier's tracer (the GPU's f64 structures hold triangles), and so are the other ray
/// queries (counts, transmittance through opacity) in every tier.
pub fn spheres_on_host(scene: &Scene, request: Request) -> bool {
    scene.has_spheres() && (request.precision.is_f64() || !matches!(request.query, Query::Closest | Query::Occluded))
}

//! Meshes as every engine sees them: the host's f64 copy of the surface (re-centred, for the f64
//! tiers), its counts, opacity and update lock, and the engine's own hierarchy over it behind
//! `MeshHierarchy` (the Vulkan engine's BLAS, a CPU engine's BVH).

use std::any::Any;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock, RwLockReadGuard};
use std::time::Instant;

use glam::DVec3;

use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::{check_faces, check_vertices, Indices, Vec3s};
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::geometry::interrupt::Interrupt;
use crate::geometry::precision::Aabb;
use crate::geometry::rays::PerRay;
use crate::geometry::reference::TriangleSet;
use crate::geometry::vertex_format::VertexFormat;

/// Largest radius, and extent of a sphere set: squares of distances up to a few times this stay
/// finite in f32 (whose largest value is 3.4e38).
pub const MAX_SPHERE_EXTENT: f64 = 1e18;

/// What a mesh's hierarchy holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshKind {
    Triangles,
    /// Spheres, one box each, intersected by a shader.
    Spheres,
}

/// What one mesh is built from: its parts, and optionally each triangle's opacity in [0, 1]
/// (among all parts, in the caller's order; 1 blocks light, 0 cuts the triangle out).
pub struct MeshInput<'a> {
    pub parts: &'a [(Vec3s<'a>, Indices<'a>)],
    pub opacity: Option<Vec<f32>>,
}

/// Meshes to build in one call: their inputs, how to build them, and what may stop it.
#[derive(Clone, Copy)]
pub struct MeshBatch<'a> {
    pub items: &'a [MeshInput<'a>],
    pub options: BuildOptions,
    pub format: VertexFormat,
    /// Bytes of build memory (Vulkan's scratch) the batch may take at once.
    pub scratch_budget: u64,
    pub interrupt: &'a dyn Interrupt,
}

/// An engine's hierarchy over one mesh. The engine that built it reads it back with
/// `Mesh::hierarchy` (one downcast where a query starts).
pub trait MeshHierarchy: Send + Sync {
    /// Bytes and time of its build.
    fn stats(&self) -> BuildStats;
    /// Moves it to new vertices, the faces kept: `local` holds them in the mesh's device frame
    /// (f64 xyz, already quantized to `format`). Called with the mesh held alone.
    fn refit(&self, local: &[f64], format: VertexFormat, options: BuildOptions) -> Result<()>;
    fn as_any(&self) -> &dyn Any;
}

/// The host's side of a mesh before an engine builds its hierarchy: checked, re-centred on its
/// bounding box, in f64.
pub struct MeshGeometry {
    pub kind: MeshKind,
    /// Vertices of a triangle mesh; spheres of a sphere set.
    pub vertex_count: usize,
    pub triangle_count: usize,
    pub center: DVec3,
    /// Device coordinates are `(v - center) / scale` (see `Mesh::scale`).
    pub scale: f64,
    pub vertex_format: VertexFormat,
    /// Every part's triangles in the device frame; for spheres, the spheres (`TriangleSet::of_spheres`).
    pub triangles: TriangleSet,
    /// Each sphere's centre (device frame) and radius; empty for triangles.
    pub spheres: Vec<(DVec3, f64)>,
    /// Opacity per caller's triangle among all parts, where some is below 1.
    pub opacity: Option<Arc<Vec<f32>>>,
}

impl MeshGeometry {
    /// Checks a triangle mesh's parts and opacity, and re-centres them (see `device_triangles`).
    pub fn triangles(item: &MeshInput, format: VertexFormat) -> Result<MeshGeometry> {
        let parts = item.parts;
        let triangle_count = check_parts(parts)?;
        let opacity = item.opacity.as_deref().map(|o| check_opacity(o, triangle_count)).transpose()?;
        // Opacity 1 everywhere is no opacity: the mesh stays opaque.
        let opacity = opacity.filter(|o| o.iter().any(|&x| x < 1.0));
        let (triangles, center, scale) = device_triangles(parts, format);
        Ok(MeshGeometry {
            kind: MeshKind::Triangles,
            vertex_count: parts.iter().map(|(v, _)| v.rows()).sum(),
            triangle_count,
            center,
            scale,
            vertex_format: format,
            triangles,
            spheres: Vec::new(),
            opacity: opacity.map(|o| Arc::new(o.to_vec())),
        })
    }

    /// Checks a sphere set (`centers` (N, 3), `radii` one per sphere or one for all) against the
    /// range the f32 tests square, and re-centres it on its bounds.
    pub fn spheres(centers: Vec3s, radii: PerRay) -> Result<MeshGeometry> {
        let bounds = check_spheres(centers, radii)?;
        let (n, center) = (centers.rows(), bounds.center());
        let spheres: Vec<(DVec3, f64)> =
            (0..n).map(|i| (DVec3::from_array(centers.row_f64(i)) - center, radii.get(i))).collect();
        Ok(MeshGeometry {
            kind: MeshKind::Spheres,
            vertex_count: n,
            triangle_count: 0,
            center,
            scale: 1.0,
            vertex_format: VertexFormat::F32,
            // The host's f64 tiers trace the spheres themselves; their boxes make scenes' frames.
            triangles: TriangleSet::of_spheres(spheres.clone()),
            spheres,
            opacity: None,
        })
    }
}

/// A mesh: the host's f64 copy of its surface and an engine's hierarchy over it.
///
/// The engine holds the vertices re-centred on their bounding box (`center`, subtracted in f64
/// before anything becomes f32), so that a mesh far from the origin keeps its full f32 precision;
/// scenes add the centre back in their placements. The host keeps the same re-centred vertices in
/// f64 for the f64 precision tiers.
pub struct Mesh {
    pub kind: MeshKind,
    /// Vertices of a triangle mesh; spheres of a sphere set.
    pub vertex_count: usize,
    pub triangle_count: usize,
    /// Where the device's coordinates are centred (in f64): moved by `update` for float32 meshes.
    center: RwLock<DVec3>,
    /// Device coordinates are `(v - center) / scale`: 1 in float32, the largest magnitude of
    /// `v - center` in the 16-bit formats (whose range is [-1, 1]).
    pub scale: f64,
    pub vertex_format: VertexFormat,
    pub options: BuildOptions,
    /// The host's f64 copy, replaced whole by `update` (scenes hold the one they were placed with).
    triangles: RwLock<Arc<TriangleSet>>,
    /// Each sphere's centre (device frame) and radius; empty for triangles.
    pub spheres: Arc<Vec<(DVec3, f64)>>,
    /// Counts `update`s, so that scenes can tell they hold an older copy.
    generation: AtomicU64,
    /// Seconds the last `update` took (upload and refit), 0 before any.
    last_update_seconds: Mutex<f64>,
    /// Queries on scenes holding this mesh share it; `update` takes it alone, so it never writes
    /// what a running trace reads (and waits for running traces instead).
    in_use: RwLock<()>,
    /// Opacity in [0, 1] per caller's triangle among all parts; `None`: every triangle is opaque.
    pub opacity: Option<Arc<Vec<f32>>>,
    hierarchy: Box<dyn MeshHierarchy>,
}

impl Mesh {
    /// A mesh of `geometry` under the hierarchy an engine built over it.
    pub fn new(geometry: MeshGeometry, options: BuildOptions, hierarchy: Box<dyn MeshHierarchy>) -> Mesh {
        Mesh {
            kind: geometry.kind,
            vertex_count: geometry.vertex_count,
            triangle_count: geometry.triangle_count,
            center: RwLock::new(geometry.center),
            scale: geometry.scale,
            vertex_format: geometry.vertex_format,
            options,
            triangles: RwLock::new(Arc::new(geometry.triangles)),
            spheres: Arc::new(geometry.spheres),
            generation: AtomicU64::new(0),
            last_update_seconds: Mutex::new(0.0),
            in_use: RwLock::new(()),
            opacity: geometry.opacity,
            hierarchy,
        }
    }

    /// The engine's hierarchy, where it is an `H` (the engine that built the mesh reads its own).
    pub fn hierarchy<H: 'static>(&self) -> Result<&H> {
        self.hierarchy.as_any().downcast_ref::<H>().ok_or_else(|| {
            invalid_value("this mesh was built by another engine: build it on the device that traces it")
        })
    }

    /// Bytes and time of the hierarchy's build.
    pub fn stats(&self) -> BuildStats {
        self.hierarchy.stats()
    }

    /// The host's f64 copy of the triangles as they are now.
    pub fn triangles(&self) -> Arc<TriangleSet> {
        self.triangles.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// The host's f64 triangles and the centre of their frame, taken together.
    pub fn placed(&self) -> (Arc<TriangleSet>, DVec3) {
        let triangles = self.triangles.read().unwrap_or_else(|e| e.into_inner());
        (triangles.clone(), self.center())
    }

    /// The centre of the device's coordinates (`v - center`), as it is now.
    pub fn center(&self) -> DVec3 {
        *self.center.read().unwrap_or_else(|e| e.into_inner())
    }

    /// Holds the mesh against `update` while the guard lives (see `Scene::hold_meshes`).
    pub fn hold(&self) -> RwLockReadGuard<'_, ()> {
        self.in_use.read().unwrap_or_else(|e| e.into_inner())
    }

    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    pub fn last_update_seconds(&self) -> f64 {
        *self.last_update_seconds.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Moves the vertices (same count, same faces) and refits the hierarchy in place instead of
    /// rebuilding it. Needs `allow_update` at build. Scenes holding the mesh must be `update`d
    /// before they trace again. Waits for running queries on scenes holding the mesh.
    pub fn update(&self, vertices: Vec3s) -> Result<()> {
        if !self.options.allow_update {
            return Err(invalid_value("this mesh was built without allow_update=True, so it cannot be refitted"));
        }
        if self.part_count() != 1 {
            return Err(Error::Unsupported("Mesh.update refits single-part meshes; rebuild a multi-part mesh".into()));
        }
        if self.kind == MeshKind::Spheres {
            return Err(Error::Unsupported("Mesh.update refits triangle meshes; rebuild the spheres".into()));
        }
        if vertices.rows() != self.vertex_count {
            return Err(invalid_value(format!(
                "update needs the same {} vertices (the faces stay), got {}: rebuild the mesh to change its topology",
                self.vertex_count,
                vertices.rows()
            )));
        }
        check_vertices("vertices", vertices)?;
        // Waits for queries on scenes holding this mesh to finish; new ones wait for the update.
        let _exclusive = self.in_use.write().unwrap_or_else(|e| e.into_inner());
        let started = Instant::now();
        // float32 meshes are re-centred on their new bounds (in f64), so that vertices moved far
        // keep their precision; scenes pick the new centre up in their `update`. The 16-bit
        // formats keep the range they were quantized for.
        let center = match self.vertex_format {
            VertexFormat::F32 => {
                Aabb::of_points((0..vertices.rows()).map(|i| DVec3::from_array(vertices.row_f64(i)))).center()
            }
            _ => self.center(),
        };
        let outside = (0..vertices.rows())
            .any(|i| ((DVec3::from_array(vertices.row_f64(i)) - center) / self.scale).abs().max_element() > 1.0);
        let local = device_coordinates(vertices, center, self.scale, self.vertex_format);
        if self.vertex_format != VertexFormat::F32 && outside {
            return Err(invalid_value(format!(
                "update moves vertices beyond the range {} was built for: rebuild the mesh",
                self.vertex_format.name()
            )));
        }
        self.hierarchy.refit(bytemuck::cast_slice(&local), self.vertex_format, self.options)?;
        let old = self.triangles();
        let moved = TriangleSet::new(local, old.faces.clone(), old.part_offsets.clone());
        // Both under the triangles' lock: `placed` sees the old pair or the new one.
        let mut triangles = self.triangles.write().unwrap_or_else(|e| e.into_inner());
        *triangles = Arc::new(moved);
        *self.center.write().unwrap_or_else(|e| e.into_inner()) = center;
        drop(triangles);
        self.generation.fetch_add(1, Ordering::AcqRel);
        *self.last_update_seconds.lock().unwrap_or_else(|e| e.into_inner()) = started.elapsed().as_secs_f64();
        Ok(())
    }

    pub fn part_count(&self) -> usize {
        self.triangles().part_offsets.len() - 1
    }

    /// Whether some triangle lets light through (opacity below 1).
    pub fn is_translucent(&self) -> bool {
        self.opacity.is_some()
    }
}

/// Checks a sphere set against the range the f32 tests square; returns its bounds.
fn check_spheres(centers: Vec3s, radii: PerRay) -> Result<Aabb> {
    check_vertices("centers", centers)?;
    let n = centers.rows();
    if let PerRay::Each(r) = radii {
        if r.len() != n {
            return Err(invalid_value(format!("radii has {} values for {n} centers", r.len())));
        }
    }
    // The f32 tests square distances: radii and the spheres' extent must stay well inside its
    // range.
    if let Some(i) = (0..n).find(|&i| !(radii.get(i) > 0.0 && radii.get(i) <= MAX_SPHERE_EXTENT)) {
        return Err(invalid_value(format!(
            "radius {i} must be finite and > 0, and at most {MAX_SPHERE_EXTENT:e} (the shaders square it in float32), got {}",
            radii.get(i)
        )));
    }
    let bounds = (0..n).fold(Aabb::EMPTY, |b, i| {
        let (c, r) = (DVec3::from_array(centers.row_f64(i)), radii.get(i));
        b.union(&Aabb { min: c - DVec3::splat(r), max: c + DVec3::splat(r) })
    });
    if bounds.extent().max_element() > MAX_SPHERE_EXTENT {
        return Err(invalid_value(format!(
            "the spheres span {:e}, more than {MAX_SPHERE_EXTENT:e} (the shaders square distances in float32): \
             split them into sphere sets placed by instances",
            bounds.extent().max_element()
        )));
    }
    Ok(bounds)
}

/// Checks a mesh's parts; returns their triangle count.
fn check_parts(parts: &[(Vec3s, Indices)]) -> Result<usize> {
    if parts.is_empty() {
        return Err(invalid_value("a mesh needs at least one part"));
    }
    for (k, (vertices, faces)) in parts.iter().enumerate() {
        let named = |e: Error| match (e, parts.len()) {
            (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("part {k}: {m}")),
            (e, _) => e,
        };
        check_vertices("vertices", *vertices).map_err(named)?;
        check_faces("faces", *faces, vertices.rows()).map_err(named)?;
    }
    Ok(parts.iter().map(|(_, f)| f.triangles()).sum())
}

/// Checks one opacity per triangle, each in [0, 1].
fn check_opacity(opacity: &[f32], triangles: usize) -> Result<&[f32]> {
    if opacity.len() != triangles {
        return Err(invalid_value(format!("opacity has {} values for {triangles} triangles", opacity.len())));
    }
    if let Some(i) = opacity.iter().position(|x| !(0.0..=1.0).contains(x)) {
        return Err(invalid_value(format!(
            "opacity[{i}] must be in [0, 1] (1 blocks, 0 cuts the triangle out), got {}",
            opacity[i]
        )));
    }
    Ok(opacity)
}

/// The vertices in the device's frame, `(v - center) / scale`, as the device will hold them
/// (quantized to `format`), in f64.
fn device_coordinates(vertices: Vec3s, center: DVec3, scale: f64, format: VertexFormat) -> Vec<DVec3> {
    (0..vertices.rows())
        .map(|i| ((DVec3::from_array(vertices.row_f64(i)) - center) / scale).to_array().map(|c| format.quantize(c)))
        .map(DVec3::from_array)
        .collect()
}

/// The mesh as the device holds it, all parts together, in f64 (re-centred on its bounding box,
/// and for the 16-bit formats scaled into [-1, 1] and quantized, so that every tier sees the same
/// surface), with that centre and scale.
fn device_triangles(parts: &[(Vec3s, Indices)], format: VertexFormat) -> (TriangleSet, DVec3, f64) {
    let points = || parts.iter().flat_map(|(v, _)| (0..v.rows()).map(move |i| DVec3::from_array(v.row_f64(i))));
    let bounds = Aabb::of_points(points());
    let center = bounds.center();
    let half_extent = 0.5 * bounds.extent().max_element();
    let scale = if format == VertexFormat::F32 || half_extent == 0.0 { 1.0 } else { half_extent };
    let local =
        points().map(|p| DVec3::from_array(((p - center) / scale).to_array().map(|c| format.quantize(c)))).collect();
    let (mut faces, mut part_offsets, mut first_vertex) = (Vec::new(), vec![0u32], 0u32);
    for (vertices, indices) in parts {
        faces.extend((0..indices.triangles()).map(|t| [0, 1, 2].map(|k| first_vertex + indices.corner(t, k) as u32)));
        part_offsets.push(faces.len() as u32);
        first_vertex += vertices.rows() as u32;
    }
    (TriangleSet::new(local, faces, part_offsets), center, scale)
}

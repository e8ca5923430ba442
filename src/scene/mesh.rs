//! Meshes: a bottom-level structure over device copies of vertices and faces (or sphere boxes),
//! with the host's f64 copy of the same surface for the f64 tiers.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock, RwLockReadGuard};
use std::time::Instant;

use ash::vk;
use glam::DVec3;

use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::{check_faces, check_vertices, Indices, Vec3s};
use crate::geometry::interrupt::{Interrupt, NoInterrupt};
use crate::geometry::morton::morton_order;
use crate::geometry::precision::Aabb;
use crate::geometry::rays::PerRay;
use crate::geometry::reference::TriangleSet;
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::accel::{self, AccelerationStructure, BuildInput, BuildOptions, BuildStats};
use crate::gpu::context::{vulkan_vertex_format, Context};
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};
use crate::gpu::records::{GeometrySource, SPHERE_SOURCE};

/// Largest radius, and extent of a sphere set: squares of distances up to a few times this stay
/// finite in f32 (whose largest value is 3.4e38).
const MAX_SPHERE_EXTENT: f64 = 1e18;

/// A triangle mesh on the device with its bottom-level acceleration structure.
///
/// The device holds the vertices re-centred on their bounding box (`center`, subtracted in f64
/// before anything becomes f32), so that a mesh far from the origin keeps its full f32 precision;
/// scenes add the centre back in their instance transforms. The host keeps the same re-centred
/// vertices in f64 for the f64 precision tiers.
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
    pub stats: BuildStats,
    /// The host's f64 copy, replaced whole by `update` (scenes hold the one they were placed with).
    triangles: RwLock<Arc<TriangleSet>>,
    /// Counts `update`s, so that scenes can tell they hold an older copy.
    generation: AtomicU64,
    /// Seconds the last `update` took (upload and refit), 0 before any.
    last_update_seconds: Mutex<f64>,
    /// Queries on scenes holding this mesh share it; `update` takes it alone, so it never writes
    /// what a running trace reads (and waits for running traces instead).
    in_use: RwLock<()>,
    blas: AccelerationStructure,
    /// One per geometry of the BLAS.
    pub(super) parts: Vec<Part>,
    /// A `GeometrySource` per part, read by shaders (normals, caller's triangle indices).
    pub(super) sources: Buffer,
    /// The same records without opacity, for instances forced opaque (meshes with opacity only).
    pub(super) opaque_sources: Option<Buffer>,
    /// Opacity in [0, 1] per caller's triangle among all parts; `None`: every triangle is opaque.
    pub opacity: Option<Arc<Vec<f32>>>,
}

/// What a mesh's BLAS holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshKind {
    Triangles,
    /// Spheres, one box each, intersected by a shader.
    Spheres,
}

/// One geometry of a mesh's BLAS: its device buffers.
pub(super) struct Part {
    vertex_count: usize,
    /// Triangles, or spheres (boxes).
    pub(super) triangle_count: usize,
    /// Triangle vertices; or spheres, as f32 (centre xyz, radius).
    vertices: Buffer,
    /// Triangle corners (none for spheres).
    indices: Option<Buffer>,
    index_is_u16: bool,
    /// The spheres' boxes (`VkAabbPositionsKHR`), for sphere sets.
    boxes: Option<Buffer>,
    /// Device triangle -> caller's triangle, where the device holds them in another order.
    device_order: Option<Vec<u32>>,
    primitive_order: Option<Buffer>,
    /// f32 opacity per device triangle, for parts with a triangle that is not opaque.
    opacity: Option<Buffer>,
}

impl Part {
    fn geometry(&self, format: VertexFormat) -> vk::AccelerationStructureGeometryKHR<'static> {
        if let Some(boxes) = &self.boxes {
            return accel::aabbs_geometry(boxes.address());
        }
        let indices = self.indices.as_ref().expect("triangle parts have indices");
        let triangles = vk::AccelerationStructureGeometryTrianglesDataKHR::default()
            .vertex_format(vulkan_vertex_format(format))
            .vertex_data(vk::DeviceOrHostAddressConstKHR { device_address: self.vertices.address() })
            .vertex_stride(format.stride() as u64)
            .max_vertex(self.vertex_count as u32 - 1)
            .index_type(if self.index_is_u16 { vk::IndexType::UINT16 } else { vk::IndexType::UINT32 })
            .index_data(vk::DeviceOrHostAddressConstKHR { device_address: indices.address() });
        let flags = if self.opacity.is_some() { accel::TRANSLUCENT_GEOMETRY_FLAGS } else { accel::GEOMETRY_FLAGS };
        vk::AccelerationStructureGeometryKHR::default()
            .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
            .geometry(vk::AccelerationStructureGeometryDataKHR { triangles })
            .flags(flags)
    }

    /// Uploads one part of a triangle mesh: `local` holds its vertices in the mesh's device frame
    /// (f64 xyz, already quantized to `format`); `opacity` its triangles' (caller's order).
    fn triangles(
        ctx: &Arc<Context>,
        uploads: &mut Uploads,
        (vertices, faces): (Vec3s, Indices),
        local: &[f64],
        format: VertexFormat,
        opacity: Option<&[f32]>,
    ) -> Result<Part> {
        let vertex_bytes = (format.stride() * vertices.rows()) as u64;
        let vertex_buffer =
            uploads.buffer(ctx, vertex_bytes, GEOMETRY_INPUT, "vertices", |out, _| format.write(local, out))?;
        let order = ctx.presort_primitives.then(|| morton_order(vertices, faces));
        let index_buffer = uploads.buffer(ctx, faces.device_bytes(), GEOMETRY_INPUT, "faces", |out, _| {
            faces.write_device(out, order.as_deref())
        })?;
        // Shaders map the device's triangle order back to the caller's.
        let primitive_order =
            order.as_ref().map(|order| uploads.records(ctx, order, GEOMETRY_INPUT, "primitive order")).transpose()?;
        // Shaders read opacity by the device's triangle index: kept in the device's order.
        let opacity = match opacity.filter(|o| o.iter().any(|&x| x < 1.0)) {
            Some(opacity) => {
                let device: Vec<f32> = match &order {
                    Some(order) => order.iter().map(|&caller| opacity[caller as usize]).collect(),
                    None => opacity.to_vec(),
                };
                Some(uploads.records(ctx, &device, GEOMETRY_INPUT, "opacity")?)
            }
            None => None,
        };
        Ok(Part {
            vertex_count: vertices.rows(),
            triangle_count: faces.triangles(),
            vertices: vertex_buffer,
            indices: Some(index_buffer),
            index_is_u16: faces.is_u16(),
            boxes: None,
            device_order: order,
            primitive_order,
            opacity,
        })
    }

    /// Uploads a sphere set: `n` spheres (`sphere(i)`: centre and radius) re-centred on `center`,
    /// in f32 (centre, radius), and their boxes.
    fn spheres(
        ctx: &Arc<Context>,
        uploads: &mut Uploads,
        n: usize,
        sphere: impl Fn(usize) -> (DVec3, f64),
        center: DVec3,
    ) -> Result<Part> {
        let spheres: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                let (c, r) = sphere(i);
                let local = (c - center).as_vec3();
                [local.x, local.y, local.z, r as f32]
            })
            .collect();
        let records = uploads.records(ctx, &spheres, GEOMETRY_INPUT, "spheres")?;
        // Boxes hold the f32 spheres whole: rounded outward from their f64 extent.
        let boxes: Vec<[f32; 6]> = (0..n)
            .map(|i| {
                let (c, r) = sphere(i);
                let half = DVec3::splat(r * (1.0 + 1e-6));
                Aabb { min: c - center - half, max: c - center + half }.outward_f32()
            })
            .collect();
        let boxes = uploads.records(ctx, &boxes, GEOMETRY_INPUT, "sphere boxes")?;
        Ok(Part {
            vertex_count: n,
            triangle_count: n,
            vertices: records,
            indices: None,
            index_is_u16: false,
            boxes: Some(boxes),
            device_order: None,
            primitive_order: None,
            opacity: None,
        })
    }

    /// This part's `GeometrySource` record; `kind` is its `vertex_format` field (a `VertexFormat`,
    /// or `SPHERE_SOURCE`); `opaque`: without its opacity (for instances forced opaque).
    fn source(&self, kind: u32, opaque: bool) -> GeometrySource {
        GeometrySource {
            vertices: self.vertices.address(),
            indices: self.indices.as_ref().map_or(0, |b| b.address()),
            primitive_order: self.primitive_order.as_ref().map_or(0, |b| b.address()),
            opacity: if opaque { 0 } else { self.opacity.as_ref().map_or(0, |b| b.address()) },
            index_is_u16: self.index_is_u16 as u32,
            vertex_format: kind,
        }
    }

    /// The caller's triangle (within this part) held at `device`.
    pub(super) fn caller_triangle(&self, device: usize) -> usize {
        self.device_order.as_ref().map_or(device, |order| order[device] as usize)
    }
}

impl Mesh {
    /// Checks and uploads vertices and faces, then builds the BLAS (opaque triangles).
    pub fn build(
        ctx: &Arc<Context>,
        vertices: Vec3s,
        faces: Indices,
        options: BuildOptions,
        format: VertexFormat,
    ) -> Result<Mesh> {
        Mesh::build_parts(ctx, &[(vertices, faces)], None, options, format)
    }

    /// A set of spheres (`centers` (N, 3), `radii` one per sphere or one for all): a BLAS of one
    /// box per sphere, whose spheres a shader intersects. Scenes mix them with triangle meshes.
    pub fn spheres(ctx: &Arc<Context>, centers: Vec3s, radii: PerRay, options: BuildOptions) -> Result<Mesh> {
        let bounds = check_spheres(ctx, centers, radii)?;
        let (n, center) = (centers.rows(), bounds.center());
        let sphere = |i: usize| (DVec3::from_array(centers.row_f64(i)), radii.get(i));
        let mut uploads = Uploads::default();
        let part = Part::spheres(ctx, &mut uploads, n, sphere, center)?;
        let sources = uploads.records(ctx, &[part.source(SPHERE_SOURCE, true)], GEOMETRY_INPUT, "geometry sources")?;
        // The host keeps the spheres' bounds (two corners each) for scenes' frames; the f64 tiers
        // do not trace spheres.
        let corners = (0..n)
            .flat_map(|i| {
                let (c, r) = sphere(i);
                [c - center - DVec3::splat(r), c - center + DVec3::splat(r)]
            })
            .collect();
        let prepared = PreparedMesh {
            kind: MeshKind::Spheres,
            vertex_count: n,
            triangle_count: 0,
            center,
            scale: 1.0,
            vertex_format: VertexFormat::F32,
            host_triangles: TriangleSet::new(corners, Vec::new(), vec![0, 0]),
            parts: vec![part],
            sources,
            opaque_sources: None,
            opacity: None,
        };
        let (blas, stats) = accel::build(ctx, &prepared.input(), options, &uploads)?;
        Ok(prepared.finish(options, blas, stats))
    }

    /// One mesh from several parts, each a geometry of one BLAS (`Hits.geometry_id` tells them
    /// apart; triangle ids count within each part); `opacity`: per triangle among all parts.
    pub fn build_parts(
        ctx: &Arc<Context>,
        parts: &[(Vec3s, Indices)],
        opacity: Option<Vec<f32>>,
        options: BuildOptions,
        format: VertexFormat,
    ) -> Result<Mesh> {
        let item = MeshInput { parts, opacity };
        let mut meshes = Mesh::build_many(ctx, &[item], options, format, u64::MAX, &NoInterrupt)?;
        Ok(meshes.pop().expect("one mesh per input"))
    }

    /// Builds many meshes (each from its parts) in as few submissions as `scratch_budget` bytes
    /// of build scratch allow (see `accel::build_many`); the error of a bad input names its
    /// position.
    pub fn build_many(
        ctx: &Arc<Context>,
        items: &[MeshInput],
        options: BuildOptions,
        format: VertexFormat,
        scratch_budget: u64,
        interrupt: &dyn Interrupt,
    ) -> Result<Vec<Mesh>> {
        let mut uploads = Uploads::default();
        let prepared = items
            .iter()
            .enumerate()
            .map(|(k, item)| {
                PreparedMesh::new(ctx, item, format, &mut uploads).map_err(|e| match (e, items.len()) {
                    (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("mesh {k}: {m}")),
                    (e, _) => e,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let inputs: Vec<BuildInput> = prepared.iter().map(PreparedMesh::input).collect();
        let built = accel::build_many(ctx, &inputs, options, &uploads, scratch_budget, interrupt)?;
        Ok(prepared.into_iter().zip(built).map(|(p, (blas, stats))| p.finish(options, blas, stats)).collect())
    }

    pub fn blas_address(&self) -> u64 {
        self.blas.address()
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

    /// Moves the vertices (same count, same faces) and refits the BLAS in place (Vulkan's UPDATE
    /// mode with source = destination) instead of rebuilding it. Needs `allow_update` at build.
    /// Scenes holding the mesh must be `update`d before they trace again. Waits for running
    /// queries on scenes holding the mesh.
    pub fn update(&self, vertices: Vec3s) -> Result<()> {
        let ctx = self.blas.context();
        if !self.options.allow_update {
            return Err(invalid_value("this mesh was built without allow_update=True, so it cannot be refitted"));
        }
        let [part] = self.parts.as_slice() else {
            return Err(Error::Unsupported("Mesh.update refits single-part meshes; rebuild a multi-part mesh".into()));
        };
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
        let mut uploads = Uploads::default();
        uploads.overwrite(ctx, &part.vertices, |out| self.vertex_format.write(bytemuck::cast_slice(&local), out))?;
        let old = self.triangles();
        let input = mesh_input(std::slice::from_ref(part), self.vertex_format);
        accel::update(ctx, &self.blas, &input, self.options, self.stats.update_scratch_size, &uploads)?;
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
        self.parts.len()
    }

    /// Whether some triangle lets light through (opacity below 1).
    pub fn is_translucent(&self) -> bool {
        self.opacity.is_some()
    }

    /// The `GeometrySource` records an instance reads: without opacity where it is forced opaque.
    pub(super) fn sources_address(&self, force_opaque: bool) -> u64 {
        match (&self.opaque_sources, force_opaque) {
            (Some(opaque), true) => opaque.address(),
            _ => self.sources.address(),
        }
    }
}

/// What one mesh is built from: its parts, and optionally each triangle's opacity in [0, 1]
/// (among all parts, in the caller's order; 1 blocks light, 0 cuts the triangle out).
pub struct MeshInput<'a> {
    pub parts: &'a [(Vec3s<'a>, Indices<'a>)],
    pub opacity: Option<Vec<f32>>,
}

/// A mesh's device buffers and host copy, uploaded (or recorded for upload) and ready for its
/// BLAS build.
struct PreparedMesh {
    kind: MeshKind,
    vertex_count: usize,
    pub(super) triangle_count: usize,
    center: DVec3,
    scale: f64,
    vertex_format: VertexFormat,
    host_triangles: TriangleSet,
    pub(super) parts: Vec<Part>,
    pub(super) sources: Buffer,
    opaque_sources: Option<Buffer>,
    opacity: Option<Arc<Vec<f32>>>,
}

impl PreparedMesh {
    fn new(ctx: &Arc<Context>, item: &MeshInput, format: VertexFormat, uploads: &mut Uploads) -> Result<PreparedMesh> {
        let parts = item.parts;
        let triangle_count = check_parts(ctx, parts, format)?;
        let opacity = item.opacity.as_deref().map(|o| check_opacity(o, triangle_count)).transpose()?;
        // Opacity 1 everywhere is no opacity: the mesh stays opaque.
        let opacity = opacity.filter(|o| o.iter().any(|&x| x < 1.0));
        let (host_triangles, center, scale) = device_triangles(parts, format);
        let local: &[f64] = bytemuck::cast_slice(&host_triangles.vertices);
        let mut first_vertex = 0;
        let mut prepared = Vec::with_capacity(parts.len());
        for (k, &(vertices, faces)) in parts.iter().enumerate() {
            let own = &local[3 * first_vertex..3 * (first_vertex + vertices.rows())];
            first_vertex += vertices.rows();
            let range = host_triangles.part_offsets[k] as usize..host_triangles.part_offsets[k + 1] as usize;
            let own_opacity = opacity.map(|o| &o[range]);
            prepared.push(Part::triangles(ctx, uploads, (vertices, faces), own, format, own_opacity)?);
        }
        let records = |opaque: bool| -> Vec<GeometrySource> {
            prepared.iter().map(|part| part.source(format as u32, opaque)).collect()
        };
        let sources = uploads.records(ctx, &records(false), GEOMETRY_INPUT, "geometry sources")?;
        let opaque_sources = match opacity {
            Some(_) => Some(uploads.records(ctx, &records(true), GEOMETRY_INPUT, "opaque geometry sources")?),
            None => None,
        };
        Ok(PreparedMesh {
            kind: MeshKind::Triangles,
            vertex_count: first_vertex,
            triangle_count,
            center,
            scale,
            vertex_format: format,
            host_triangles,
            parts: prepared,
            sources,
            opaque_sources,
            opacity: opacity.map(|o| Arc::new(o.to_vec())),
        })
    }

    fn input(&self) -> BuildInput<'static> {
        mesh_input(&self.parts, self.vertex_format)
    }

    fn finish(self, options: BuildOptions, blas: AccelerationStructure, stats: BuildStats) -> Mesh {
        Mesh {
            kind: self.kind,
            vertex_count: self.vertex_count,
            triangle_count: self.triangle_count,
            center: RwLock::new(self.center),
            scale: self.scale,
            vertex_format: self.vertex_format,
            triangles: RwLock::new(Arc::new(self.host_triangles)),
            generation: AtomicU64::new(0),
            last_update_seconds: Mutex::new(0.0),
            in_use: RwLock::new(()),
            options,
            stats,
            blas,
            parts: self.parts,
            sources: self.sources,
            opaque_sources: self.opaque_sources,
            opacity: self.opacity,
        }
    }
}

/// Checks a sphere set against the range the shaders square in f32 and the device's limits;
/// returns its bounds.
fn check_spheres(ctx: &Context, centers: Vec3s, radii: PerRay) -> Result<Aabb> {
    check_vertices("centers", centers)?;
    let n = centers.rows();
    if let PerRay::Each(r) = radii {
        if r.len() != n {
            return Err(invalid_value(format!("radii has {} values for {n} centers", r.len())));
        }
    }
    // The shaders square distances in f32: radii and the spheres' extent must stay well
    // inside its range.
    if let Some(i) = (0..n).find(|&i| !(radii.get(i) > 0.0 && radii.get(i) <= MAX_SPHERE_EXTENT)) {
        return Err(invalid_value(format!(
            "radius {i} must be finite and > 0, and at most {MAX_SPHERE_EXTENT:e} (the shaders square it in float32), got {}",
            radii.get(i)
        )));
    }
    if n as u64 > ctx.limits.max_primitive_count {
        return Err(Error::Unsupported(format!(
            "{n} spheres exceed this device's maxPrimitiveCount ({})",
            ctx.limits.max_primitive_count
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

/// Checks a mesh's parts and what the device can build from them; returns their triangle count.
fn check_parts(ctx: &Context, parts: &[(Vec3s, Indices)], format: VertexFormat) -> Result<usize> {
    if parts.is_empty() {
        return Err(invalid_value("a mesh needs at least one part"));
    }
    if parts.len() as u64 > ctx.limits.max_geometry_count {
        return Err(Error::Unsupported(format!(
            "{} parts exceed this device's maxGeometryCount ({})",
            parts.len(),
            ctx.limits.max_geometry_count
        )));
    }
    for (k, (vertices, faces)) in parts.iter().enumerate() {
        let named = |e: Error| match (e, parts.len()) {
            (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("part {k}: {m}")),
            (e, _) => e,
        };
        check_vertices("vertices", *vertices).map_err(named)?;
        check_faces("faces", *faces, vertices.rows()).map_err(named)?;
    }
    let triangle_count: usize = parts.iter().map(|(_, f)| f.triangles()).sum();
    if triangle_count as u64 > ctx.limits.max_primitive_count {
        return Err(Error::Unsupported(format!(
            "{triangle_count} triangles exceed this device's maxPrimitiveCount ({})",
            ctx.limits.max_primitive_count
        )));
    }
    if format != VertexFormat::F32 && !ctx.limits.vertex_formats.contains(&format) {
        return Err(Error::Unsupported(format!(
            "{} cannot build acceleration structures from {} vertices",
            ctx.info.name,
            format.name()
        )));
    }
    Ok(triangle_count)
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

/// The build input of a mesh's BLAS: one triangle geometry per part (opaque unless some of its
/// triangles let light through).
fn mesh_input(parts: &[Part], format: VertexFormat) -> BuildInput<'static> {
    BuildInput {
        ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
        geometries: parts.iter().map(|p| p.geometry(format)).collect(),
        primitive_counts: parts.iter().map(|p| p.triangle_count as u32).collect(),
        name: "mesh BLAS",
    }
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

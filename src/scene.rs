//! Meshes (a bottom-level structure over device copies of vertices and faces) and scenes (a
//! top-level structure over instances of meshes): the level users work at.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Instant;

use ash::vk;
use glam::DVec3;

use crate::accel::{self, AccelerationStructure, BuildInput, BuildOptions, BuildPreference, BuildStats, InstanceBits};
use crate::context::{Context, Wait};
use crate::error::{invalid_value, Error, Result};
use crate::input::{check_faces, check_vertices, morton_order, Indices, Vec3s, VertexFormat};
use crate::memory::{Buffer, Uploads};
use crate::precision::{Aabb, Affine};
use crate::reference::{PlacedSet, ReferenceTracer, TriangleSet};

const GEOMETRY_INPUT: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw(),
);

/// Bytes of one `GeometrySource` record in `shaders/common.glsl`.
const GEOMETRY_SOURCE_BYTES: usize = 32;

/// `GeometrySource.vertex_format` of sphere sets (after the `VertexFormat`s).
const SPHERE_SOURCE: u32 = 3;

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
    pub center: DVec3,
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
    blas: AccelerationStructure,
    /// One per geometry of the BLAS.
    parts: Vec<Part>,
    /// A `GeometrySource` per part, read by shaders (normals, caller's triangle indices).
    sources: Buffer,
}

/// What a mesh's BLAS holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshKind {
    Triangles,
    /// Spheres, one box each, intersected by a shader.
    Spheres,
}

/// One geometry of a mesh's BLAS: its device buffers.
struct Part {
    vertex_count: usize,
    /// Triangles, or spheres (boxes).
    triangle_count: usize,
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
}

impl Part {
    fn geometry(&self, format: VertexFormat) -> vk::AccelerationStructureGeometryKHR<'static> {
        if let Some(boxes) = &self.boxes {
            let data = vk::AccelerationStructureGeometryAabbsDataKHR::default()
                .data(vk::DeviceOrHostAddressConstKHR { device_address: boxes.address() })
                .stride(24);
            return vk::AccelerationStructureGeometryKHR::default()
                .geometry_type(vk::GeometryTypeKHR::AABBS)
                .geometry(vk::AccelerationStructureGeometryDataKHR { aabbs: data })
                .flags(vk::GeometryFlagsKHR::OPAQUE);
        }
        let indices = self.indices.as_ref().expect("triangle parts have indices");
        let triangles = vk::AccelerationStructureGeometryTrianglesDataKHR::default()
            .vertex_format(vulkan_vertex_format(format))
            .vertex_data(vk::DeviceOrHostAddressConstKHR { device_address: self.vertices.address() })
            .vertex_stride(format.stride() as u64)
            .max_vertex(self.vertex_count as u32 - 1)
            .index_type(if self.index_is_u16 { vk::IndexType::UINT16 } else { vk::IndexType::UINT32 })
            .index_data(vk::DeviceOrHostAddressConstKHR { device_address: indices.address() });
        vk::AccelerationStructureGeometryKHR::default()
            .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
            .geometry(vk::AccelerationStructureGeometryDataKHR { triangles })
            .flags(vk::GeometryFlagsKHR::OPAQUE)
    }

    /// This part's `GeometrySource` record (shaders/common.glsl); `kind` is its `vertex_format`
    /// field (a `VertexFormat`, or `SPHERE_SOURCE`).
    fn source(&self, kind: u32) -> [u8; GEOMETRY_SOURCE_BYTES] {
        let mut out = [0u8; GEOMETRY_SOURCE_BYTES];
        out[0..8].copy_from_slice(&self.vertices.address().to_ne_bytes());
        out[8..16].copy_from_slice(&self.indices.as_ref().map_or(0, |b| b.address()).to_ne_bytes());
        out[16..24].copy_from_slice(&self.primitive_order.as_ref().map_or(0, |b| b.address()).to_ne_bytes());
        out[24..28].copy_from_slice(&(self.index_is_u16 as u32).to_ne_bytes());
        out[28..32].copy_from_slice(&kind.to_ne_bytes());
        out
    }

    /// The caller's triangle (within this part) held at `device`.
    fn caller_triangle(&self, device: usize) -> usize {
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
        wait: &dyn Wait,
    ) -> Result<Mesh> {
        Mesh::build_parts(ctx, &[(vertices, faces)], options, format, wait)
    }

    /// A set of spheres (`centers` (N, 3), `radii` one per sphere or one for all): a BLAS of one
    /// box per sphere, whose spheres a shader intersects. Scenes mix them with triangle meshes.
    pub fn spheres(
        ctx: &Arc<Context>,
        centers: Vec3s,
        radii: crate::input::PerRay,
        options: BuildOptions,
        wait: &dyn Wait,
    ) -> Result<Mesh> {
        check_vertices("centers", centers)?;
        let n = centers.rows();
        if let crate::input::PerRay::Each(r) = radii {
            if r.len() != n {
                return Err(invalid_value(format!("radii has {} values for {n} centers", r.len())));
            }
        }
        if let Some(i) = (0..n).find(|&i| !(radii.get(i) > 0.0 && (radii.get(i) as f32).is_finite())) {
            return Err(invalid_value(format!("radius {i} must be finite and > 0, got {}", radii.get(i))));
        }
        if n as u64 > ctx.limits.max_primitive_count {
            return Err(Error::Unsupported(format!(
                "{n} spheres exceed this device's maxPrimitiveCount ({})",
                ctx.limits.max_primitive_count
            )));
        }
        let sphere = |i: usize| (DVec3::from_array(centers.row_f64(i)), radii.get(i));
        let bounds = (0..n).fold(Aabb::EMPTY, |b, i| {
            let (c, r) = sphere(i);
            b.union(&Aabb { min: c - DVec3::splat(r), max: c + DVec3::splat(r) })
        });
        let center = bounds.center();
        let mut uploads = Uploads::default();
        let records = uploads.buffer(ctx, 16 * n as u64, GEOMETRY_INPUT, "spheres", |out, _| {
            for (i, dst) in out.chunks_exact_mut(16).enumerate() {
                let (c, r) = sphere(i);
                let local = (c - center).as_vec3();
                for (d, v) in dst.chunks_exact_mut(4).zip([local.x, local.y, local.z, r as f32]) {
                    d.copy_from_slice(&v.to_ne_bytes());
                }
            }
        })?;
        // Boxes hold the f32 spheres whole: rounded outward from their f64 extent.
        let boxes = uploads.buffer(ctx, 24 * n as u64, GEOMETRY_INPUT, "sphere boxes", |out, _| {
            for (i, dst) in out.chunks_exact_mut(24).enumerate() {
                let (c, r) = sphere(i);
                let (lo, hi) =
                    (c - center - DVec3::splat(r * (1.0 + 1e-6)), c - center + DVec3::splat(r * (1.0 + 1e-6)));
                let corners = [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z];
                for (k, (d, v)) in dst.chunks_exact_mut(4).zip(corners).enumerate() {
                    d.copy_from_slice(&round_outward(v, k < 3).to_ne_bytes());
                }
            }
        })?;
        let part = Part {
            vertex_count: n,
            triangle_count: n,
            vertices: records,
            indices: None,
            index_is_u16: false,
            boxes: Some(boxes),
            device_order: None,
            primitive_order: None,
        };
        let sources =
            uploads.buffer(ctx, GEOMETRY_SOURCE_BYTES as u64, GEOMETRY_INPUT, "geometry sources", |out, _| {
                out.copy_from_slice(&part.source(SPHERE_SOURCE))
            })?;
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
        };
        let (blas, stats) = accel::build(ctx, &prepared.input(), options, &uploads, wait)?;
        Ok(prepared.finish(options, blas, stats))
    }

    /// One mesh from several parts, each a geometry of one BLAS (`Hits.geometry_id` tells them
    /// apart; triangle ids count within each part).
    pub fn build_parts(
        ctx: &Arc<Context>,
        parts: &[(Vec3s, Indices)],
        options: BuildOptions,
        format: VertexFormat,
        wait: &dyn Wait,
    ) -> Result<Mesh> {
        let mut meshes = Mesh::build_many(ctx, &[parts], options, format, u64::MAX, wait)?;
        Ok(meshes.pop().expect("one mesh per input"))
    }

    /// Builds many meshes (each from its parts) in as few submissions as `scratch_budget` bytes
    /// of build scratch allow (see `accel::build_many`); the error of a bad input names its
    /// position.
    pub fn build_many(
        ctx: &Arc<Context>,
        items: &[&[(Vec3s, Indices)]],
        options: BuildOptions,
        format: VertexFormat,
        scratch_budget: u64,
        wait: &dyn Wait,
    ) -> Result<Vec<Mesh>> {
        let mut uploads = Uploads::default();
        let prepared = items
            .iter()
            .enumerate()
            .map(|(k, parts)| {
                PreparedMesh::new(ctx, parts, format, &mut uploads).map_err(|e| match (e, items.len()) {
                    (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("mesh {k}: {m}")),
                    (e, _) => e,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let inputs: Vec<BuildInput> = prepared.iter().map(PreparedMesh::input).collect();
        let built = accel::build_many(ctx, &inputs, options, &uploads, scratch_budget, wait)?;
        Ok(prepared.into_iter().zip(built).map(|(p, (blas, stats))| p.finish(options, blas, stats)).collect())
    }

    pub fn blas_address(&self) -> u64 {
        self.blas.address()
    }

    /// The host's f64 copy of the triangles as they are now.
    pub fn triangles(&self) -> Arc<TriangleSet> {
        self.triangles.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    pub fn last_update_seconds(&self) -> f64 {
        *self.last_update_seconds.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Moves the vertices (same count, same faces) and refits the BLAS in place (Vulkan's UPDATE
    /// mode with source = destination) instead of rebuilding it. Needs `allow_update` at build.
    /// Scenes holding the mesh must be `update`d before they trace again. Not to be called while
    /// a query on a scene holding this mesh runs.
    pub fn update(&self, vertices: Vec3s, wait: &dyn Wait) -> Result<()> {
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
        let started = Instant::now();
        // The same frame as at build: scenes' transforms and the exact tier's frames keep meaning.
        let outside = (0..vertices.rows())
            .any(|i| ((DVec3::from_array(vertices.row_f64(i)) - self.center) / self.scale).abs().max_element() > 1.0);
        let local = device_coordinates(vertices, self.center, self.scale, self.vertex_format);
        if self.vertex_format != VertexFormat::F32 && outside {
            return Err(invalid_value(format!(
                "update moves vertices beyond the range {} was built for: rebuild the mesh",
                self.vertex_format.name()
            )));
        }
        let flat: Vec<f64> = local.iter().flat_map(|v| v.to_array()).collect();
        let mut uploads = Uploads::default();
        uploads.overwrite(ctx, &part.vertices, |out| self.vertex_format.write(&flat, out))?;
        let old = self.triangles();
        let input = mesh_input(std::slice::from_ref(part), self.vertex_format);
        accel::update(ctx, &self.blas, &input, self.options, self.stats.update_scratch_size, &uploads, wait)?;
        let moved = TriangleSet::new(local, old.faces.clone(), old.part_offsets.clone());
        *self.triangles.write().unwrap_or_else(|e| e.into_inner()) = Arc::new(moved);
        self.generation.fetch_add(1, Ordering::AcqRel);
        *self.last_update_seconds.lock().unwrap_or_else(|e| e.into_inner()) = started.elapsed().as_secs_f64();
        Ok(())
    }

    pub fn part_count(&self) -> usize {
        self.parts.len()
    }
}

/// A mesh's device buffers and host copy, uploaded (or recorded for upload) and ready for its
/// BLAS build.
struct PreparedMesh {
    kind: MeshKind,
    vertex_count: usize,
    triangle_count: usize,
    center: DVec3,
    scale: f64,
    vertex_format: VertexFormat,
    host_triangles: TriangleSet,
    parts: Vec<Part>,
    sources: Buffer,
}

impl PreparedMesh {
    fn new(
        ctx: &Arc<Context>,
        parts: &[(Vec3s, Indices)],
        format: VertexFormat,
        uploads: &mut Uploads,
    ) -> Result<PreparedMesh> {
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
        let (host_triangles, center, scale) = device_triangles(parts, format);
        let local: &[f64] = {
            // SAFETY: DVec3 is three f64 in a repr(C) struct, so a slice of them is a slice of f64.
            let v = &host_triangles.vertices;
            unsafe { std::slice::from_raw_parts(v.as_ptr() as *const f64, 3 * v.len()) }
        };
        let mut first_vertex = 0;
        let mut prepared = Vec::with_capacity(parts.len());
        for (vertices, faces) in parts {
            let own = &local[3 * first_vertex..3 * (first_vertex + vertices.rows())];
            first_vertex += vertices.rows();
            let vertex_bytes = (format.stride() * vertices.rows()) as u64;
            let vertex_buffer =
                uploads.buffer(ctx, vertex_bytes, GEOMETRY_INPUT, "vertices", |out, _| format.write(own, out))?;
            let order = ctx.presort_primitives.then(|| morton_order(*vertices, *faces));
            let index_buffer = uploads.buffer(ctx, faces.device_bytes(), GEOMETRY_INPUT, "faces", |out, _| {
                faces.write_device(out, order.as_deref())
            })?;
            // Shaders map the device's triangle order back to the caller's.
            let primitive_order = match &order {
                Some(order) => {
                    Some(uploads.buffer(ctx, 4 * order.len() as u64, GEOMETRY_INPUT, "primitive order", |out, _| {
                        for (dst, t) in out.chunks_exact_mut(4).zip(order) {
                            dst.copy_from_slice(&t.to_ne_bytes());
                        }
                    })?)
                }
                None => None,
            };
            prepared.push(Part {
                vertex_count: vertices.rows(),
                triangle_count: faces.triangles(),
                vertices: vertex_buffer,
                indices: Some(index_buffer),
                index_is_u16: faces.is_u16(),
                boxes: None,
                device_order: order,
                primitive_order,
            });
        }
        let sources = uploads.buffer(
            ctx,
            (GEOMETRY_SOURCE_BYTES * parts.len()) as u64,
            GEOMETRY_INPUT,
            "geometry sources",
            |out, _| {
                for (dst, part) in out.chunks_exact_mut(GEOMETRY_SOURCE_BYTES).zip(&prepared) {
                    dst.copy_from_slice(&part.source(format as u32));
                }
            },
        )?;
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
            center: self.center,
            scale: self.scale,
            vertex_format: self.vertex_format,
            triangles: RwLock::new(Arc::new(self.host_triangles)),
            generation: AtomicU64::new(0),
            last_update_seconds: Mutex::new(0.0),
            options,
            stats,
            blas,
            parts: self.parts,
            sources: self.sources,
        }
    }
}

/// The build input of a mesh's BLAS: one opaque triangle geometry per part.
fn mesh_input(parts: &[Part], format: VertexFormat) -> BuildInput<'static> {
    BuildInput {
        ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
        geometries: parts.iter().map(|p| p.geometry(format)).collect(),
        primitive_counts: parts.iter().map(|p| p.triangle_count as u32).collect(),
        name: "mesh BLAS",
    }
}

pub fn vulkan_vertex_format(format: VertexFormat) -> vk::Format {
    match format {
        VertexFormat::F32 => vk::Format::R32G32B32_SFLOAT,
        VertexFormat::F16 => vk::Format::R16G16B16A16_SFLOAT,
        VertexFormat::Snorm16 => vk::Format::R16G16B16A16_SNORM,
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

/// One placement of a mesh in a scene.
#[derive(Clone)]
pub struct Instance {
    pub mesh: Arc<Mesh>,
    /// Row-major 3×4 affine transform (object to world), in f64.
    pub transform: [f64; 12],
    pub custom_index: u32,
    pub mask: u8,
    pub flags: InstanceFlags,
}

/// What an instance asks of traversal beyond its placement.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct InstanceFlags {
    /// Query culling (`Cull`) does not apply to this instance.
    pub cull_disable: bool,
    /// Swap front and back (front is otherwise the side the hit's normal points to).
    pub flip_facing: bool,
    /// Treat the triangles as opaque (they are; kept for the guides' vocabulary).
    pub force_opaque: bool,
    /// Treat the triangles as non-opaque: traversal hands them to the shader, which accepts
    /// them (vkray has no any-hit programs), the path a future any-hit stage takes.
    pub force_no_opaque: bool,
}

// Instance flags of `VkGeometryInstanceFlagBitsKHR`.
const INSTANCE_CULL_DISABLE: u8 = 0x1;
const INSTANCE_FRONT_COUNTERCLOCKWISE: u8 = 0x2;
const INSTANCE_FORCE_OPAQUE: u8 = 0x4;
const INSTANCE_FORCE_NO_OPAQUE: u8 = 0x8;

pub const IDENTITY: [f64; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Where an instance's mesh sits in the scene's frame (world coordinates minus the scene centre).
pub struct Placement {
    pub mesh: Arc<Mesh>,
    /// The mesh's f64 triangles as this scene placed them (see `Scene::update`).
    pub triangles: Arc<TriangleSet>,
    /// From the mesh's re-centred frame to the scene's frame.
    pub to_scene: Affine,
    /// The inverse: from the scene's frame to the mesh's.
    pub to_local: Affine,
    pub custom_index: u32,
    pub mask: u8,
    /// The mesh's bounds in the scene's frame.
    pub bounds: Aabb,
    pub flags: InstanceFlags,
    /// Front is the side opposite the object-space normal: a mirroring transform (which flips the
    /// world normal) or `flip_facing`, not both.
    pub flip_facing: bool,
}

impl Placement {
    /// The bits of this placement's Vulkan instance record: spheres' hits go to the second hit
    /// group of the shader binding table (the procedural one).
    fn bits(&self) -> InstanceBits {
        InstanceBits {
            custom_index: self.custom_index,
            mask: self.mask,
            flags: self.vulkan_flags(),
            sbt_offset: (self.mesh.kind == MeshKind::Spheres) as u32,
        }
    }

    /// Vulkan's instance flags. Vulkan judges facing in object space and by default calls front
    /// the side `cross(v1 - v0, v2 - v0)` points to (clockwise seen from the ray, in its
    /// left-handed wording), our convention too; its counter-clockwise flag swaps the two.
    fn vulkan_flags(&self) -> u8 {
        let mut flags = 0;
        if self.flags.cull_disable {
            flags |= INSTANCE_CULL_DISABLE;
        }
        if self.flip_facing {
            flags |= INSTANCE_FRONT_COUNTERCLOCKWISE;
        }
        if self.flags.force_opaque {
            flags |= INSTANCE_FORCE_OPAQUE;
        }
        if self.flags.force_no_opaque {
            flags |= INSTANCE_FORCE_NO_OPAQUE;
        }
        flags
    }
}

/// Largest custom index an instance can carry (24 bits).
pub const MAX_CUSTOM_INDEX: u32 = (1 << 24) - 1;

/// Instances of meshes under one top-level acceleration structure.
///
/// The TLAS lives in the scene's frame: world coordinates minus `center` (the middle of the
/// instances' bounds), so that instance translations and ray origins far from the origin are
/// subtracted in f64 and reach f32 as small numbers.
pub struct Scene {
    pub instance_count: usize,
    pub center: DVec3,
    pub placements: Vec<Placement>,
    pub options: BuildOptions,
    pub stats: BuildStats,
    tlas: AccelerationStructure,
    // Where each instance's triangles live, for shaders (normals).
    instance_geometries: Buffer,
    instance_records: Buffer,
    instances: Vec<Instance>,
    // The meshes' BLAS and buffers must outlive the TLAS that points at them.
    meshes: Vec<Arc<Mesh>>,
    /// Each mesh's `generation` when this scene last placed it.
    mesh_generations: Vec<u64>,
    last_update_seconds: f64,
    /// The exact tier's structures, built on its first query.
    exact: Mutex<Option<Arc<ExactScene>>>,
}

impl Scene {
    pub fn build(ctx: &Arc<Context>, instances: &[Instance], options: BuildOptions, wait: &dyn Wait) -> Result<Scene> {
        if instances.len() as u64 > ctx.limits.max_instance_count {
            return Err(Error::Unsupported(format!(
                "{} instances exceed this device's maxInstanceCount ({})",
                instances.len(),
                ctx.limits.max_instance_count
            )));
        }
        if let Some((i, instance)) = instances.iter().enumerate().find(|(_, x)| x.custom_index > MAX_CUSTOM_INDEX) {
            return Err(invalid_value(format!(
                "instance {i} has custom_index {} but Vulkan keeps 24 bits (at most {MAX_CUSTOM_INDEX})",
                instance.custom_index
            )));
        }
        let (center, placements) = place(instances, None)?;
        let mut uploads = Uploads::default();
        let records = uploads.buffer(ctx, 64 * instances.len() as u64, GEOMETRY_INPUT, "instances", |out, _| {
            write_instance_records(&placements, out)
        })?;
        debug_assert_eq!(records.address() % 16, 0, "Vulkan wants instance data 16-byte aligned");
        let instance_geometries =
            uploads.buffer(ctx, 8 * instances.len() as u64, GEOMETRY_INPUT, "instance geometries", |out, _| {
                for (dst, x) in out.chunks_exact_mut(8).zip(instances) {
                    dst.copy_from_slice(&x.mesh.sources.address().to_ne_bytes());
                }
            })?;
        let input = instances_input(records.address(), instances.len());
        let (tlas, stats) = accel::build(ctx, &input, options, &uploads, wait)?;
        let mut meshes: Vec<Arc<Mesh>> = Vec::new();
        for instance in instances {
            if !meshes.iter().any(|m| Arc::ptr_eq(m, &instance.mesh)) {
                meshes.push(instance.mesh.clone());
            }
        }
        Ok(Scene {
            instance_count: instances.len(),
            center,
            placements,
            options,
            stats,
            tlas,
            instance_geometries,
            instance_records: records,
            instances: instances.to_vec(),
            mesh_generations: meshes.iter().map(|m| m.generation()).collect(),
            meshes,
            last_update_seconds: 0.0,
            exact: Mutex::new(None),
        })
    }

    /// Refits the TLAS in place after its instances moved (`transforms`, row-major 3×4 in f64)
    /// or changed masks, and picks up its meshes' `update`s. Needs `allow_update` at build; the
    /// scene keeps its frame (centre), so moves far from it cost f32 precision until a rebuild.
    pub fn update(
        &mut self,
        transforms: Option<Vec<[f64; 12]>>,
        masks: Option<Vec<u8>>,
        wait: &dyn Wait,
    ) -> Result<()> {
        if !self.options.allow_update {
            return Err(invalid_value("this scene was built without allow_update=True, so it cannot be refitted"));
        }
        let n = self.instances.len();
        for (name, len) in [("transforms", transforms.as_ref().map(Vec::len)), ("masks", masks.as_ref().map(Vec::len))]
        {
            if let Some(len) = len.filter(|&len| len != n) {
                return Err(invalid_value(format!("{name} has {len} entries for the scene's {n} instances")));
            }
        }
        let started = Instant::now();
        let mut instances = self.instances.clone();
        for (k, x) in instances.iter_mut().enumerate() {
            if let Some(t) = &transforms {
                x.transform = t[k];
            }
            if let Some(m) = &masks {
                x.mask = m[k];
            }
        }
        let (_, placements) = place(&instances, Some(self.center))?;
        let ctx = self.tlas.context().clone();
        let mut uploads = Uploads::default();
        uploads.overwrite(&ctx, &self.instance_records, |out| write_instance_records(&placements, out))?;
        let input = instances_input(self.instance_records.address(), n);
        accel::update(&ctx, &self.tlas, &input, self.options, self.stats.update_scratch_size, &uploads, wait)?;
        self.instances = instances;
        self.placements = placements;
        self.mesh_generations = self.meshes.iter().map(|m| m.generation()).collect();
        *self.exact.get_mut().unwrap_or_else(|e| e.into_inner()) = None;
        self.last_update_seconds = started.elapsed().as_secs_f64();
        Ok(())
    }

    pub fn last_update_seconds(&self) -> f64 {
        self.last_update_seconds
    }

    /// Tracing a scene whose meshes moved since it last placed them would use stale bounds.
    pub fn check_current(&self) -> Result<()> {
        match self.meshes.iter().zip(&self.mesh_generations).position(|(m, g)| m.generation() != *g) {
            Some(_) => Err(invalid_value(
                "a mesh of this scene was updated since the scene was built or updated: call scene.update() first",
            )),
            None => Ok(()),
        }
    }

    pub fn tlas_address(&self) -> u64 {
        self.tlas.address()
    }

    /// Whether any instance is a sphere set (boxes for the shaders' sphere test).
    pub fn has_spheres(&self) -> bool {
        self.meshes.iter().any(|m| m.kind == MeshKind::Spheres)
    }

    /// Whether every instance's triangles are opaque (no `force_no_opaque`).
    pub fn all_opaque(&self) -> bool {
        self.placements.iter().all(|p| !p.flags.force_no_opaque)
    }

    pub fn instance_geometries_address(&self) -> u64 {
        self.instance_geometries.address()
    }

    /// The exact tier's structures over this scene, built on first use.
    pub fn exact(&self, wait: &dyn Wait) -> Result<Arc<ExactScene>> {
        let mut exact = self.exact.lock().unwrap_or_else(|e| e.into_inner());
        if exact.is_none() {
            *exact = Some(Arc::new(ExactScene::build(self, wait)?));
        }
        Ok(exact.as_ref().expect("just built").clone())
    }

    /// The CPU tracer over this scene's instances (each mesh's hierarchy is built once).
    pub fn reference_tracer(&self) -> ReferenceTracer<'_> {
        ReferenceTracer::new(
            self.placements
                .iter()
                .map(|p| PlacedSet {
                    triangles: &p.triangles,
                    to_local: p.to_local,
                    custom_index: p.custom_index,
                    mask: p.mask,
                    bounds: p.bounds,
                    flip_facing: p.flip_facing,
                    cull_disable: p.flags.cull_disable,
                })
                .collect(),
        )
    }
}

fn write_instance_records(placements: &[Placement], out: &mut [u8]) {
    for (dst, p) in out.chunks_exact_mut(64).zip(placements) {
        dst.copy_from_slice(&accel::instance_record(&p.to_scene.to_rows_f32(), p.bits(), p.mesh.blas_address()));
    }
}

/// The build input of a TLAS over `count` instance records at `address`.
fn instances_input(address: u64, count: usize) -> BuildInput<'static> {
    let data = vk::AccelerationStructureGeometryInstancesDataKHR::default()
        .array_of_pointers(false)
        .data(vk::DeviceOrHostAddressConstKHR { device_address: address });
    let geometry = vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .geometry(vk::AccelerationStructureGeometryDataKHR { instances: data });
    BuildInput {
        ty: vk::AccelerationStructureTypeKHR::TOP_LEVEL,
        geometries: vec![geometry],
        primitive_counts: vec![count as u32],
        name: "scene TLAS",
    }
}

/// The scene's centre (the middle of its instances' bounds, unless `center` keeps an earlier one)
/// and each instance's placement relative to it, all in f64.
fn place(instances: &[Instance], center: Option<DVec3>) -> Result<(DVec3, Vec<Placement>)> {
    let triangles: Vec<Arc<TriangleSet>> = instances.iter().map(|x| x.mesh.triangles()).collect();
    // Object to world for the mesh's device frame: M (s v + c) + T = (s M) v + (M c + T).
    let to_world: Vec<Affine> = instances
        .iter()
        .map(|x| {
            let user = Affine::from_rows(&x.transform);
            Affine { linear: user.linear * x.mesh.scale, offset: user.point(x.mesh.center) }
        })
        .collect();
    let bounds = triangles.iter().zip(&to_world).fold(Aabb::EMPTY, |b, (t, m)| b.union(&t.bounds.transformed(m)));
    let center = center.unwrap_or(if instances.is_empty() { DVec3::ZERO } else { bounds.center() });
    let mut placements = Vec::with_capacity(instances.len());
    for (i, ((x, m), triangles)) in instances.iter().zip(&to_world).zip(triangles).enumerate() {
        let to_scene = Affine { offset: m.offset - center, ..*m };
        let to_local = to_scene.inverse().ok_or_else(|| {
            invalid_value(format!("instance {i} has a singular transform (its 3x3 part has no inverse)"))
        })?;
        placements.push(Placement {
            mesh: x.mesh.clone(),
            bounds: triangles.bounds.transformed(&to_scene),
            triangles,
            to_scene,
            to_local,
            custom_index: x.custom_index,
            mask: x.mask,
            flags: x.flags,
            flip_facing: (to_scene.linear.determinant() < 0.0) != x.flags.flip_facing,
        });
    }
    Ok((center, placements))
}

/// Bytes of one `ExactInstance` record in `shaders/exact.glsl` (136, padded to its dvec4 alignment).
const EXACT_INSTANCE_BYTES: usize = 160;

/// Relative slack of the exact tier's boxes: f32 traversal (origin, direction, instance transform
/// and the hardware's own box test, each a few ulps of the scene's size) must never miss a box
/// whose triangle the f64 test would hit. 2^-20 is 16 ulps of float32.
const EXACT_SLACK: f64 = 1.0 / (1u64 << 20) as f64;

/// The exact tier's view of a scene: per mesh, one conservative box per triangle (an AABB BLAS)
/// and its vertices in f64; per instance, the f64 map from the scene's frame to the mesh's.
/// Candidates from f32 traversal of the boxes are decided by the f64 watertight test in a shader.
pub struct ExactScene {
    tlas: AccelerationStructure,
    instances: Buffer,
    /// The scene's bounds in its frame, padded and rounded outward to f32 (min xyz, max xyz).
    bounds: [f32; 6],
    _records: Buffer,
    _meshes: Vec<ExactMesh>,
}

/// The exact tier's copy of one mesh: a box per triangle (all parts in one geometry, the device
/// order of each part in turn) and what the shader reads to test and name them.
struct ExactMesh {
    blas: AccelerationStructure,
    _boxes: Buffer,
    vertices: Buffer,
    /// u32 corner triples (indices among all parts' vertices), in box order.
    faces: Buffer,
    /// Box -> caller's triangle among all parts, where they differ.
    primitive_order: Option<Buffer>,
    /// The first triangle of each part among all, then the total (u32 each).
    part_offsets: Buffer,
}

impl ExactScene {
    fn build(scene: &Scene, wait: &dyn Wait) -> Result<ExactScene> {
        let ctx = scene.tlas.context();
        if !ctx.info.shader_float64 {
            return Err(Error::Unsupported(format!(
                "{} has no shaderFloat64, which precision='exact' needs; precision='reference' gives the same answers on the CPU",
                ctx.info.name
            )));
        }
        let scene_bounds = scene.placements.iter().fold(Aabb::EMPTY, |b, p| b.union(&p.bounds));
        let world_slack = EXACT_SLACK * scene_bounds.extent().max_element();
        let options = BuildOptions { preference: BuildPreference::FastTrace, allow_update: false, compact: false };
        let mut built: Vec<ExactMesh> = Vec::new();
        for mesh in &scene.meshes {
            let triangles =
                &scene.placements.iter().find(|p| Arc::ptr_eq(&p.mesh, mesh)).expect("placed mesh").triangles;
            // How far the world's slack reaches in this mesh's frame: the most any placement of
            // it stretches a vector (the max-row-sum norm of its world-to-mesh map).
            let stretch = scene
                .placements
                .iter()
                .filter(|p| Arc::ptr_eq(&p.mesh, mesh))
                .map(|p| {
                    let m = p.to_local.linear.transpose();
                    (0..3).map(|r| m.col(r).abs().element_sum()).fold(0.0, f64::max)
                })
                .fold(0.0, f64::max);
            let pad = world_slack * stretch + EXACT_SLACK * triangles.bounds.extent().max_element();
            // Box order: each part's device order in turn, as caller's triangles among all.
            let order: Vec<u32> = mesh
                .parts
                .iter()
                .enumerate()
                .flat_map(|(k, part)| {
                    (0..part.triangle_count).map(move |d| triangles.global(k, part.caller_triangle(d)) as u32)
                })
                .collect();
            let identity = order.iter().enumerate().all(|(d, &t)| d as u32 == t);
            let mut uploads = Uploads::default();
            let boxes = uploads.buffer(ctx, 24 * order.len() as u64, GEOMETRY_INPUT, "exact boxes", |out, _| {
                for (dst, &t) in out.chunks_exact_mut(24).zip(&order) {
                    let b = Aabb::of_points(triangles.triangle(t as usize)).padded(pad);
                    let corners = [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z];
                    for (k, (d, v)) in dst.chunks_exact_mut(4).zip(corners).enumerate() {
                        d.copy_from_slice(&round_outward(v, k < 3).to_ne_bytes());
                    }
                }
            })?;
            let u32s = |values: &mut dyn Iterator<Item = u32>, out: &mut [u8]| {
                for (dst, v) in out.chunks_exact_mut(4).zip(values) {
                    dst.copy_from_slice(&v.to_ne_bytes());
                }
            };
            let vertices = uploads.buffer(
                ctx,
                24 * triangles.vertices.len() as u64,
                GEOMETRY_INPUT,
                "exact vertices",
                |out, _| {
                    for (dst, v) in out.chunks_exact_mut(24).zip(&triangles.vertices) {
                        for (d, c) in dst.chunks_exact_mut(8).zip(v.to_array()) {
                            d.copy_from_slice(&c.to_ne_bytes());
                        }
                    }
                },
            )?;
            let faces = uploads.buffer(ctx, 12 * order.len() as u64, GEOMETRY_INPUT, "exact faces", |out, _| {
                u32s(&mut order.iter().flat_map(|&t| triangles.faces[t as usize]), out)
            })?;
            let primitive_order = if identity {
                None
            } else {
                Some(uploads.buffer(ctx, 4 * order.len() as u64, GEOMETRY_INPUT, "exact order", |out, _| {
                    u32s(&mut order.iter().copied(), out)
                })?)
            };
            let offsets = &triangles.part_offsets;
            let part_offsets =
                uploads.buffer(ctx, 4 * offsets.len() as u64, GEOMETRY_INPUT, "exact part offsets", |out, _| {
                    u32s(&mut offsets.iter().copied(), out)
                })?;
            let data = vk::AccelerationStructureGeometryAabbsDataKHR::default()
                .data(vk::DeviceOrHostAddressConstKHR { device_address: boxes.address() })
                .stride(24);
            let geometry = vk::AccelerationStructureGeometryKHR::default()
                .geometry_type(vk::GeometryTypeKHR::AABBS)
                .geometry(vk::AccelerationStructureGeometryDataKHR { aabbs: data })
                .flags(vk::GeometryFlagsKHR::OPAQUE);
            let input = BuildInput {
                ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                geometries: vec![geometry],
                primitive_counts: vec![order.len() as u32],
                name: "exact boxes BLAS",
            };
            let (blas, _) = accel::build(ctx, &input, options, &uploads, wait)?;
            built.push(ExactMesh { blas, _boxes: boxes, vertices, faces, primitive_order, part_offsets });
        }
        let mesh_index = |p: &Placement| scene.meshes.iter().position(|m| Arc::ptr_eq(m, &p.mesh)).expect("scene mesh");
        let mut uploads = Uploads::default();
        let n = scene.placements.len();
        let records = uploads.buffer(ctx, 64 * n as u64, GEOMETRY_INPUT, "exact instances", |out, _| {
            for (dst, p) in out.chunks_exact_mut(64).zip(&scene.placements) {
                let blas = built[mesh_index(p)].blas.address();
                // Boxes only: facing and culling are the exact shader's, opacity does not apply.
                let bits = InstanceBits { flags: 0, sbt_offset: 0, ..p.bits() };
                dst.copy_from_slice(&accel::instance_record(&p.to_scene.to_rows_f32(), bits, blas));
            }
        })?;
        let instances = uploads.buffer(
            ctx,
            (EXACT_INSTANCE_BYTES * n.max(1)) as u64,
            GEOMETRY_INPUT,
            "exact instance data",
            |out, _| {
                for (dst, p) in out.chunks_exact_mut(EXACT_INSTANCE_BYTES).zip(&scene.placements) {
                    let (l, o) = (p.to_local.linear, p.to_local.offset);
                    let mut doubles = [0f64; 12];
                    for r in 0..3 {
                        let row = l.row(r);
                        doubles[4 * r..4 * r + 4].copy_from_slice(&[row.x, row.y, row.z, o[r]]);
                    }
                    for (d, v) in dst[..96].chunks_exact_mut(8).zip(doubles) {
                        d.copy_from_slice(&v.to_ne_bytes());
                    }
                    let mesh = &built[mesh_index(p)];
                    dst[96..104].copy_from_slice(&mesh.vertices.address().to_ne_bytes());
                    dst[104..112].copy_from_slice(&mesh.faces.address().to_ne_bytes());
                    let order = mesh.primitive_order.as_ref().map_or(0, |b| b.address());
                    dst[112..120].copy_from_slice(&order.to_ne_bytes());
                    dst[120..128].copy_from_slice(&mesh.part_offsets.address().to_ne_bytes());
                    let parts = p.triangles.part_offsets.len() as u32 - 1;
                    dst[128..132].copy_from_slice(&parts.to_ne_bytes());
                    let flags = p.flags.cull_disable as u32 | (p.flip_facing as u32) << 1;
                    dst[132..136].copy_from_slice(&flags.to_ne_bytes());
                    dst[136..].fill(0);
                }
            },
        )?;
        let input = instances_input(records.address(), n);
        let (tlas, _) = accel::build(ctx, &input, scene.options, &uploads, wait)?;
        let padded =
            if n == 0 { Aabb { min: DVec3::ZERO, max: DVec3::ZERO } } else { scene_bounds.padded(world_slack) };
        let bounds = [
            round_outward(padded.min.x, true),
            round_outward(padded.min.y, true),
            round_outward(padded.min.z, true),
            round_outward(padded.max.x, false),
            round_outward(padded.max.y, false),
            round_outward(padded.max.z, false),
        ];
        Ok(ExactScene { tlas, instances, bounds, _records: records, _meshes: built })
    }

    pub fn tlas_address(&self) -> u64 {
        self.tlas.address()
    }

    pub fn instances_address(&self) -> u64 {
        self.instances.address()
    }

    pub fn bounds_f32(&self) -> [f32; 6] {
        self.bounds
    }
}

/// The f32 nearest to `v` on the outside of a box: below it for a minimum, above for a maximum.
fn round_outward(v: f64, is_min: bool) -> f32 {
    let f = v as f32;
    match (is_min, (f as f64).partial_cmp(&v)) {
        (true, Some(std::cmp::Ordering::Greater)) => f.next_down(),
        (false, Some(std::cmp::Ordering::Less)) => f.next_up(),
        _ => f,
    }
}

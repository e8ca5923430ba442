//! The Vulkan engine's hierarchy over a mesh: a bottom-level acceleration structure over device
//! copies of the vertices and faces (or the spheres' boxes), and the records shaders read.

use std::any::Any;
use std::sync::Arc;

use ash::vk;
use glam::DVec3;

use super::mesh::{Mesh, MeshBatch, MeshGeometry, MeshHierarchy, MeshInput};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::{Indices, Vec3s};
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::geometry::morton::morton_order;
use crate::geometry::precision::Aabb;
use crate::geometry::rays::PerRay;
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::accel::{self, AccelerationStructure, BuildInput};
use crate::gpu::context::{vulkan_vertex_format, Context};
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};
use crate::gpu::records::{GeometrySource, SPHERE_SOURCE};

/// A mesh's BLAS and the device buffers it is built over.
pub struct VulkanMesh {
    blas: AccelerationStructure,
    stats: BuildStats,
    /// One per geometry of the BLAS.
    pub(super) parts: Vec<Part>,
    /// A `GeometrySource` per part, read by shaders (normals, caller's triangle indices).
    sources: Buffer,
    /// The same records without opacity, for instances forced opaque (meshes with opacity only).
    opaque_sources: Option<Buffer>,
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

    /// Uploads a sphere set (centres in the mesh's device frame, and radii) in f32 (centre,
    /// radius), and their boxes.
    fn spheres(ctx: &Arc<Context>, uploads: &mut Uploads, spheres: &[(DVec3, f64)]) -> Result<Part> {
        let records: Vec<[f32; 4]> = spheres
            .iter()
            .map(|&(c, r)| {
                let local = c.as_vec3();
                [local.x, local.y, local.z, r as f32]
            })
            .collect();
        let records = uploads.records(ctx, &records, GEOMETRY_INPUT, "spheres")?;
        // Boxes hold the f32 spheres whole: rounded outward from their f64 extent.
        let boxes: Vec<[f32; 6]> = spheres
            .iter()
            .map(|&(c, r)| {
                let half = DVec3::splat(r * (1.0 + 1e-6));
                Aabb { min: c - half, max: c + half }.outward_f32()
            })
            .collect();
        let boxes = uploads.records(ctx, &boxes, GEOMETRY_INPUT, "sphere boxes")?;
        Ok(Part {
            vertex_count: spheres.len(),
            triangle_count: spheres.len(),
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

/// A mesh's device buffers, uploaded (or recorded for upload) and ready for its BLAS build.
struct PreparedMesh {
    geometry: MeshGeometry,
    parts: Vec<Part>,
    sources: Buffer,
    opaque_sources: Option<Buffer>,
}

impl PreparedMesh {
    fn triangles(ctx: &Arc<Context>, item: &MeshInput, format: VertexFormat, uploads: &mut Uploads) -> Result<Self> {
        let geometry = MeshGeometry::triangles(item, format)?;
        check_device_limits(ctx, item.parts.len(), geometry.triangle_count, format)?;
        let local: &[f64] = bytemuck::cast_slice(&geometry.triangles.vertices);
        let mut first_vertex = 0;
        let mut parts = Vec::with_capacity(item.parts.len());
        for (k, &(vertices, faces)) in item.parts.iter().enumerate() {
            let own = &local[3 * first_vertex..3 * (first_vertex + vertices.rows())];
            first_vertex += vertices.rows();
            let offsets = &geometry.triangles.part_offsets;
            let own_opacity = geometry.opacity.as_ref().map(|o| &o[offsets[k] as usize..offsets[k + 1] as usize]);
            parts.push(Part::triangles(ctx, uploads, (vertices, faces), own, format, own_opacity)?);
        }
        let records =
            |opaque: bool| -> Vec<GeometrySource> { parts.iter().map(|p| p.source(format as u32, opaque)).collect() };
        let sources = uploads.records(ctx, &records(false), GEOMETRY_INPUT, "geometry sources")?;
        let opaque_sources = match geometry.opacity {
            Some(_) => Some(uploads.records(ctx, &records(true), GEOMETRY_INPUT, "opaque geometry sources")?),
            None => None,
        };
        Ok(PreparedMesh { geometry, parts, sources, opaque_sources })
    }

    fn input(&self) -> BuildInput<'static> {
        mesh_input(&self.parts, self.geometry.vertex_format)
    }

    fn finish(self, options: BuildOptions, blas: AccelerationStructure, stats: BuildStats) -> Mesh {
        let hierarchy =
            VulkanMesh { blas, stats, parts: self.parts, sources: self.sources, opaque_sources: self.opaque_sources };
        Mesh::new(self.geometry, options, Box::new(hierarchy))
    }
}

/// Builds many meshes (each from its parts) in as few submissions as `scratch_budget` bytes of
/// build scratch allow (see `accel::build_many`); the error of a bad input names its position.
pub fn build_vulkan_meshes(ctx: &Arc<Context>, batch: MeshBatch) -> Result<Vec<Mesh>> {
    let MeshBatch { items, options, format, scratch_budget, interrupt } = batch;
    let mut uploads = Uploads::default();
    let prepared = items
        .iter()
        .enumerate()
        .map(|(k, item)| {
            PreparedMesh::triangles(ctx, item, format, &mut uploads).map_err(|e| match (e, items.len()) {
                (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("mesh {k}: {m}")),
                (e, _) => e,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let inputs: Vec<BuildInput> = prepared.iter().map(PreparedMesh::input).collect();
    let built = accel::build_many(ctx, &inputs, options, &uploads, scratch_budget, interrupt)?;
    Ok(prepared.into_iter().zip(built).map(|(p, (blas, stats))| p.finish(options, blas, stats)).collect())
}

/// A set of spheres (`centers` (N, 3), `radii` one per sphere or one for all): a BLAS of one box
/// per sphere, whose spheres a shader intersects. Scenes mix them with triangle meshes.
pub fn build_vulkan_spheres(ctx: &Arc<Context>, centers: Vec3s, radii: PerRay, options: BuildOptions) -> Result<Mesh> {
    let geometry = MeshGeometry::spheres(centers, radii)?;
    let n = geometry.spheres.len();
    if n as u64 > ctx.limits.max_primitive_count {
        return Err(Error::Unsupported(format!(
            "{n} spheres exceed this device's maxPrimitiveCount ({})",
            ctx.limits.max_primitive_count
        )));
    }
    let mut uploads = Uploads::default();
    let part = Part::spheres(ctx, &mut uploads, &geometry.spheres)?;
    let sources = uploads.records(ctx, &[part.source(SPHERE_SOURCE, true)], GEOMETRY_INPUT, "geometry sources")?;
    let prepared = PreparedMesh { geometry, parts: vec![part], sources, opaque_sources: None };
    let (blas, stats) = accel::build(ctx, &prepared.input(), options, &uploads)?;
    Ok(prepared.finish(options, blas, stats))
}

impl VulkanMesh {
    /// The Vulkan engine's hierarchy of `mesh`.
    pub fn of(mesh: &Mesh) -> Result<&VulkanMesh> {
        mesh.hierarchy::<VulkanMesh>()
    }

    pub fn blas_address(&self) -> u64 {
        self.blas.address()
    }

    /// The `GeometrySource` records an instance reads: without opacity where it is forced opaque.
    pub(super) fn sources_address(&self, force_opaque: bool) -> u64 {
        match (&self.opaque_sources, force_opaque) {
            (Some(opaque), true) => opaque.address(),
            _ => self.sources.address(),
        }
    }
}

impl MeshHierarchy for VulkanMesh {
    fn stats(&self) -> BuildStats {
        self.stats
    }

    /// Uploads the moved vertices and refits the BLAS in place (Vulkan's UPDATE mode with
    /// source = destination).
    fn refit(&self, local: &[f64], format: VertexFormat, options: BuildOptions) -> Result<()> {
        let ctx = self.blas.context();
        let [part] = self.parts.as_slice() else {
            return Err(Error::Unsupported("Mesh.update refits single-part meshes; rebuild a multi-part mesh".into()));
        };
        let mut uploads = Uploads::default();
        uploads.overwrite(ctx, &part.vertices, |out| format.write(local, out))?;
        let input = mesh_input(std::slice::from_ref(part), format);
        accel::update(ctx, &self.blas, &input, options, self.stats.update_scratch_size, &uploads)?;
        Ok(())
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Checks what the device can build from a mesh of `parts` parts and `triangles` triangles.
fn check_device_limits(ctx: &Context, parts: usize, triangles: usize, format: VertexFormat) -> Result<()> {
    if parts as u64 > ctx.limits.max_geometry_count {
        return Err(Error::Unsupported(format!(
            "{parts} parts exceed this device's maxGeometryCount ({})",
            ctx.limits.max_geometry_count
        )));
    }
    if triangles as u64 > ctx.limits.max_primitive_count {
        return Err(Error::Unsupported(format!(
            "{triangles} triangles exceed this device's maxPrimitiveCount ({})",
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
    Ok(())
}

/// The build input of a mesh's BLAS: one geometry per part (opaque unless some of its triangles
/// let light through).
fn mesh_input(parts: &[Part], format: VertexFormat) -> BuildInput<'static> {
    BuildInput {
        ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
        geometries: parts.iter().map(|p| p.geometry(format)).collect(),
        primitive_counts: parts.iter().map(|p| p.triangle_count as u32).collect(),
        name: "mesh BLAS",
    }
}

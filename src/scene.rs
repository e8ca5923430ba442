//! Meshes (a bottom-level structure over device copies of vertices and faces) and scenes (a
//! top-level structure over instances of meshes): the level users work at.

use std::sync::Arc;

use ash::vk;

use crate::accel::{self, AccelerationStructure, BuildInput, BuildOptions, BuildStats};
use crate::context::{Context, Wait};
use crate::error::{invalid_value, Error, Result};
use crate::input::{check_faces, check_vertices, morton_order, write_vertices_f32, Indices, Vec3s};
use crate::memory::{Buffer, Uploads};

const GEOMETRY_INPUT: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw(),
);

/// Bytes of one `GeometrySource` record in `shaders/common.glsl`.
const GEOMETRY_SOURCE_BYTES: usize = 32;

/// A triangle mesh on the device with its bottom-level acceleration structure.
pub struct Mesh {
    pub vertex_count: usize,
    pub triangle_count: usize,
    pub options: BuildOptions,
    pub stats: BuildStats,
    blas: AccelerationStructure,
    // Read by shaders (normals) through `sources`; kept alive as long as the mesh.
    _vertices: Buffer,
    _indices: Buffer,
    _primitive_order: Option<Buffer>,
    sources: Buffer,
}

impl Mesh {
    /// Checks and uploads vertices and faces, then builds the BLAS (opaque triangles).
    pub fn build(
        ctx: &Arc<Context>,
        vertices: Vec3s,
        faces: Indices,
        options: BuildOptions,
        wait: &dyn Wait,
    ) -> Result<Mesh> {
        check_vertices("vertices", vertices)?;
        check_faces("faces", faces, vertices.rows())?;
        let triangle_count = faces.triangles();
        if triangle_count as u64 > ctx.limits.max_primitive_count {
            return Err(Error::Unsupported(format!(
                "{triangle_count} triangles exceed this device's maxPrimitiveCount ({})",
                ctx.limits.max_primitive_count
            )));
        }
        let mut uploads = Uploads::default();
        let vertex_bytes = 12 * vertices.rows() as u64;
        let vertex_buffer = uploads
            .buffer(ctx, vertex_bytes, GEOMETRY_INPUT, "vertices", |out, _| write_vertices_f32(vertices, out))?;
        let order = ctx.presort_primitives.then(|| morton_order(vertices, faces));
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
        let sources =
            uploads.buffer(ctx, GEOMETRY_SOURCE_BYTES as u64, GEOMETRY_INPUT, "geometry sources", |out, _| {
                out[0..8].copy_from_slice(&vertex_buffer.address().to_ne_bytes());
                out[8..16].copy_from_slice(&index_buffer.address().to_ne_bytes());
                out[16..24].copy_from_slice(&primitive_order.as_ref().map_or(0, |b| b.address()).to_ne_bytes());
                out[24..28].copy_from_slice(&(faces.is_u16() as u32).to_ne_bytes());
                out[28..32].fill(0);
            })?;

        let triangles = vk::AccelerationStructureGeometryTrianglesDataKHR::default()
            .vertex_format(vk::Format::R32G32B32_SFLOAT)
            .vertex_data(vk::DeviceOrHostAddressConstKHR { device_address: vertex_buffer.address() })
            .vertex_stride(12)
            .max_vertex(vertices.rows() as u32 - 1)
            .index_type(if faces.is_u16() { vk::IndexType::UINT16 } else { vk::IndexType::UINT32 })
            .index_data(vk::DeviceOrHostAddressConstKHR { device_address: index_buffer.address() });
        let geometry = vk::AccelerationStructureGeometryKHR::default()
            .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
            .geometry(vk::AccelerationStructureGeometryDataKHR { triangles })
            .flags(vk::GeometryFlagsKHR::OPAQUE);
        let input = BuildInput {
            ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
            geometries: vec![geometry],
            primitive_counts: vec![triangle_count as u32],
            name: "mesh BLAS",
        };
        let (blas, stats) = accel::build(ctx, &input, options, &uploads, wait)?;
        Ok(Mesh {
            vertex_count: vertices.rows(),
            triangle_count,
            options,
            stats,
            blas,
            _vertices: vertex_buffer,
            _indices: index_buffer,
            _primitive_order: primitive_order,
            sources,
        })
    }

    pub fn blas_address(&self) -> u64 {
        self.blas.address()
    }
}

/// One placement of a mesh in a scene.
#[derive(Clone)]
pub struct Instance {
    pub mesh: Arc<Mesh>,
    /// Row-major 3×4 affine transform (object to world).
    pub transform: [f32; 12],
    pub custom_index: u32,
    pub mask: u8,
}

pub const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Largest custom index an instance can carry (24 bits).
pub const MAX_CUSTOM_INDEX: u32 = (1 << 24) - 1;

/// Instances of meshes under one top-level acceleration structure.
pub struct Scene {
    pub instance_count: usize,
    pub options: BuildOptions,
    pub stats: BuildStats,
    tlas: AccelerationStructure,
    // Where each instance's triangles live, for shaders (normals).
    instance_geometries: Buffer,
    _instance_records: Buffer,
    // The meshes' BLAS and buffers must outlive the TLAS that points at them.
    _meshes: Vec<Arc<Mesh>>,
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
        let mut uploads = Uploads::default();
        let records = uploads.buffer(ctx, 64 * instances.len() as u64, GEOMETRY_INPUT, "instances", |out, _| {
            for (dst, x) in out.chunks_exact_mut(64).zip(instances) {
                dst.copy_from_slice(&accel::instance_record(
                    &x.transform,
                    x.custom_index,
                    x.mask,
                    0,
                    x.mesh.blas_address(),
                ));
            }
        })?;
        debug_assert_eq!(records.address() % 16, 0, "Vulkan wants instance data 16-byte aligned");
        let instance_geometries =
            uploads.buffer(ctx, 8 * instances.len() as u64, GEOMETRY_INPUT, "instance geometries", |out, _| {
                for (dst, x) in out.chunks_exact_mut(8).zip(instances) {
                    dst.copy_from_slice(&x.mesh.sources.address().to_ne_bytes());
                }
            })?;
        let instances_data = vk::AccelerationStructureGeometryInstancesDataKHR::default()
            .array_of_pointers(false)
            .data(vk::DeviceOrHostAddressConstKHR { device_address: records.address() });
        let geometry = vk::AccelerationStructureGeometryKHR::default()
            .geometry_type(vk::GeometryTypeKHR::INSTANCES)
            .geometry(vk::AccelerationStructureGeometryDataKHR { instances: instances_data });
        let input = BuildInput {
            ty: vk::AccelerationStructureTypeKHR::TOP_LEVEL,
            geometries: vec![geometry],
            primitive_counts: vec![instances.len() as u32],
            name: "scene TLAS",
        };
        let (tlas, stats) = accel::build(ctx, &input, options, &uploads, wait)?;
        let mut meshes: Vec<Arc<Mesh>> = Vec::new();
        for instance in instances {
            if !meshes.iter().any(|m| Arc::ptr_eq(m, &instance.mesh)) {
                meshes.push(instance.mesh.clone());
            }
        }
        Ok(Scene {
            instance_count: instances.len(),
            options,
            stats,
            tlas,
            instance_geometries,
            _instance_records: records,
            _meshes: meshes,
        })
    }

    pub fn tlas_address(&self) -> u64 {
        self.tlas.address()
    }

    pub fn instance_geometries_address(&self) -> u64 {
        self.instance_geometries.address()
    }
}

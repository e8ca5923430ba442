//! Meshes (a bottom-level structure over device copies of vertices and faces) and scenes (a
//! top-level structure over instances of meshes): the level users work at.

use std::sync::{Arc, Mutex};

use ash::vk;
use glam::DVec3;

use crate::accel::{self, AccelerationStructure, BuildInput, BuildOptions, BuildPreference, BuildStats};
use crate::context::{Context, Wait};
use crate::error::{invalid_value, Error, Result};
use crate::input::{check_faces, check_vertices, morton_order, write_vertices_f32, Indices, Vec3s};
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

/// A triangle mesh on the device with its bottom-level acceleration structure.
///
/// The device holds the vertices re-centred on their bounding box (`center`, subtracted in f64
/// before anything becomes f32), so that a mesh far from the origin keeps its full f32 precision;
/// scenes add the centre back in their instance transforms. The host keeps the same re-centred
/// vertices in f64 for the f64 precision tiers.
pub struct Mesh {
    pub vertex_count: usize,
    pub triangle_count: usize,
    pub center: DVec3,
    pub triangles: TriangleSet,
    pub options: BuildOptions,
    pub stats: BuildStats,
    blas: AccelerationStructure,
    /// Device triangle -> caller's triangle, where the device holds them in another order.
    device_order: Option<Vec<u32>>,
    // Read by shaders (normals) through `sources`; kept alive as long as the mesh.
    _vertices: Buffer,
    indices: Buffer,
    index_is_u16: bool,
    primitive_order: Option<Buffer>,
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
        let (host_triangles, center) = recentred_triangles(vertices, faces);
        let local: &[f64] = {
            // SAFETY: DVec3 is three f64 in a repr(C) struct, so a slice of them is a slice of f64.
            let v = &host_triangles.vertices;
            unsafe { std::slice::from_raw_parts(v.as_ptr() as *const f64, 3 * v.len()) }
        };
        let mut uploads = Uploads::default();
        let vertex_bytes = 12 * vertices.rows() as u64;
        let vertex_buffer = uploads.buffer(ctx, vertex_bytes, GEOMETRY_INPUT, "vertices", |out, _| {
            write_vertices_f32(Vec3s::F64(local), out)
        })?;
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
            center,
            triangles: host_triangles,
            options,
            stats,
            blas,
            device_order: order,
            _vertices: vertex_buffer,
            indices: index_buffer,
            index_is_u16: faces.is_u16(),
            primitive_order,
            sources,
        })
    }

    pub fn blas_address(&self) -> u64 {
        self.blas.address()
    }

    /// The caller's triangle held at `device` on the device.
    fn caller_triangle(&self, device: usize) -> usize {
        self.device_order.as_ref().map_or(device, |order| order[device] as usize)
    }
}

/// The mesh in f64, re-centred on its bounding box, and that centre.
fn recentred_triangles(vertices: Vec3s, faces: Indices) -> (TriangleSet, DVec3) {
    let points: Vec<DVec3> = (0..vertices.rows()).map(|i| DVec3::from_array(vertices.row_f64(i))).collect();
    let center = Aabb::of_points(points.iter().copied()).center();
    let local = points.into_iter().map(|p| p - center).collect();
    let corners = (0..faces.triangles()).map(|t| [0, 1, 2].map(|k| faces.corner(t, k) as u32)).collect();
    (TriangleSet::new(local, corners), center)
}

/// One placement of a mesh in a scene.
#[derive(Clone)]
pub struct Instance {
    pub mesh: Arc<Mesh>,
    /// Row-major 3×4 affine transform (object to world), in f64.
    pub transform: [f64; 12],
    pub custom_index: u32,
    pub mask: u8,
}

pub const IDENTITY: [f64; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Where an instance's mesh sits in the scene's frame (world coordinates minus the scene centre).
pub struct Placement {
    pub mesh: Arc<Mesh>,
    /// From the mesh's re-centred frame to the scene's frame.
    pub to_scene: Affine,
    /// The inverse: from the scene's frame to the mesh's.
    pub to_local: Affine,
    pub custom_index: u32,
    pub mask: u8,
    /// The mesh's bounds in the scene's frame.
    pub bounds: Aabb,
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
    _instance_records: Buffer,
    // The meshes' BLAS and buffers must outlive the TLAS that points at them.
    meshes: Vec<Arc<Mesh>>,
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
        let (center, placements) = place(instances)?;
        let mut uploads = Uploads::default();
        let records = uploads.buffer(ctx, 64 * instances.len() as u64, GEOMETRY_INPUT, "instances", |out, _| {
            for (dst, p) in out.chunks_exact_mut(64).zip(&placements) {
                dst.copy_from_slice(&accel::instance_record(
                    &p.to_scene.to_rows_f32(),
                    p.custom_index,
                    p.mask,
                    0,
                    p.mesh.blas_address(),
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
            center,
            placements,
            options,
            stats,
            tlas,
            instance_geometries,
            _instance_records: records,
            meshes,
            exact: Mutex::new(None),
        })
    }

    pub fn tlas_address(&self) -> u64 {
        self.tlas.address()
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
                    triangles: &p.mesh.triangles,
                    to_local: p.to_local,
                    custom_index: p.custom_index,
                    mask: p.mask,
                    bounds: p.bounds,
                })
                .collect(),
        )
    }
}

/// The scene's centre and each instance's placement relative to it, all in f64.
fn place(instances: &[Instance]) -> Result<(DVec3, Vec<Placement>)> {
    // Object to world for the re-centred mesh: M (v + c) + T = M v + (M c + T).
    let to_world: Vec<Affine> = instances
        .iter()
        .map(|x| {
            let user = Affine::from_rows(&x.transform);
            Affine { linear: user.linear, offset: user.point(x.mesh.center) }
        })
        .collect();
    let bounds =
        instances.iter().zip(&to_world).fold(Aabb::EMPTY, |b, (x, m)| b.union(&x.mesh.triangles.bounds.transformed(m)));
    let center = if instances.is_empty() { DVec3::ZERO } else { bounds.center() };
    let mut placements = Vec::with_capacity(instances.len());
    for (i, (x, m)) in instances.iter().zip(&to_world).enumerate() {
        let to_scene = Affine { offset: m.offset - center, ..*m };
        let to_local = to_scene.inverse().ok_or_else(|| {
            invalid_value(format!("instance {i} has a singular transform (its 3x3 part has no inverse)"))
        })?;
        placements.push(Placement {
            mesh: x.mesh.clone(),
            bounds: x.mesh.triangles.bounds.transformed(&to_scene),
            to_scene,
            to_local,
            custom_index: x.custom_index,
            mask: x.mask,
        });
    }
    Ok((center, placements))
}

/// Bytes of one `ExactInstance` record in `shaders/exact.glsl`.
const EXACT_INSTANCE_BYTES: usize = 128;

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
    _meshes: Vec<(AccelerationStructure, Buffer, Buffer)>,
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
        let mut built: Vec<(AccelerationStructure, Buffer, Buffer)> = Vec::new();
        for mesh in &scene.meshes {
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
            let pad = world_slack * stretch + EXACT_SLACK * mesh.triangles.bounds.extent().max_element();
            let mut uploads = Uploads::default();
            let aabbs =
                uploads.buffer(ctx, 24 * mesh.triangle_count as u64, GEOMETRY_INPUT, "exact boxes", |out, _| {
                    for (device, dst) in out.chunks_exact_mut(24).enumerate() {
                        let b = Aabb::of_points(mesh.triangles.triangle(mesh.caller_triangle(device))).padded(pad);
                        let corners = [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z];
                        for (k, (d, v)) in dst.chunks_exact_mut(4).zip(corners).enumerate() {
                            d.copy_from_slice(&round_outward(v, k < 3).to_ne_bytes());
                        }
                    }
                })?;
            let vertices64 =
                uploads.buffer(ctx, 24 * mesh.vertex_count as u64, GEOMETRY_INPUT, "exact vertices", |out, _| {
                    for (dst, v) in out.chunks_exact_mut(24).zip(&mesh.triangles.vertices) {
                        for (d, c) in dst.chunks_exact_mut(8).zip(v.to_array()) {
                            d.copy_from_slice(&c.to_ne_bytes());
                        }
                    }
                })?;
            let data = vk::AccelerationStructureGeometryAabbsDataKHR::default()
                .data(vk::DeviceOrHostAddressConstKHR { device_address: aabbs.address() })
                .stride(24);
            let geometry = vk::AccelerationStructureGeometryKHR::default()
                .geometry_type(vk::GeometryTypeKHR::AABBS)
                .geometry(vk::AccelerationStructureGeometryDataKHR { aabbs: data })
                .flags(vk::GeometryFlagsKHR::OPAQUE);
            let input = BuildInput {
                ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                geometries: vec![geometry],
                primitive_counts: vec![mesh.triangle_count as u32],
                name: "exact boxes BLAS",
            };
            let (blas, _) = accel::build(ctx, &input, options, &uploads, wait)?;
            built.push((blas, aabbs, vertices64));
        }
        let mesh_index = |p: &Placement| scene.meshes.iter().position(|m| Arc::ptr_eq(m, &p.mesh)).expect("scene mesh");
        let mut uploads = Uploads::default();
        let n = scene.placements.len();
        let records = uploads.buffer(ctx, 64 * n as u64, GEOMETRY_INPUT, "exact instances", |out, _| {
            for (dst, p) in out.chunks_exact_mut(64).zip(&scene.placements) {
                let blas = built[mesh_index(p)].0.address();
                dst.copy_from_slice(&accel::instance_record(
                    &p.to_scene.to_rows_f32(),
                    p.custom_index,
                    p.mask,
                    0,
                    blas,
                ));
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
                    let mesh = &p.mesh;
                    dst[96..104].copy_from_slice(&built[mesh_index(p)].2.address().to_ne_bytes());
                    dst[104..112].copy_from_slice(&mesh.indices.address().to_ne_bytes());
                    dst[112..120]
                        .copy_from_slice(&mesh.primitive_order.as_ref().map_or(0, |b| b.address()).to_ne_bytes());
                    dst[120..124].copy_from_slice(&(mesh.index_is_u16 as u32).to_ne_bytes());
                    dst[124..128].fill(0);
                }
            },
        )?;
        let data = vk::AccelerationStructureGeometryInstancesDataKHR::default()
            .array_of_pointers(false)
            .data(vk::DeviceOrHostAddressConstKHR { device_address: records.address() });
        let geometry = vk::AccelerationStructureGeometryKHR::default()
            .geometry_type(vk::GeometryTypeKHR::INSTANCES)
            .geometry(vk::AccelerationStructureGeometryDataKHR { instances: data });
        let input = BuildInput {
            ty: vk::AccelerationStructureTypeKHR::TOP_LEVEL,
            geometries: vec![geometry],
            primitive_counts: vec![n as u32],
            name: "exact TLAS",
        };
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

//! The exact tier's view of a scene: conservative per-triangle boxes and f64 vertices on the device.

use std::sync::Arc;

use ash::vk;
use glam::DVec3;

use super::instance::Placement;
use super::mesh::Mesh;
use super::vulkan_instance::instance_bits;
use super::vulkan_mesh::VulkanMesh;
use crate::error::{Error, Result};
use crate::geometry::build_options::{BuildOptions, BuildPreference};
use crate::geometry::precision::Aabb;
use crate::geometry::reference::TriangleSet;
use crate::gpu::accel::{self, instances_input, upload_instances, AccelerationStructure, BuildInput, InstanceBits};
use crate::gpu::context::Context;
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};
use crate::gpu::records::{ExactInstance, EXACT_CULL_DISABLE, EXACT_FLIP_FACING};

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
    /// f32 opacity per caller's triangle among all parts, for meshes with translucent triangles.
    opacity: Option<Buffer>,
}

impl ExactScene {
    /// The exact tier's structures over a scene's `placements` of its `meshes` (each once), every
    /// box padded by its slack; the TLAS built with the scene's `options`.
    pub(super) fn build(
        ctx: &Arc<Context>,
        placements: &[Placement],
        meshes: &[Arc<Mesh>],
        options: BuildOptions,
    ) -> Result<ExactScene> {
        if !ctx.info.shader_float64 {
            return Err(Error::Unsupported(format!(
                "{} has no shaderFloat64, which precision='exact' needs; precision='reference' gives the same answers on the CPU",
                ctx.info.name
            )));
        }
        let scene_bounds = placements.iter().fold(Aabb::EMPTY, |b, p| b.union(&p.bounds));
        let world_slack = EXACT_SLACK * scene_bounds.extent().max_element();
        let exact_meshes = meshes
            .iter()
            .map(|mesh| ExactMesh::build(ctx, placements, mesh, world_slack))
            .collect::<Result<Vec<_>>>()?;
        let mesh_of =
            |p: &Placement| &exact_meshes[meshes.iter().position(|m| Arc::ptr_eq(m, &p.mesh)).expect("scene mesh")];
        let mut uploads = Uploads::default();
        let n = placements.len();
        let records: Vec<_> = placements
            .iter()
            .map(|p| {
                // Boxes only: facing, culling and opacity are the exact shader's.
                let bits = InstanceBits { flags: 0, sbt_offset: 0, ..instance_bits(p) };
                accel::instance_record(&p.to_scene.to_rows_f32(), bits, mesh_of(p).blas.address())
            })
            .collect();
        let records = upload_instances(ctx, &mut uploads, &records, "exact instances")?;
        let mut data: Vec<ExactInstance> = placements.iter().map(|p| mesh_of(p).instance(p)).collect();
        if data.is_empty() {
            // An empty scene still hands the shaders one (zeroed) record's worth of buffer.
            data.push(ExactInstance::default());
        }
        let instances = uploads.records(ctx, &data, GEOMETRY_INPUT, "exact instance data")?;
        let input = instances_input(records.address(), n);
        let (tlas, _) = accel::build(ctx, &input, options, &uploads)?;
        let padded =
            if n == 0 { Aabb { min: DVec3::ZERO, max: DVec3::ZERO } } else { scene_bounds.padded(world_slack) };
        Ok(ExactScene { tlas, instances, bounds: padded.outward_f32(), _records: records, _meshes: exact_meshes })
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

impl ExactMesh {
    /// The exact tier's copy of `mesh`, as a scene's `placements` placed it: its boxes are padded by
    /// the scene's slack (`world_slack`, in the scene's frame) as seen in the mesh's frame, and by
    /// the mesh's own.
    fn build(ctx: &Arc<Context>, placements: &[Placement], mesh: &Arc<Mesh>, world_slack: f64) -> Result<ExactMesh> {
        let placements = || placements.iter().filter(|p| Arc::ptr_eq(&p.mesh, mesh));
        let triangles = &placements().next().expect("placed mesh").triangles;
        // How far the world's slack reaches in this mesh's frame: the most any placement of
        // it stretches a vector (the max-row-sum norm of its world-to-mesh map).
        let stretch = placements()
            .map(|p| {
                let m = p.to_local.linear.transpose();
                (0..3).map(|r| m.col(r).abs().element_sum()).fold(0.0, f64::max)
            })
            .fold(0.0, f64::max);
        let pad = world_slack * stretch + EXACT_SLACK * triangles.bounds.extent().max_element();
        let order = box_order(VulkanMesh::of(mesh)?, triangles);
        let mut uploads = Uploads::default();
        let boxes: Vec<[f32; 6]> =
            order.iter().map(|&t| Aabb::of_points(triangles.triangle(t as usize)).padded(pad).outward_f32()).collect();
        let boxes = uploads.records(ctx, &boxes, GEOMETRY_INPUT, "exact boxes")?;
        let vertices = uploads.records(ctx, &triangles.vertices, GEOMETRY_INPUT, "exact vertices")?;
        let faces: Vec<[u32; 3]> = order.iter().map(|&t| triangles.faces[t as usize]).collect();
        let faces = uploads.records(ctx, &faces, GEOMETRY_INPUT, "exact faces")?;
        let identity = order.iter().enumerate().all(|(d, &t)| d as u32 == t);
        let primitive_order =
            if identity { None } else { Some(uploads.records(ctx, &order, GEOMETRY_INPUT, "exact order")?) };
        let part_offsets = uploads.records(ctx, &triangles.part_offsets, GEOMETRY_INPUT, "exact part offsets")?;
        let opacity = match &mesh.opacity {
            Some(opacity) => Some(uploads.records(ctx, opacity, GEOMETRY_INPUT, "exact opacity")?),
            None => None,
        };
        let input = BuildInput {
            ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
            geometries: vec![accel::aabbs_geometry(boxes.address())],
            primitive_counts: vec![order.len() as u32],
            name: "exact boxes BLAS",
        };
        let options = BuildOptions { preference: BuildPreference::FastTrace, allow_update: false, compact: false };
        let (blas, _) = accel::build(ctx, &input, options, &uploads)?;
        Ok(ExactMesh { blas, _boxes: boxes, vertices, faces, primitive_order, part_offsets, opacity })
    }

    /// The record of an instance of this mesh placed at `p`.
    fn instance(&self, p: &Placement) -> ExactInstance {
        let (linear, offset) = (p.to_local.linear, p.to_local.offset);
        let row = |r: usize| {
            let row = linear.row(r);
            [row.x, row.y, row.z, offset[r]]
        };
        let mut flags = 0;
        if p.flags.cull_disable {
            flags |= EXACT_CULL_DISABLE;
        }
        if p.flip_facing {
            flags |= EXACT_FLIP_FACING;
        }
        ExactInstance {
            rows: [row(0), row(1), row(2)],
            vertices: self.vertices.address(),
            indices: self.faces.address(),
            primitive_order: self.primitive_order.as_ref().map_or(0, |b| b.address()),
            part_offsets: self.part_offsets.address(),
            part_count: p.triangles.part_offsets.len() as u32 - 1,
            flags,
            // Instances forced opaque block wherever they are hit.
            opacity: match (&self.opacity, p.flags.force_opaque) {
                (Some(opacity), false) => opacity.address(),
                _ => 0,
            },
            _padding: [0; 2],
        }
    }
}

/// The order of a mesh's boxes: each part's device order in turn, as caller's triangles among all.
fn box_order(mesh: &VulkanMesh, triangles: &TriangleSet) -> Vec<u32> {
    mesh.parts
        .iter()
        .enumerate()
        .flat_map(|(k, part)| {
            (0..part.triangle_count).map(move |d| triangles.global(k, part.caller_triangle(d)) as u32)
        })
        .collect()
}

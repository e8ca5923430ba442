//! The exact tier's view of a scene: conservative per-triangle boxes and f64 vertices on the device.

use std::sync::Arc;

use ash::vk;
use glam::DVec3;

use super::instance::Placement;
use super::top_level::{instances_input, Scene};
use crate::error::{Error, Result};
use crate::geometry::precision::{round_outward, Aabb};
use crate::gpu::accel::{self, AccelerationStructure, BuildInput, BuildOptions, BuildPreference, InstanceBits};
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};

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
    pub(super) fn build(scene: &Scene) -> Result<ExactScene> {
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
            let (blas, _) = accel::build(ctx, &input, options, &uploads)?;
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
        let (tlas, _) = accel::build(ctx, &input, scene.options, &uploads)?;
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

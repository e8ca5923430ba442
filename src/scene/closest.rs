//! Closest points' view of a scene on the device: the reference tier's own hierarchies (each
//! mesh's, and the one over the instances' bounds), flattened into f64 records that a compute
//! shader searches best first, as `ReferenceTracer::closest_point` does on the CPU; and winding
//! numbers' boundaries of those hierarchies' nodes.

use std::mem::{size_of, size_of_val};
use std::sync::Arc;

use super::inside_grid::InsideGrid;
use super::instance::Placement;
use super::winding_cap::{band_of, cap_geometry, CapGeometry};
use crate::error::{Error, Result};
use crate::geometry::bvh::{Bvh, Node};
use crate::geometry::precision::{Aabb, Affine};
use crate::geometry::reference::{gap_weights, TriangleSet};
use crate::gpu::context::Context;
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};
use crate::gpu::records::{
    BvhInstance, BvhNode, BvhTriangle, InsideGridHeader, WindingCapHeader, WindingEdge, WindingSpan,
};

/// The device's copy of every hierarchy closest points search.
pub struct ClosestScene {
    nodes: Buffer,
    triangles: Buffer,
    instances: Buffer,
    top_nodes: Buffer,
    top_items: Buffer,
    pub instance_count: u32,
}

impl ClosestScene {
    pub(super) fn build(ctx: &Arc<Context>, placements: &[Placement]) -> Result<ClosestScene> {
        if !ctx.info.shader_float64 {
            return Err(Error::Unsupported(format!(
                "{} has no shaderFloat64, which closest points on the GPU need; precision='reference' gives the same \
                 answers on the CPU",
                ctx.info.name
            )));
        }
        let sets = unique_sets(placements);
        let (mut nodes, mut triangles) = (Vec::new(), Vec::new());
        // Where each set's nodes and triangles start.
        let mut starts: Vec<(u32, u32)> = Vec::new();
        for set in &sets {
            starts.push((count_u32(nodes.len(), "nodes")?, count_u32(triangles.len(), "triangles")?));
            flatten(set, &mut nodes, &mut triangles);
        }
        let instances: Vec<BvhInstance> = placements
            .iter()
            .map(|p| {
                let set = sets.iter().position(|s| Arc::ptr_eq(s, &p.triangles)).expect("placed set");
                instance_record(p, starts[set])
            })
            .collect();
        let boxes: Vec<Aabb> = placements.iter().map(|p| p.bounds).collect();
        let top = Bvh::build(&boxes);
        let top_nodes: Vec<BvhNode> = top.nodes().iter().map(node_record).collect();
        let mut uploads = Uploads::default();
        // Shaders read one record at least: empty scenes get one zeroed.
        let built = ClosestScene {
            nodes: uploads.records(ctx, &at_least_one(nodes), GEOMETRY_INPUT, "closest-point nodes")?,
            triangles: uploads.records(ctx, &at_least_one(triangles), GEOMETRY_INPUT, "closest-point triangles")?,
            instances: uploads.records(ctx, &at_least_one(instances), GEOMETRY_INPUT, "closest-point instances")?,
            top_nodes: uploads.records(ctx, &at_least_one(top_nodes), GEOMETRY_INPUT, "closest-point top nodes")?,
            top_items: uploads.records(
                ctx,
                &at_least_one(top.items().to_vec()),
                GEOMETRY_INPUT,
                "closest-point top",
            )?,
            instance_count: placements.len() as u32,
        };
        ctx.run_commands(|cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        Ok(built)
    }

    /// Device addresses: nodes, triangles, instances, top nodes, top items.
    pub fn addresses(&self) -> [u64; 5] {
        [&self.nodes, &self.triangles, &self.instances, &self.top_nodes, &self.top_items].map(Buffer::address)
    }
}

/// Winding numbers' view of a scene on the device: every node's boundary (geometry::winding),
/// beside `ClosestScene`'s nodes and in their order, the edges' corners in f64.
pub struct WindingScene {
    spans: Buffer,
    edges: Buffer,
}

impl WindingScene {
    pub(super) fn build(ctx: &Arc<Context>, placements: &[Placement]) -> Result<WindingScene> {
        let (mut spans, mut edges) = (Vec::new(), Vec::new());
        for set in unique_sets(placements) {
            let tree = set.winding_tree();
            let first = count_u32(edges.len(), "boundary edges")?;
            count_u32(edges.len() + tree.edges().len(), "boundary edges")?;
            spans.extend(tree.spans().iter().map(|span| WindingSpan { first: first + span.first, count: span.count }));
            edges.extend(tree.edges().iter().map(|&[u, v]| WindingEdge {
                a: set.vertices[u as usize].to_array(),
                b: set.vertices[v as usize].to_array(),
            }));
        }
        let mut uploads = Uploads::default();
        let built = WindingScene {
            spans: uploads.records(ctx, &at_least_one(spans), GEOMETRY_INPUT, "winding spans")?,
            edges: uploads.records(ctx, &at_least_one(edges), GEOMETRY_INPUT, "winding edges")?,
        };
        ctx.run_commands(|cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        Ok(built)
    }

    /// Device addresses: spans, edges.
    pub fn addresses(&self) -> [u64; 2] {
        [&self.spans, &self.edges].map(Buffer::address)
    }
}

/// The caps that close the holes of a one-instance scene's mesh, for the exact tier's winding
/// query (trace::Query::Winding): per hole (a loop of the hierarchy's root's boundary,
/// geometry::winding::boundary_loops) the fan from the hole's mean corner over its edges, corners
/// in the mesh's frame and the scene's. The mesh less the caps has no boundary, so its winding
/// number about a point is the signed count of a ray's crossings, and the mesh's is that plus the
/// caps'. A hole's own fan, rather than one fan from the mesh's centre over every edge, lets a ray
/// pass it over: no ray passing beyond its bounding sphere crosses it, and seen from afar its
/// winding number is bounded by its area over the squared distance (records.glsl WindingCapHole).
pub struct WindingCap {
    buffer: Buffer,
    edge_count: usize,
}

impl WindingCap {
    /// The cap of the scene's one instance, or None: several instances (a ray's crossings would
    /// need telling apart), an instance no ray meets (mask 0), or a boundary of more than
    /// `MAX_CAP_EDGES` edges (the root keeps none, or too many to sum per ray).
    pub(super) fn build(ctx: &Arc<Context>, placements: &[Placement]) -> Result<Option<WindingCap>> {
        let Some(CapGeometry { holes, edges, mirrored }) = cap_geometry(placements) else { return Ok(None) };
        let edge_count = edges.len();
        let band = band_of(edge_count);
        let mirrored = u32::from(mirrored);
        let holes_at = size_of::<WindingCapHeader>();
        let edges_at = holes_at + size_of_val(holes.as_slice());
        let size = edges_at + size_of_val(edges.as_slice());
        let mut uploads = Uploads::default();
        let buffer = uploads.buffer(ctx, size as u64, GEOMETRY_INPUT, "winding cap", |out, address| {
            let header = WindingCapHeader {
                hole_count: holes.len() as u32,
                mirrored,
                band,
                holes: address + holes_at as u64,
                edges: address + edges_at as u64,
            };
            out[..holes_at].copy_from_slice(bytemuck::bytes_of(&header));
            out[holes_at..edges_at].copy_from_slice(bytemuck::cast_slice(&holes));
            out[edges_at..].copy_from_slice(bytemuck::cast_slice(&edges));
        })?;
        ctx.run_commands(|cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        Ok(Some(WindingCap { buffer, edge_count }))
    }

    /// The device address of the header.
    pub fn address(&self) -> u64 {
        self.buffer.address()
    }

    /// Whether the mesh has holes for the cap to close (a closed mesh's cap has none).
    pub fn has_holes(&self) -> bool {
        self.edge_count > 0
    }

    /// Winding numbers within this of 1/2 (the mesh's crossings plus the caps') are decided on the
    /// CPU: the bound on the GPU's terms' error, and a margin.
    pub fn band(&self) -> f64 {
        band_of(self.edge_count)
    }
}

/// The scene's inside grid on the device (`InsideGridHeader`, then its marks), for the rays that
/// sign distances: a point whose cell the grid decides casts none (exact.glsl grid_crossings).
pub struct InsideGridBuffer {
    buffer: Buffer,
    /// The grid it holds (kept until the scene's next update, as the grid is).
    pub grid: Arc<InsideGrid>,
}

impl InsideGridBuffer {
    pub(super) fn build(ctx: &Arc<Context>, grid: &Arc<InsideGrid>) -> Result<InsideGridBuffer> {
        let (min, inverse_cell, dims, marks) = grid.marks_layout();
        let marks_at = size_of::<InsideGridHeader>();
        // Whole words: the shaders read the marks as uints.
        let size = marks_at + marks.len().next_multiple_of(4);
        let mut uploads = Uploads::default();
        let buffer = uploads.buffer(ctx, size as u64, GEOMETRY_INPUT, "inside grid", |out, address| {
            let header = InsideGridHeader {
                min: min.to_array(),
                inverse_cell,
                dims: dims.map(|n| n as u32),
                unused: 0,
                marks: address + marks_at as u64,
            };
            out[..marks_at].copy_from_slice(bytemuck::bytes_of(&header));
            out[marks_at..marks_at + marks.len()].copy_from_slice(marks);
            out[marks_at + marks.len()..].fill(0);
        })?;
        ctx.run_commands(|cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        Ok(InsideGridBuffer { buffer, grid: grid.clone() })
    }

    /// The device address of the header.
    pub fn address(&self) -> u64 {
        self.buffer.address()
    }
}

/// The scene's triangle sets, each once, in the order of their first placement: the order of
/// both views' records.
fn unique_sets(placements: &[Placement]) -> Vec<&Arc<TriangleSet>> {
    let mut sets: Vec<&Arc<TriangleSet>> = Vec::new();
    for placement in placements {
        if !sets.iter().any(|s| Arc::ptr_eq(s, &placement.triangles)) {
            sets.push(&placement.triangles);
        }
    }
    sets
}

/// Appends a set's hierarchy (child and leaf indices from its first node) and its triangles in
/// its leaves' order.
fn flatten(set: &TriangleSet, nodes: &mut Vec<BvhNode>, triangles: &mut Vec<BvhTriangle>) {
    let bvh = set.bvh();
    nodes.extend(bvh.nodes().iter().map(node_record));
    triangles.extend(bvh.items().iter().map(|&prim| {
        let [a, b, c] = set.triangle(prim as usize).map(|v| v.to_array());
        BvhTriangle { a, b, c, prim, unused: 0 }
    }));
}

fn node_record(node: &Node) -> BvhNode {
    BvhNode { lo: node.bounds.min.to_array(), hi: node.bounds.max.to_array(), first: node.first, count: node.count }
}

/// An instance's record: its maps, its bound factor (ReferenceTracer::closest_point's), and
/// where its set's nodes and triangles start.
fn instance_record(p: &Placement, (nodes, triangles): (u32, u32)) -> BvhInstance {
    BvhInstance {
        to_local: rows(&p.to_local),
        to_scene: rows(&p.to_scene),
        weights: gap_weights(&p.to_scene, &p.to_local),
        nodes,
        triangles,
        mask: p.mask as u32,
        identity: (p.to_scene.linear == glam::DMat3::IDENTITY) as u32,
        triangle_count: p.triangles.faces.len() as u32,
        mirrored: (p.to_scene.linear.determinant() < 0.0) as u32,
    }
}

/// Row-major 3×4 (xyz linear, then the offset) in f64.
fn rows(map: &Affine) -> [f64; 12] {
    let mut out = [0.0; 12];
    for r in 0..3 {
        let row = map.linear.row(r);
        out[4 * r..4 * r + 4].copy_from_slice(&[row.x, row.y, row.z, map.offset[r]]);
    }
    out
}

fn at_least_one<T: bytemuck::Pod + Default>(mut records: Vec<T>) -> Vec<T> {
    if records.is_empty() {
        records.push(T::default());
    }
    records
}

fn count_u32(n: usize, what: &str) -> Result<u32> {
    u32::try_from(n).map_err(|_| Error::Unsupported(format!("closest points on the GPU hold at most 2^32 {what}")))
}

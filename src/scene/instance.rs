//! Instances: placements of meshes in a scene's frame, in f64.

use std::sync::Arc;

use glam::DVec3;

use super::mesh::Mesh;
use crate::error::{invalid_value, Result};
use crate::geometry::precision::{Aabb, Affine};
use crate::geometry::reference::TriangleSet;

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

/// The scene's centre (the middle of its instances' bounds, unless `center` keeps an earlier one)
/// and each instance's placement relative to it, all in f64.
pub(crate) fn place(instances: &[Instance], center: Option<DVec3>) -> Result<(DVec3, Vec<Placement>)> {
    let (triangles, centers): (Vec<Arc<TriangleSet>>, Vec<DVec3>) = instances.iter().map(|x| x.mesh.placed()).unzip();
    // Object to world for the mesh's device frame: M (s v + c) + T = (s M) v + (M c + T).
    let to_world: Vec<Affine> = instances
        .iter()
        .zip(&centers)
        .map(|(x, c)| {
            let user = Affine::from_rows(&x.transform);
            Affine { linear: user.linear * x.mesh.scale, offset: user.point(*c) }
        })
        .collect();
    let bounds = triangles.iter().zip(&to_world).fold(Aabb::EMPTY, |b, (t, m)| b.union(&t.bounds.transformed(m)));
    let center = center.unwrap_or(if instances.is_empty() { DVec3::ZERO } else { bounds.center() });
    let mut placements = Vec::with_capacity(instances.len());
    for (i, ((x, m), triangles)) in instances.iter().zip(&to_world).zip(triangles).enumerate() {
        let to_scene = Affine { offset: m.offset - center, ..*m };
        let bounds = triangles.bounds.transformed(&to_scene);
        // The TLAS holds the transform, and traversal the instance's extent, in f32.
        let in_f32 = |v: f64| (v as f32).is_finite();
        if !(to_scene.to_rows_f32().iter().all(|v| v.is_finite())
            && bounds.min.to_array().into_iter().chain(bounds.max.to_array()).all(in_f32))
        {
            return Err(invalid_value(format!(
                "instance {i} lies too far from the scene's other instances for float32 (the scene spans more than 3.4e38)"
            )));
        }
        let to_local = to_scene.inverse().ok_or_else(|| {
            invalid_value(format!("instance {i} has a singular transform (its 3x3 part has no inverse)"))
        })?;
        placements.push(Placement {
            mesh: x.mesh.clone(),
            bounds,
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

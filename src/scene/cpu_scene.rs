//! The CPU engine's hierarchy over a scene: an Embree scene of one instance per placement (its
//! mesh's Embree scene, placed by the f32 transform the GPU's TLAS holds, under its mask).

use std::any::Any;
use std::sync::Arc;

use glam::{DMat3, DVec3};

use super::cpu_mesh::{build_quality, built_stats, scene_flags, unit_of, CpuMesh};
use super::instance::{Instance, Placement};
use super::mesh::Mesh;
use super::top_level::{Scene, SceneHierarchy};
use crate::embree::api::GEOMETRY_TYPE_INSTANCE;
use crate::embree::objects::{EmbreeDevice, EmbreeGeometry, EmbreeScene};
use crate::error::Result;
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::geometry::precision::Affine;

/// A scene's Embree scene of instances.
///
/// Embree inverts each instance's f32 transform (its determinant overflows past a scale of
/// 1e12) and multiplies distances by areas in its triangle test: so it holds the scene's frame
/// divided by `unit`, the power of two at or above the largest coordinate of the instances'
/// bounds, and rays are divided by it too (origin and direction: `t` keeps its meaning).
pub struct CpuScene {
    device: Arc<EmbreeDevice>,
    scene: EmbreeScene,
    unit: f64,
    /// The one instance's mesh, where it is placed as Embree holds it (identity in units, every
    /// mask bit): traced without the instance level (Embree then reports no instance id: 0).
    direct: Option<Arc<Mesh>>,
    /// Instance geometry k places instance k (Embree reports it as the hit's instance id).
    _instances: Vec<EmbreeGeometry>,
    stats: BuildStats,
}

/// Builds a scene of `instances` on the CPU engine's device.
pub fn build_cpu_scene(device: &Arc<EmbreeDevice>, instances: &[Instance], options: BuildOptions) -> Result<Scene> {
    Scene::build(instances, options, |placements| {
        let hierarchy: Box<dyn SceneHierarchy> = Box::new(CpuScene::build(device, placements, options)?);
        Ok(hierarchy)
    })
}

impl CpuScene {
    /// The CPU engine's hierarchy of `scene`.
    pub fn of(scene: &Scene) -> Result<&CpuScene> {
        scene.hierarchy::<CpuScene>()
    }

    pub fn scene(&self) -> &EmbreeScene {
        match &self.direct {
            Some(mesh) => CpuMesh::of(mesh).expect("a CPU scene holds CPU meshes").scene(),
            None => &self.scene,
        }
    }

    /// What the scene's frame is divided by in Embree (rays are divided by it too).
    pub fn unit(&self) -> f64 {
        self.unit
    }

    fn build(device: &Arc<EmbreeDevice>, placements: &[Placement], options: BuildOptions) -> Result<CpuScene> {
        let meshes = placements.iter().map(|p| CpuMesh::of(&p.mesh)).collect::<Result<Vec<_>>>()?;
        let unit = unit_of(placements.iter().map(|p| p.bounds.min.abs().max(p.bounds.max.abs()).max_element()));
        let ((scene, instances), bytes, seconds) = device.measured(|| {
            let scene = device.scene(scene_flags(options), build_quality(options))?;
            let mut instances = Vec::with_capacity(placements.len());
            for (k, (p, mesh)) in placements.iter().zip(&meshes).enumerate() {
                let instance = device.geometry(GEOMETRY_TYPE_INSTANCE)?;
                let linear = p.to_scene.linear * (mesh.unit() / unit);
                let placed = Affine { linear, offset: p.to_scene.offset / unit };
                instance.instance(mesh.scene(), &placed.to_rows_f32());
                scene.attach(&instance, k as u32, u32::from(p.mask))?;
                instances.push(instance);
            }
            scene.commit()?;
            Ok((scene, instances))
        })?;
        let stats = built_stats(bytes, seconds);
        let direct = match (placements, meshes.as_slice()) {
            ([p], [mesh]) if p.mask == 0xFF && placed_as_held(p, mesh.unit(), unit) => Some(p.mesh.clone()),
            _ => None,
        };
        Ok(CpuScene { device: device.clone(), scene, unit, direct, _instances: instances, stats })
    }
}

/// Whether `p`'s transform in Embree's units is the identity: its mesh's scene is the scene.
fn placed_as_held(p: &Placement, mesh_unit: f64, unit: f64) -> bool {
    p.to_scene.offset == DVec3::ZERO && p.to_scene.linear * (mesh_unit / unit) == DMat3::IDENTITY
}

impl SceneHierarchy for CpuScene {
    fn stats(&self) -> BuildStats {
        self.stats
    }

    /// Builds the instances' hierarchy again (Embree's top level over a few boxes takes
    /// microseconds to milliseconds; its meshes' hierarchies are kept).
    fn update(&mut self, placements: &[Placement], options: BuildOptions) -> Result<()> {
        *self = CpuScene::build(&self.device.clone(), placements, options)?;
        Ok(())
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

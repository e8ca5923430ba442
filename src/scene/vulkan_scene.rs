//! The Vulkan engine's hierarchy over a scene: the top-level acceleration structure over its
//! meshes' BLAS, the records shaders read per instance, and the structures the exact tier,
//! closest points and winding numbers build on their first query.

use std::any::Any;
use std::sync::{Arc, Mutex, OnceLock};

use ash::vk;

use super::closest::{ClosestScene, InsideGridBuffer, WindingCap, WindingScene};
use super::exact::ExactScene;
use super::inside_grid::InsideGrid;
use super::instance::{Instance, Placement};
use super::top_level::{Scene, SceneHierarchy};
use super::vulkan_instance::{instance_bits, MAX_CUSTOM_INDEX};
use super::vulkan_mesh::VulkanMesh;
use crate::error::{invalid_value, Error, Result};
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::gpu::accel::{self, instances_input, upload_instances, AccelerationStructure};
use crate::gpu::context::Context;
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};

/// A scene's TLAS and what the Vulkan paths build over its placements.
pub struct VulkanScene {
    tlas: AccelerationStructure,
    stats: BuildStats,
    // Where each instance's triangles live, for shaders (normals).
    instance_geometries: Buffer,
    instance_records: Buffer,
    /// The exact tier's structures, built on its first query.
    exact: OnceLock<Arc<ExactScene>>,
    /// Closest points' hierarchies on the device, built on their first query.
    closest: OnceLock<Arc<ClosestScene>>,
    /// Winding numbers' boundaries on the device, built on their first query.
    winding: OnceLock<Arc<WindingScene>>,
    winding_cap: OnceLock<Option<Arc<WindingCap>>>,
    /// The scene's inside grids on the device (by parity, by winding number), each the copy of
    /// the grid the scene keeps (`Scene::inside_grid`), made on a signed distance's first use.
    inside_grids: Mutex<[Option<Arc<InsideGridBuffer>>; 2]>,
}

/// Builds a scene of `instances` on the Vulkan device `ctx`.
pub fn build_vulkan_scene(ctx: &Arc<Context>, instances: &[Instance], options: BuildOptions) -> Result<Scene> {
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
    Scene::build(instances, options, |placements| {
        let hierarchy: Box<dyn SceneHierarchy> = Box::new(VulkanScene::build(ctx, placements, options)?);
        Ok(hierarchy)
    })
}

impl VulkanScene {
    fn build(ctx: &Arc<Context>, placements: &[Placement], options: BuildOptions) -> Result<VulkanScene> {
        let mut uploads = Uploads::default();
        let records = upload_instances(ctx, &mut uploads, &instance_records(placements)?, "instances")?;
        let sources = placements
            .iter()
            .map(|p| Ok(VulkanMesh::of(&p.mesh)?.sources_address(p.flags.force_opaque)))
            .collect::<Result<Vec<u64>>>()?;
        let instance_geometries = uploads.records(ctx, &sources, GEOMETRY_INPUT, "instance geometries")?;
        let input = instances_input(records.address(), placements.len());
        let (tlas, stats) = accel::build(ctx, &input, options, &uploads)?;
        Ok(VulkanScene {
            tlas,
            stats,
            instance_geometries,
            instance_records: records,
            exact: OnceLock::new(),
            closest: OnceLock::new(),
            winding: OnceLock::new(),
            winding_cap: OnceLock::new(),
            inside_grids: Default::default(),
        })
    }

    /// The Vulkan engine's hierarchy of `scene`.
    pub fn of(scene: &Scene) -> Result<&VulkanScene> {
        scene.hierarchy::<VulkanScene>()
    }

    pub fn tlas_address(&self) -> u64 {
        self.tlas.address()
    }

    pub fn instance_geometries_address(&self) -> u64 {
        self.instance_geometries.address()
    }

    /// The exact tier's structures over `scene` (this hierarchy's), built on first use (outside
    /// any lock: two threads may both build them, and the first one stored is kept).
    pub fn exact(&self, scene: &Scene) -> Result<Arc<ExactScene>> {
        if let Some(exact) = self.exact.get() {
            return Ok(exact.clone());
        }
        let built = Arc::new(ExactScene::build(self.tlas.context(), &scene.placements, scene.meshes(), scene.options)?);
        Ok(self.exact.get_or_init(|| built).clone())
    }

    /// Closest points' hierarchies on the device, built on first use (outside any lock, as
    /// `exact`).
    pub fn closest(&self, scene: &Scene) -> Result<Arc<ClosestScene>> {
        if let Some(closest) = self.closest.get() {
            return Ok(closest.clone());
        }
        let built = Arc::new(ClosestScene::build(self.tlas.context(), &scene.placements)?);
        Ok(self.closest.get_or_init(|| built).clone())
    }

    /// Winding numbers' boundaries on the device, built on first use (outside any lock, as
    /// `exact`).
    pub fn winding(&self, scene: &Scene) -> Result<Arc<WindingScene>> {
        if let Some(winding) = self.winding.get() {
            return Ok(winding.clone());
        }
        let built = Arc::new(WindingScene::build(self.tlas.context(), &scene.placements)?);
        Ok(self.winding.get_or_init(|| built).clone())
    }

    /// The device's copy of `grid` (the scene's inside grid by winding number or by parity),
    /// made on first use (outside the lock) and kept while the scene keeps that grid.
    pub fn inside_grid_buffer(&self, grid: &Arc<InsideGrid>, winding: bool) -> Result<Arc<InsideGridBuffer>> {
        let kept = |grids: &[Option<Arc<InsideGridBuffer>>; 2]| {
            grids[winding as usize].as_ref().filter(|b| Arc::ptr_eq(&b.grid, grid)).cloned()
        };
        if let Some(buffer) = kept(&self.inside_grids.lock().unwrap_or_else(|e| e.into_inner())) {
            return Ok(buffer);
        }
        let built = Arc::new(InsideGridBuffer::build(self.tlas.context(), grid)?);
        let mut grids = self.inside_grids.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(buffer) = kept(&grids) {
            return Ok(buffer);
        }
        grids[winding as usize] = Some(built.clone());
        Ok(built)
    }

    /// The cap that closes the holes of the scene's one mesh, for the exact tier's winding query,
    /// built on first use (outside any lock, as `exact`); None where the scene has none
    /// (`WindingCap::build`).
    pub fn winding_cap(&self, scene: &Scene) -> Result<Option<Arc<WindingCap>>> {
        if let Some(cap) = self.winding_cap.get() {
            return Ok(cap.clone());
        }
        let built = WindingCap::build(self.tlas.context(), &scene.placements)?.map(Arc::new);
        Ok(self.winding_cap.get_or_init(|| built).clone())
    }
}

impl SceneHierarchy for VulkanScene {
    fn stats(&self) -> BuildStats {
        self.stats
    }

    fn update(&mut self, placements: &[Placement], options: BuildOptions) -> Result<()> {
        let ctx = self.tlas.context().clone();
        let n = placements.len();
        let mut uploads = Uploads::default();
        let records = instance_records(placements)?;
        if options.allow_update {
            let bytes = accel::instance_bytes(&records);
            uploads.overwrite(&ctx, &self.instance_records, |out| out[..bytes.len()].copy_from_slice(bytes))?;
            let input = instances_input(self.instance_records.address(), n);
            accel::update(&ctx, &self.tlas, &input, options, self.stats.update_scratch_size, &uploads)?;
        } else {
            let records = upload_instances(&ctx, &mut uploads, &records, "instances")?;
            let (tlas, stats) = accel::build(&ctx, &instances_input(records.address(), n), options, &uploads)?;
            (self.tlas, self.stats, self.instance_records) = (tlas, stats, records);
        }
        self.exact = OnceLock::new();
        self.closest = OnceLock::new();
        self.winding = OnceLock::new();
        self.winding_cap = OnceLock::new();
        self.inside_grids = Default::default();
        Ok(())
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// The TLAS instance record of each placement.
fn instance_records(placements: &[Placement]) -> Result<Vec<vk::AccelerationStructureInstanceKHR>> {
    placements
        .iter()
        .map(|p| {
            let blas = VulkanMesh::of(&p.mesh)?.blas_address();
            Ok(accel::instance_record(&p.to_scene.to_rows_f32(), instance_bits(p), blas))
        })
        .collect()
}

//! Scenes: instances of meshes under one top-level acceleration structure.

use std::sync::{Arc, OnceLock, RwLockReadGuard};
use std::time::Instant;

use ash::vk;
use glam::DVec3;

use super::closest::{ClosestScene, WindingCap, WindingScene};
use super::exact::ExactScene;
use super::instance::{place, Instance, Placement, MAX_CUSTOM_INDEX};
use super::mesh::{Mesh, MeshKind};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::precision::Aabb;
use crate::geometry::rays::Frame;
use crate::geometry::reference::{PlacedSet, ReferenceTracer};
use crate::gpu::accel::{self, instances_input, upload_instances, AccelerationStructure, BuildOptions, BuildStats};
use crate::gpu::context::Context;
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};

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
    pub(super) tlas: AccelerationStructure,
    // Where each instance's triangles live, for shaders (normals).
    instance_geometries: Buffer,
    instance_records: Buffer,
    instances: Vec<Instance>,
    // The meshes' BLAS and buffers must outlive the TLAS that points at them.
    pub(super) meshes: Vec<Arc<Mesh>>,
    /// Each mesh's `generation` when this scene last placed it.
    mesh_generations: Vec<u64>,
    last_update_seconds: f64,
    /// The exact tier's structures, built on its first query.
    exact: OnceLock<Arc<ExactScene>>,
    /// Closest points' hierarchies on the device, built on their first query.
    closest: OnceLock<Arc<ClosestScene>>,
    /// Winding numbers' boundaries on the device, built on their first query.
    winding: OnceLock<Arc<WindingScene>>,
    winding_cap: OnceLock<Option<Arc<WindingCap>>>,
    /// The instances' bounds in the scene's frame.
    bounds: Aabb,
}

impl Scene {
    pub fn build(ctx: &Arc<Context>, instances: &[Instance], options: BuildOptions) -> Result<Scene> {
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
        let records = upload_instances(ctx, &mut uploads, &instance_records(&placements), "instances")?;
        let sources: Vec<u64> = instances.iter().map(|x| x.mesh.sources_address(x.flags.force_opaque)).collect();
        let instance_geometries = uploads.records(ctx, &sources, GEOMETRY_INPUT, "instance geometries")?;
        let input = instances_input(records.address(), instances.len());
        let (tlas, stats) = accel::build(ctx, &input, options, &uploads)?;
        let mut meshes: Vec<Arc<Mesh>> = Vec::new();
        for instance in instances {
            if !meshes.iter().any(|m| Arc::ptr_eq(m, &instance.mesh)) {
                meshes.push(instance.mesh.clone());
            }
        }
        Ok(Scene {
            bounds: bounds_of(&placements),
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
            exact: OnceLock::new(),
            closest: OnceLock::new(),
            winding: OnceLock::new(),
            winding_cap: OnceLock::new(),
        })
    }

    /// Moves its instances (`transforms`, row-major 3×4 in f64) or changes their masks, and picks
    /// up its meshes' `update`s: refits the TLAS in place where it was built with `allow_update`,
    /// else builds it again (milliseconds). The scene is re-centred on its instances' new bounds,
    /// so moves far away keep f32 precision.
    pub fn update(&mut self, transforms: Option<Vec<[f64; 12]>>, masks: Option<Vec<u8>>) -> Result<()> {
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
        let (center, placements) = place(&instances, None)?;
        let ctx = self.tlas.context().clone();
        let mut uploads = Uploads::default();
        let records = instance_records(&placements);
        if self.options.allow_update {
            let bytes = accel::instance_bytes(&records);
            uploads.overwrite(&ctx, &self.instance_records, |out| out[..bytes.len()].copy_from_slice(bytes))?;
            let input = instances_input(self.instance_records.address(), n);
            accel::update(&ctx, &self.tlas, &input, self.options, self.stats.update_scratch_size, &uploads)?;
        } else {
            let records = upload_instances(&ctx, &mut uploads, &records, "instances")?;
            let (tlas, stats) = accel::build(&ctx, &instances_input(records.address(), n), self.options, &uploads)?;
            (self.tlas, self.stats, self.instance_records) = (tlas, stats, records);
        }
        self.instances = instances;
        self.center = center;
        self.bounds = bounds_of(&placements);
        self.placements = placements;
        self.mesh_generations = self.meshes.iter().map(|m| m.generation()).collect();
        self.exact = OnceLock::new();
        self.closest = OnceLock::new();
        self.winding = OnceLock::new();
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

    /// Whether every instance's triangles are opaque: none forced non-opaque, and every mesh
    /// with translucent triangles forced opaque.
    pub fn all_opaque(&self) -> bool {
        self.placements.iter().all(|p| !p.flags.force_no_opaque && (p.flags.force_opaque || !p.mesh.is_translucent()))
    }

    /// Whether some instance's triangles have an opacity below 1 that traversal reads.
    pub fn has_opacity(&self) -> bool {
        self.placements.iter().any(|p| !p.flags.force_opaque && p.mesh.is_translucent())
    }

    pub fn instance_geometries_address(&self) -> u64 {
        self.instance_geometries.address()
    }

    /// The exact tier's structures over this scene, built on first use (outside any lock: two
    /// threads may both build them, and the first one stored is kept).
    pub fn exact(&self) -> Result<Arc<ExactScene>> {
        if let Some(exact) = self.exact.get() {
            return Ok(exact.clone());
        }
        let built = Arc::new(ExactScene::build(self.tlas.context(), &self.placements, &self.meshes, self.options)?);
        Ok(self.exact.get_or_init(|| built).clone())
    }

    /// The instances' bounds in the scene's frame (empty without instances).
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Closest points' hierarchies on the device, built on first use (outside any lock, as
    /// `exact`).
    pub fn closest(&self) -> Result<Arc<ClosestScene>> {
        if let Some(closest) = self.closest.get() {
            return Ok(closest.clone());
        }
        let built = Arc::new(ClosestScene::build(self.tlas.context(), &self.placements)?);
        Ok(self.closest.get_or_init(|| built).clone())
    }

    /// Winding numbers' boundaries on the device, built on first use (outside any lock, as
    /// `exact`).
    pub fn winding(&self) -> Result<Arc<WindingScene>> {
        if let Some(winding) = self.winding.get() {
            return Ok(winding.clone());
        }
        let built = Arc::new(WindingScene::build(self.tlas.context(), &self.placements)?);
        Ok(self.winding.get_or_init(|| built).clone())
    }

    /// The cap that closes the holes of the scene's one mesh, for the exact tier's winding query,
    /// built on first use (outside any lock, as `exact`); None where the scene has none
    /// (`WindingCap::build`).
    pub fn winding_cap(&self) -> Result<Option<Arc<WindingCap>>> {
        if let Some(cap) = self.winding_cap.get() {
            return Ok(cap.clone());
        }
        let built = WindingCap::build(self.tlas.context(), &self.placements)?.map(Arc::new);
        Ok(self.winding_cap.get_or_init(|| built).clone())
    }

    /// Where rays are packed: the scene's frame and the sphere bounding its instances.
    pub fn frame(&self) -> Frame {
        let radius = if self.placements.is_empty() { 0.0 } else { 0.5 * self.bounds.extent().length() };
        Frame::new(self.center, self.bounds.center(), radius)
    }

    /// Holds this scene's meshes against `Mesh::update` until the guards drop (a query's time).
    /// Taken in one global order (by address), so that queries on scenes sharing meshes never
    /// wait for each other around a waiting update.
    pub fn hold_meshes(&self) -> Vec<RwLockReadGuard<'_, ()>> {
        let mut meshes: Vec<&Arc<Mesh>> = self.meshes.iter().collect();
        meshes.sort_by_key(|m| Arc::as_ptr(m));
        meshes.into_iter().map(|m| m.hold()).collect()
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
                    opacity: if p.flags.force_opaque { None } else { p.mesh.opacity.as_deref().map(Vec::as_slice) },
                    to_scene: p.to_scene,
                })
                .collect(),
        )
    }
}

/// The union of the placements' bounds.
fn bounds_of(placements: &[Placement]) -> Aabb {
    placements.iter().fold(Aabb::EMPTY, |b, p| b.union(&p.bounds))
}

/// The TLAS instance record of each placement.
fn instance_records(placements: &[Placement]) -> Vec<vk::AccelerationStructureInstanceKHR> {
    placements
        .iter()
        .map(|p| accel::instance_record(&p.to_scene.to_rows_f32(), p.bits(), p.mesh.blas_address()))
        .collect()
}

//! Scenes as every engine sees them: instances of meshes placed in the scene's frame (in f64),
//! their bounds and update bookkeeping, and the engine's own hierarchy over them behind
//! `SceneHierarchy` (the Vulkan engine's TLAS, a CPU engine's top-level BVH).

use std::any::Any;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, RwLockReadGuard};
use std::time::Instant;

use glam::DVec3;

use super::inside_grid::InsideGrid;
use super::instance::{place, Instance, Placement};
use super::mesh::{Mesh, MeshKind};
use crate::error::{invalid_value, Result};
use crate::geometry::build_options::{BuildOptions, BuildStats};
use crate::geometry::precision::Aabb;
use crate::geometry::rays::Frame;
use crate::geometry::reference::{PlacedSet, ReferenceTracer};

/// An engine's hierarchy over a scene's placements. The engine that built it reads it back with
/// `Scene::hierarchy` (one downcast where a query starts).
pub trait SceneHierarchy: Send + Sync {
    /// Bytes and time of its build.
    fn stats(&self) -> BuildStats;
    /// Follows new placements of the same instances (and their meshes' refits): refits where
    /// built with `allow_update`, else builds again; drops what it derived from the old ones.
    fn update(&mut self, placements: &[Placement], options: BuildOptions) -> Result<()>;
    fn as_any(&self) -> &dyn Any;
}

/// Instances of meshes under an engine's hierarchy.
///
/// The scene lives in its own frame: world coordinates minus `center` (the middle of the
/// instances' bounds), so that instance translations and ray origins far from the origin are
/// subtracted in f64 and reach f32 as small numbers.
pub struct Scene {
    pub instance_count: usize,
    pub center: DVec3,
    pub placements: Vec<Placement>,
    pub options: BuildOptions,
    instances: Vec<Instance>,
    // The meshes (and their hierarchies) must outlive the scene's hierarchy that points at them.
    meshes: Vec<Arc<Mesh>>,
    /// Each mesh's `generation` when this scene last placed it.
    mesh_generations: Vec<u64>,
    last_update_seconds: f64,
    /// The instances' bounds in the scene's frame.
    bounds: Aabb,
    hierarchy: Box<dyn SceneHierarchy>,
    /// The grids `contains` answers most points from (by parity, by winding number), kept from
    /// the first query that built them until the scene's next update.
    inside_grids: Mutex<[Option<Arc<InsideGrid>>; 2]>,
    /// Large `contains` queries (by parity, by winding number) that found no grid kept, since
    /// the scene's last update (`count_gridless_query`).
    gridless_queries: [AtomicU32; 2],
    /// A grid's build under way (`start_grid_build`), by parity and by winding number.
    grid_builds: [AtomicBool; 2],
}

/// A build of a scene's inside grid under way (`Scene::start_grid_build`), until dropped.
pub struct GridBuild<'a> {
    under_way: &'a AtomicBool,
}

impl Drop for GridBuild<'_> {
    fn drop(&mut self) {
        self.under_way.store(false, Ordering::Release);
    }
}

impl Scene {
    /// Places `instances` and has `build` (an engine's) make its hierarchy over the placements.
    pub fn build(
        instances: &[Instance],
        options: BuildOptions,
        build: impl FnOnce(&[Placement]) -> Result<Box<dyn SceneHierarchy>>,
    ) -> Result<Scene> {
        let (center, placements) = place(instances, None)?;
        let hierarchy = build(&placements)?;
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
            instances: instances.to_vec(),
            mesh_generations: meshes.iter().map(|m| m.generation()).collect(),
            meshes,
            last_update_seconds: 0.0,
            hierarchy,
            inside_grids: Mutex::new([None, None]),
            gridless_queries: Default::default(),
            grid_builds: Default::default(),
        })
    }

    /// The engine's hierarchy, where it is an `H` (the engine that built the scene reads its own).
    pub fn hierarchy<H: 'static>(&self) -> Result<&H> {
        self.hierarchy.as_any().downcast_ref::<H>().ok_or_else(|| {
            invalid_value("this scene was built by another engine: trace it on the device that built it")
        })
    }

    /// Bytes and time of the hierarchy's build (or last update).
    pub fn stats(&self) -> BuildStats {
        self.hierarchy.stats()
    }

    /// The scene's meshes, each once.
    pub fn meshes(&self) -> &[Arc<Mesh>] {
        &self.meshes
    }

    /// Moves its instances (`transforms`, row-major 3×4 in f64) or changes their masks, and picks
    /// up its meshes' `update`s: the hierarchy refits in place where it was built with
    /// `allow_update`, else it is built again. The scene is re-centred on its instances' new
    /// bounds, so moves far away keep f32 precision.
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
        self.hierarchy.update(&placements, self.options)?;
        self.instances = instances;
        self.center = center;
        self.bounds = bounds_of(&placements);
        self.placements = placements;
        *self.inside_grids.get_mut().unwrap_or_else(|e| e.into_inner()) = [None, None];
        self.gridless_queries = Default::default();
        self.mesh_generations = self.meshes.iter().map(|m| m.generation()).collect();
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

    /// The grid kept for `contains` by winding number (or parity), if a query built one.
    pub fn inside_grid(&self, winding: bool) -> Option<Arc<InsideGrid>> {
        self.inside_grids.lock().unwrap_or_else(|e| e.into_inner())[usize::from(winding)].clone()
    }

    /// Counts a large `contains` query by winding number (or parity) that found no grid kept;
    /// returns how many did since the scene was built or last updated, this one included.
    pub fn count_gridless_query(&self, winding: bool) -> u32 {
        self.gridless_queries[usize::from(winding)].fetch_add(1, Ordering::Relaxed).saturating_add(1)
    }

    /// Marks a build of the grid by winding number (or parity) under way, unless another is:
    /// then None (the caller may go on without the grid, or build beside it).
    pub fn start_grid_build(&self, winding: bool) -> Option<GridBuild<'_>> {
        let under_way = &self.grid_builds[usize::from(winding)];
        under_way.compare_exchange(false, true, Ordering::Acquire, Ordering::Relaxed).ok()?;
        Some(GridBuild { under_way })
    }

    /// Keeps `grid` (built outside the lock) for `contains` by winding number (or parity), unless
    /// another query kept one first; returns the one kept.
    pub fn keep_inside_grid(&self, winding: bool, grid: InsideGrid) -> Arc<InsideGrid> {
        let mut grids = self.inside_grids.lock().unwrap_or_else(|e| e.into_inner());
        grids[usize::from(winding)].get_or_insert_with(|| Arc::new(grid)).clone()
    }

    /// Whether any instance is a sphere set.
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

    /// The instances' bounds in the scene's frame (empty without instances).
    pub fn bounds(&self) -> Aabb {
        self.bounds
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

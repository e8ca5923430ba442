//! The CPU engine's hierarchy over a mesh: an Embree scene of one geometry per part (triangles
//! over the mesh's f32 vertices in its device frame, or a sphere set), built on every core.

use std::any::Any;
use std::ffi::c_void;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use glam::DVec3;

use super::mesh::{Mesh, MeshBatch, MeshGeometry, MeshHierarchy, MeshKind};
use crate::embree::api::{
    BUFFER_TYPE_INDEX, BUFFER_TYPE_VERTEX, BUILD_QUALITY_LOW, BUILD_QUALITY_MEDIUM, BUILD_QUALITY_REFIT, FORMAT_FLOAT3,
    FORMAT_FLOAT4, FORMAT_UINT3, GEOMETRY_TYPE_SPHERE_POINT, GEOMETRY_TYPE_TRIANGLE, SCENE_FLAG_COMPACT,
    SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS, SCENE_FLAG_ROBUST,
};
use crate::embree::objects::{EmbreeDevice, EmbreeGeometry, EmbreeScene};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::build_options::{BuildOptions, BuildPreference, BuildStats};
use crate::geometry::rays::PerRay;
use crate::geometry::vertex_format::VertexFormat;

/// A mesh's Embree scene and the vertices its geometries share.
///
/// Embree's triangle test multiplies a distance by a triangle's area: with coordinates near 1e15
/// that overflows f32 (the ray misses). So Embree holds the mesh's device-frame coordinates divided
/// by `unit`, the power of two at or above their largest magnitude (exact: every f32 keeps its
/// digits), and each instance scales by it again.
pub struct CpuMesh {
    scene: EmbreeScene,
    /// The power of two Embree's coordinates are divided by (f64 bits; a refit may change it).
    unit: AtomicU64,
    /// One per part (geometry id = part), kept for refits.
    parts: Vec<EmbreeGeometry>,
    /// The f32 vertices (xyz and a pad: Embree's vector loads read 16 bytes) every part's
    /// triangles index; refits write them in place (the address never moves).
    vertices: Mutex<Vec<[f32; 4]>>,
    stats: BuildStats,
}

/// The scene flags of every CPU hierarchy: robust traversal (Embree's watertight test, with no
/// optimization that loses accuracy) and filters passed by each query.
pub fn scene_flags(options: BuildOptions) -> u32 {
    let compact = if options.preference == BuildPreference::LowMemory { SCENE_FLAG_COMPACT } else { 0 };
    SCENE_FLAG_ROBUST | SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS | compact
}

/// Embree's build quality for `options`: its binned SAH builder for fast traces (spatial splits,
/// `HIGH`, would report a triangle once per piece to the filters that count hits), its Morton
/// builder for fast builds.
pub fn build_quality(options: BuildOptions) -> u32 {
    match options.preference {
        BuildPreference::FastTrace | BuildPreference::LowMemory => BUILD_QUALITY_MEDIUM,
        BuildPreference::FastBuild => BUILD_QUALITY_LOW,
    }
}

/// Builds each item's mesh on the CPU engine's device; the error of a bad item names it.
pub fn build_cpu_meshes(device: &Arc<EmbreeDevice>, batch: MeshBatch) -> Result<Vec<Mesh>> {
    let MeshBatch { items, options, format, interrupt, .. } = batch;
    let mut meshes = Vec::with_capacity(items.len());
    for (k, item) in items.iter().enumerate() {
        interrupt.check()?;
        let geometry = MeshGeometry::triangles(item, format).map_err(|e| match (e, items.len()) {
            (Error::InvalidValue(m), n) if n > 1 => invalid_value(format!("mesh {k}: {m}")),
            (e, _) => e,
        })?;
        let hierarchy = CpuMesh::triangles(device, &geometry, options)?;
        meshes.push(Mesh::new(geometry, options, Box::new(hierarchy)));
    }
    Ok(meshes)
}

/// Builds a set of spheres on the CPU engine's device.
pub fn build_cpu_spheres(
    device: &Arc<EmbreeDevice>,
    centers: Vec3s,
    radii: PerRay,
    options: BuildOptions,
) -> Result<Mesh> {
    let geometry = MeshGeometry::spheres(centers, radii)?;
    let hierarchy = CpuMesh::spheres(device, &geometry, options)?;
    Ok(Mesh::new(geometry, options, Box::new(hierarchy)))
}

impl CpuMesh {
    /// The CPU engine's hierarchy of `mesh`.
    pub fn of(mesh: &Mesh) -> Result<&CpuMesh> {
        mesh.hierarchy::<CpuMesh>()
    }

    pub fn scene(&self) -> &EmbreeScene {
        &self.scene
    }

    /// What Embree's coordinates are divided by (instances scale by it).
    pub fn unit(&self) -> f64 {
        f64::from_bits(self.unit.load(Ordering::Acquire))
    }

    fn triangles(device: &Arc<EmbreeDevice>, geometry: &MeshGeometry, options: BuildOptions) -> Result<CpuMesh> {
        debug_assert_eq!(geometry.kind, MeshKind::Triangles);
        let set = &geometry.triangles;
        let unit = unit_of(set.vertices.iter().map(|v| v.abs().max_element()));
        let vertices: Vec<[f32; 4]> = set.vertices.iter().map(|v| in_units(*v, unit)).collect();
        let quality = build_quality(options);
        let ((scene, parts), bytes, seconds) = device.measured(|| {
            let scene = device.scene(scene_flags(options), quality)?;
            let mut parts = Vec::with_capacity(set.part_offsets.len() - 1);
            for (k, range) in set.part_offsets.windows(2).enumerate() {
                let part = device.geometry(GEOMETRY_TYPE_TRIANGLE)?;
                // SAFETY: `vertices` (kept in the mesh, never resized) outlives the geometry, and
                // its items are 16 bytes: Embree's loads of the last one stay inside.
                unsafe {
                    part.share_buffer(
                        BUFFER_TYPE_VERTEX,
                        FORMAT_FLOAT3,
                        vertices.as_ptr() as *const c_void,
                        16,
                        vertices.len(),
                    )?;
                }
                let faces = &set.faces[range[0] as usize..range[1] as usize];
                part.buffer(BUFFER_TYPE_INDEX, FORMAT_UINT3, faces.len(), |out: &mut [[u32; 3]]| {
                    out.copy_from_slice(faces)
                })?;
                part.set_build_quality(if options.allow_update { BUILD_QUALITY_REFIT } else { quality });
                scene.attach(&part, k as u32, u32::MAX)?;
                parts.push(part);
            }
            scene.commit()?;
            Ok((scene, parts))
        })?;
        let own = (vertices.len() * 16) as u64;
        let stats = built_stats(bytes + own, seconds);
        Ok(CpuMesh { scene, unit: AtomicU64::new(unit.to_bits()), parts, vertices: Mutex::new(vertices), stats })
    }

    fn spheres(device: &Arc<EmbreeDevice>, geometry: &MeshGeometry, options: BuildOptions) -> Result<CpuMesh> {
        let spheres = &geometry.spheres;
        let unit = unit_of(spheres.iter().map(|(c, r)| c.abs().max_element() + r));
        let ((scene, part), bytes, seconds) = device.measured(|| {
            let scene = device.scene(scene_flags(options), build_quality(options))?;
            let part = device.geometry(GEOMETRY_TYPE_SPHERE_POINT)?;
            part.buffer(BUFFER_TYPE_VERTEX, FORMAT_FLOAT4, spheres.len(), |out: &mut [[f32; 4]]| {
                for (o, (c, r)) in out.iter_mut().zip(spheres.iter()) {
                    let [x, y, z, _] = in_units(*c, unit);
                    *o = [x, y, z, (r / unit) as f32];
                }
            })?;
            scene.attach(&part, 0, u32::MAX)?;
            scene.commit()?;
            Ok((scene, part))
        })?;
        let unit = AtomicU64::new(unit.to_bits());
        Ok(CpuMesh {
            scene,
            unit,
            parts: vec![part],
            vertices: Mutex::new(Vec::new()),
            stats: built_stats(bytes, seconds),
        })
    }
}

/// The power of two at or above the largest of `magnitudes` (1 where they are all 0).
pub fn unit_of(magnitudes: impl Iterator<Item = f64>) -> f64 {
    let largest = magnitudes.fold(0.0f64, f64::max);
    if !(largest > 0.0 && largest.is_finite()) {
        return 1.0;
    }
    2f64.powi(largest.log2().ceil() as i32)
}

/// A device-frame point in `unit`s, as Embree holds it (xyz and a pad).
fn in_units(p: DVec3, unit: f64) -> [f32; 4] {
    let q = p / unit;
    [q.x as f32, q.y as f32, q.z as f32, 0.0]
}

/// A CPU build's statistics: its bytes (as built and held), no scratch (Embree frees its own),
/// and its time.
pub fn built_stats(bytes: u64, seconds: f64) -> BuildStats {
    BuildStats {
        built_size: bytes,
        size: bytes,
        scratch_size: 0,
        update_scratch_size: 0,
        build_seconds: seconds,
        batch: 0,
    }
}

impl MeshHierarchy for CpuMesh {
    fn stats(&self) -> BuildStats {
        self.stats
    }

    fn refit(&self, local: &[f64], _format: VertexFormat, _options: BuildOptions) -> Result<()> {
        let [part] = self.parts.as_slice() else {
            return Err(Error::Unsupported("Mesh.update refits single-part meshes; rebuild a multi-part mesh".into()));
        };
        let mut vertices = self.vertices.lock().unwrap_or_else(|e| e.into_inner());
        let unit = unit_of(local.iter().map(|c| c.abs()));
        for (v, xyz) in vertices.iter_mut().zip(local.chunks_exact(3)) {
            *v = in_units(DVec3::new(xyz[0], xyz[1], xyz[2]), unit);
        }
        // Scenes pick the new unit up in their update (which `check_current` asks for first).
        self.unit.store(unit.to_bits(), Ordering::Release);
        part.buffer_changed(BUFFER_TYPE_VERTEX)?;
        part.commit()?;
        self.scene.commit()
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

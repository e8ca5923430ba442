//! The dispatcher (`Tracer`): checks a query, picks its tier (the engine's GPU tiers, host
//! refinement of the engine's hits, the host's reference tier) and its query kind, and hands the
//! batch to the engine (`Engine`) or the host tiers (`host_tiers`). It holds no path's state and
//! names no device API.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use rayon::prelude::*;

use super::engine::Engine;
use super::grid_contains;
use super::hit_columns::{AskedColumn, HitColumns};
use super::hit_fields::{hits_from_prims, position_bytes_per_ray, Field, HitSink, FIELDS};
use super::host_tiers::{self, AllHits};
use super::idle::IdleMemory;
use super::profile::TraceProfile;
use super::request::{spheres_on_host, PointBatch, Precision, Query, RayBatch, Request, SignedDistance};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel::try_vec;
use crate::geometry::parallel::{self, OwnPool};
use crate::geometry::rays::Rays;
use crate::geometry::reference::ReferenceHit;
use crate::scene::Scene;

/// Dispatches queries on one device to its engine `E` and the host tiers. Any number of threads
/// may trace at once.
pub struct Tracer<E: Engine + ?Sized> {
    /// Threads of this device's own for its queries' host passes (`set_host_threads`).
    host_pool: Mutex<Option<Arc<OwnPool>>>,
    /// Last: a `Tracer<dyn Engine>` holds either engine.
    engine: E,
}

impl<E: Engine> Tracer<E> {
    pub fn new(engine: E) -> Tracer<E> {
        Tracer { host_pool: Mutex::new(None), engine }
    }
}

impl<E: Engine + ?Sized> Tracer<E> {
    /// The engine, for what only it has (the Vulkan engine's CUDA rays and `explain`).
    pub fn engine(&self) -> &E {
        &self.engine
    }

    /// The device's name, for messages.
    pub fn device_name(&self) -> &str {
        self.engine.name()
    }

    /// Where the time went in this device's last trace (of any thread).
    pub fn last_profile(&self) -> TraceProfile {
        self.engine.last_profile()
    }

    /// The staging, scratch and leases this device keeps idle between queries (as many as its
    /// queries used at once), and how many its queries had to make.
    pub fn idle_memory(&self) -> IdleMemory {
        self.engine.idle_memory()
    }

    /// Frees what `idle_memory` counts; later queries make what they need again.
    pub fn release_idle_memory(&self) {
        self.engine.release_idle_memory()
    }

    /// Rays per chunk: staging holds two chunks of rays and hits (72 bytes a ray each).
    pub fn chunk_rays(&self) -> usize {
        self.engine.chunk_rays()
    }

    pub fn set_chunk_rays(&self, rays: usize) -> Result<()> {
        self.engine.set_chunk_rays(rays)
    }

    /// How many threads of its own this device's host passes run on; `None`: the process's
    /// shared pool, on every core.
    pub fn host_threads(&self) -> Option<usize> {
        self.host_pool.lock().unwrap_or_else(|e| e.into_inner()).as_ref().map(|own| own.threads())
    }

    /// Gives this device `threads` threads of its own for its queries' host passes (packing
    /// rays, copying hits out), or (`None`) hands them back to the shared pool. Devices that
    /// trace at once (a `DeviceGroup`'s) each on cores of their own run their passes side by
    /// side, where in one pool they queue behind each other. Queries under way keep theirs.
    pub fn set_host_threads(&self, threads: Option<usize>) -> Result<()> {
        let pool = match threads {
            Some(0) => return Err(invalid_value("host_threads must be at least 1 (or None: every core)")),
            Some(n) => {
                let name = format!("vkray-device{}", self.engine.index());
                Some(Arc::new(OwnPool::new(n, &name).map_err(Error::Internal)?))
            }
            None => None,
        };
        // Started outside the lock; the old pool ends when the last query using it does.
        let old = std::mem::replace(&mut *self.host_pool.lock().unwrap_or_else(|e| e.into_inner()), pool);
        drop(old);
        Ok(())
    }

    /// Runs `work` (a query on this device) on this thread, its host passes on the device's own
    /// threads if it has them (`set_host_threads`).
    pub fn on_host_threads<R>(&self, work: impl FnOnce() -> R) -> R {
        let pool = self.host_pool.lock().unwrap_or_else(|e| e.into_inner()).clone();
        parallel::with_pool(pool.as_deref(), work)
    }

    /// Host bytes a query needs besides its inputs and outputs: staging, temporary hit fields,
    /// and the host tiers' per-ray records; for checking a query fits before it starts.
    pub fn working_bytes(&self, request: Request, rays: usize) -> usize {
        let staging = self.engine.staging_bytes(rays, request.precision == Precision::Exact);
        let host_tier = match request.precision {
            // Hits (40 bytes) and re-trace flags per ray, plus temporary ids and barycentrics.
            Precision::Refined => 40 + 1 + 12 + 16,
            Precision::Reference => 40,
            _ => 0,
        };
        staging + rays * host_tier
    }

    /// Traces `rays` against `scene` at `precision`, writing the fields `sink` asks for (`t` and
    /// `uv` as f64 in the f64 tiers). Each chunk's rays are checked as they are packed; an invalid
    /// ray stops the trace with an error naming it (chunks already in flight finish first, and
    /// what they wrote is not the caller's to read). `interrupt` is asked between chunks.
    ///
    /// The meshes of `scene` are held against `Mesh::update` for the whole trace.
    pub fn trace(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let started = Instant::now();
        let rays = &rays.sharing_origin();
        self.engine.check_usable()?;
        check_request(rays, request, sink)?;
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        self.trace_held(RayBatch { scene, rays, request, interrupt }, sink, started)
    }

    /// `trace` once its request is checked and the scene's meshes are held.
    fn trace_held(&self, batch: RayBatch, sink: &mut HitSink, started: Instant) -> Result<()> {
        let RayBatch { scene, rays, request, .. } = batch;
        let mut profile = TraceProfile { rays: rays.len(), ..Default::default() };
        let position = sink.position.take();
        let mut hit = sink.hit.take();
        if rays.is_empty() || (sink.outputs() == 0 && position.is_none() && hit.is_none()) {
            return Ok(());
        }
        let wide = request.precision.is_f64();
        let spheres_on_host = spheres_on_host(scene, request);
        let refine = request.precision == Precision::Refined && request.query == Query::Closest && !spheres_on_host;
        // The host needs the hit triangles (and barycentrics, or t on spheres) of rays whose
        // caller did not ask for them; `hit`, where the host decides the hits (the reference
        // tier, or refining, which may turn a hit into a miss), the final prim_id.
        let hit_from_host = request.precision == Precision::Reference || refine || spheres_on_host;
        let mut needed = Vec::new();
        if hit.is_some() && hit_from_host {
            needed.push(Field::Prim);
        }
        if refine || position.is_some() {
            needed.extend([Field::Prim, Field::Instance, Field::Geometry]);
        }
        if position.is_some() {
            needed.push(Field::Uv);
            if scene.has_spheres() {
                needed.push(Field::T);
            }
        }
        let mut temps = Vec::new();
        for field in needed.iter().filter(|f| sink.field(**f).is_none()) {
            temps.push((*field, try_vec(rays.len() * field.bytes_per_ray(wide), 0u8, "a temporary hit field")?));
        }
        let mut work = HitSink::default();
        for (field, out) in sink.iter_mut() {
            work.set(field, out);
        }
        for (field, temp) in temps.iter_mut() {
            work.set(*field, temp);
        }
        if !hit_from_host {
            // The GPU tiers' chunk loop writes it as it copies the hits out.
            work.hit = hit.take();
        }
        self.run_tier(batch, &mut work, &mut profile)?;
        if let Some(out) = hit {
            hits_from_prims(work.field(Field::Prim).unwrap_or_default(), out);
        }
        if let Some(out) = position {
            let hits = host_tiers::HitTriangles {
                prim: work.field(Field::Prim).unwrap_or_default(),
                instance: work.field(Field::Instance).unwrap_or_default(),
                geometry: work.field(Field::Geometry).unwrap_or_default(),
                t: work.field(Field::T).unwrap_or_default(),
                uv: work.field(Field::Uv).unwrap_or_default(),
                wide,
            };
            host_tiers::positions(scene, rays, &hits, out);
        }
        profile.total = started.elapsed().as_secs_f64();
        self.engine.keep_profile(profile);
        self.engine.check_reported()
    }

    /// Runs the query in its tier, writing every field `work` asks for.
    fn run_tier(&self, batch: RayBatch, work: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        let spheres_on_host = spheres_on_host(scene, request);
        let refine = request.precision == Precision::Refined && request.query == Query::Closest && !spheres_on_host;
        if request.query == Query::Transmit && !scene.has_opacity() {
            // Where every triangle is opaque, light is kept (1) or not (0): an occlusion query.
            return self.transmit_by_occlusion(batch, work, profile);
        }
        let host_transmit = !matches!(request.precision, Precision::Fast | Precision::Exact) || spheres_on_host;
        if request.query == Query::Transmit && host_transmit {
            // The host's tiers multiply over the f64 hits of every crossing.
            let every = Request { query: Query::All, opacity_threshold: 0.0, ..request };
            let started = Instant::now();
            let all = self.all_hits(batch.asking(every), usize::MAX, 0)?;
            let out = work.field_mut(Field::T).expect("transmittance writes t");
            if request.precision.is_f64() {
                host_tiers::transmittance(scene, &all, bytemuck::cast_slice_mut(out));
            } else {
                let mut kept = try_vec(rays.len(), 0.0f64, "the light each ray keeps")?;
                host_tiers::transmittance(scene, &all, &mut kept);
                for (dst, left) in bytemuck::cast_slice_mut::<u8, f32>(out).iter_mut().zip(kept) {
                    *dst = left as f32;
                }
            }
            if request.precision == Precision::Refined {
                // The GPU's all-hits passes left their times in the last profile.
                *profile = TraceProfile { rays: rays.len(), ..self.engine.last_profile() };
            }
            let gpu = profile.gpu_upload.unwrap_or(0.0) + profile.gpu_trace.unwrap_or(0.0);
            profile.host_f64 = (started.elapsed().as_secs_f64() - gpu).max(0.0);
            return Ok(());
        }
        match request.precision {
            _ if spheres_on_host && request.precision != Precision::Reference => {
                self.run_tier(batch.asking(Request { precision: Precision::Reference, ..request }), work, profile)
            }
            Precision::Exact => self.engine.trace_rays(batch, true, work, profile),
            Precision::Refined if refine => {
                // The GPU finds which triangle; the host recomputes where, in f64.
                let mut host_fields = HitSink::default();
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = work.take(field) {
                        host_fields.set(field, out);
                    }
                }
                self.engine.trace_rays(batch, false, work, profile)?;
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = host_fields.take(field) {
                        work.set(field, out);
                    }
                }
                let host = Instant::now();
                host_tiers::refine(scene, rays, request.filter(), work, interrupt)?;
                profile.host_f64 = host.elapsed().as_secs_f64();
                Ok(())
            }
            Precision::Fast | Precision::Refined => self.engine.trace_rays(batch, false, work, profile),
            Precision::Reference => {
                rays.check()?;
                let host = Instant::now();
                host_tiers::reference(
                    scene,
                    rays,
                    request.filter(),
                    request.query == Query::Occluded,
                    work,
                    interrupt,
                )?;
                profile.host_f64 = host.elapsed().as_secs_f64();
                Ok(())
            }
        }
    }

    /// Transmittance in a scene without opacity: 1 where a ray is not occluded, else 0.
    fn transmit_by_occlusion(&self, batch: RayBatch, work: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        let (rays, request) = (batch.rays, batch.request);
        let mut blocked = try_vec(rays.len(), 0i32, "the rays' occlusion")?;
        let mut sink = HitSink::default();
        sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut blocked));
        self.run_tier(batch.asking(Request { query: Query::Occluded, ..request }), &mut sink, profile)?;
        let out = work.field_mut(Field::T).expect("transmittance writes t");
        let left = |b: &i32| if *b >= 0 { 0.0 } else { 1.0 };
        parallel::install(|| {
            if request.precision.is_f64() {
                let out: &mut [f64] = bytemuck::cast_slice_mut(out);
                out.par_iter_mut().zip(&blocked).with_min_len(4096).for_each(|(t, b)| *t = left(b));
            } else {
                let out: &mut [f32] = bytemuck::cast_slice_mut(out);
                out.par_iter_mut().zip(&blocked).with_min_len(4096).for_each(|(t, b)| *t = left(b) as f32);
            }
        });
        Ok(())
    }

    /// Every hit of every ray (the nearest `max_hits` of each), as records: on the GPU in the
    /// fast and exact tiers (the refined tier re-intersects the fast tier's hits in f64), on the
    /// CPU in the reference tier. `host_bytes_per_hit`: what the caller will need per hit, for
    /// refusing a result that cannot fit before it is stored.
    pub fn trace_all(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        max_hits: usize,
        host_bytes_per_hit: usize,
        interrupt: &dyn Interrupt,
    ) -> Result<AllHits> {
        let rays = &rays.sharing_origin();
        self.all_hits(RayBatch { scene, rays, request, interrupt }, max_hits, host_bytes_per_hit)
    }

    /// Every hit of every ray (the nearest `max_hits` of each) as the answer's `asked` columns and
    /// each hit's ray: written by the engine where it can (the GPU's columns), else from
    /// `trace_all`'s records on all cores.
    pub fn all_hit_columns(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        max_hits: usize,
        asked: &[AskedColumn],
        interrupt: &dyn Interrupt,
    ) -> Result<HitColumns> {
        let rays = &rays.sharing_origin();
        let batch = RayBatch { scene, rays, request, interrupt };
        if matches!(request.precision, Precision::Fast | Precision::Exact) && !scene.has_spheres() {
            self.engine.check_usable()?;
            check_contacts(request)?;
            if let Some(columns) = self.engine.all_hit_columns(batch, max_hits, asked)? {
                return Ok(columns);
            }
        }
        let bytes_per_hit = HitColumns::bytes_per_hit(asked, request.precision.is_f64());
        let all = self.all_hits(batch, max_hits, bytes_per_hit)?;
        // Hundreds of millions of hits take a pass each to write out: Ctrl-C between them.
        interrupt.check()?;
        let (columns, records) = HitColumns::from_records(scene, rays, all, asked)?;
        self.engine.recycle_hits(records);
        interrupt.check()?;
        Ok(columns)
    }

    /// `trace_all` of a batch.
    fn all_hits(&self, batch: RayBatch, max_hits: usize, host_bytes_per_hit: usize) -> Result<AllHits> {
        let RayBatch { scene, rays, request, interrupt } = batch;
        self.engine.check_usable()?;
        check_contacts(request)?;
        if scene.has_spheres() && request.precision != Precision::Reference {
            // Every tier's hits of spheres are the reference tier's (the f32 tiers' values in f32).
            let reference = Request { precision: Precision::Reference, ..request };
            let all = self.all_hits(batch.asking(reference), max_hits, host_bytes_per_hit)?;
            return Ok(AllHits { wide: request.precision.is_f64(), ..all });
        }
        match request.precision {
            Precision::Exact => self.engine.all_hits(batch, max_hits, host_bytes_per_hit),
            Precision::Fast | Precision::Refined => {
                let fast = self.engine.all_hits(batch, max_hits, host_bytes_per_hit)?;
                if request.precision == Precision::Fast {
                    return Ok(fast);
                }
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                host_tiers::refine_all(scene, rays, request.filter(), max_hits, &fast, interrupt)
            }
            Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                rays.check()?;
                host_tiers::all_hits(scene, rays, request.filter(), max_hits, host_bytes_per_hit, interrupt)
            }
        }
    }

    /// Hands the records of a `trace_all` answer back to the engine, once written out.
    pub fn recycle_hits(&self, hits: Vec<ReferenceHit>) {
        self.engine.recycle_hits(hits)
    }

    /// The number of hits of each ray, into `out`: as `trace_all` finds them, without storing
    /// them (but in the refined tier, whose hits must be re-intersected on the host).
    pub fn count(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        out: &mut [i32],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if out.len() != rays.len() {
            return Err(invalid_value(format!("count's output has {} entries for {} rays", out.len(), rays.len())));
        }
        let rays = &rays.sharing_origin();
        self.engine.check_usable()?;
        match request.precision {
            _ if scene.has_spheres() => {
                // Spheres are counted on the host in every tier (both crossings of each).
                check_contacts(request)?;
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                rays.check()?;
                host_tiers::count_hits(scene, rays, request.filter(), out, interrupt)
            }
            Precision::Fast | Precision::Exact => {
                let mut sink = HitSink::default();
                sink.set(Field::Prim, bytemuck::cast_slice_mut(out));
                self.trace(scene, rays, Request { query: Query::Count, ..request }, &mut sink, interrupt)
            }
            Precision::Refined => {
                let all = self.trace_all(scene, rays, request, usize::MAX, 0, interrupt)?;
                for (count, pair) in out.iter_mut().zip(all.offsets.windows(2)) {
                    *count = (pair[1] - pair[0]) as i32;
                }
                Ok(())
            }
            Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                rays.check()?;
                host_tiers::count_hits(scene, rays, request.filter(), out, interrupt)
            }
        }
    }

    /// The surface point nearest to each of `points` within `max_distance`, its fields written
    /// into `sink` (`t`: the distance; f64 in the f64 tiers). Tiers: `reference` (the CPU, f64).
    pub fn closest_points(
        &self,
        scene: &Scene,
        points: Vec3s,
        max_distance: f64,
        precision: Precision,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        self.check_point_query(points, max_distance)?;
        if sink.hit.is_some() {
            return Err(invalid_value("hit (whether a ray hit anything) is not an output of closest_points"));
        }
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        if scene.has_spheres() {
            check_spheres_round(scene)?;
        }
        let hits =
            match precision {
                Precision::Reference => host_tiers::closest_points(scene, points, max_distance, interrupt)?,
                // The GPU's closest-point structures hold triangles: spheres are measured on the host.
                Precision::Exact | Precision::Fast if scene.has_spheres() => {
                    host_tiers::closest_points(scene, points, max_distance, interrupt)?
                }
                Precision::Exact | Precision::Fast => {
                    let batch = PointBatch { scene, points, interrupt };
                    return self.engine.closest_points(batch, max_distance, precision, sink);
                }
                Precision::Refined => return Err(Error::Unsupported(
                    "closest points are answered at precision='fast' (f32 on the GPU), 'exact' (f64 on the GPU) or \
                     'reference' (f64 on the CPU): 'refined' would be 'exact'"
                        .into(),
                )),
            };
        host_tiers::write_closest(scene, sink, |i| host_tiers::closest_hit_record(scene, &hits[i]));
        Ok(())
    }

    /// The checks every query of distances makes: the device's, `max_distance`, finite points.
    fn check_point_query(&self, points: Vec3s, max_distance: f64) -> Result<()> {
        self.engine.check_usable()?;
        if max_distance.is_nan() || max_distance < 0.0 {
            return Err(invalid_value(format!("max_distance must be >= 0 (or inf), got {max_distance}")));
        }
        crate::geometry::arrays::check_points("points", points)
    }

    /// The distance from each point to the nearest surface within `max_distance` (`closest_points`
    /// at `precision`), negative where `contains` (at `contains_precision`, by winding number or
    /// parity) puts the point inside, into `out` (f64 a point).
    pub fn signed_distance(
        &self,
        scene: &Scene,
        points: Vec3s,
        query: SignedDistance,
        out: &mut [f64],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        let SignedDistance { max_distance, precision, contains_precision, winding } = query;
        if out.len() != points.rows() {
            return Err(invalid_value(format!(
                "signed_distance's output has {} entries for {} points",
                out.len(),
                points.rows()
            )));
        }
        self.check_point_query(points, max_distance)?;
        let on_gpu = !scene.has_spheres();
        if on_gpu && self.engine.signed_distance(PointBatch { scene, points, interrupt }, query, out)? {
            return Ok(());
        }
        let mut sink = HitSink::default();
        sink.set(Field::T, bytemuck::cast_slice_mut(out));
        self.closest_points(scene, points, max_distance, precision, &mut sink, interrupt)?;
        let mut inside = try_vec(points.rows(), 0u8, "the points inside")?;
        self.contains(scene, points, contains_precision, winding, &mut inside, interrupt)?;
        parallel::install(|| {
            out.par_iter_mut().zip(&inside).with_min_len(4096).filter(|(_, &inside)| inside != 0).for_each(|(d, _)| {
                *d = -*d;
            })
        });
        Ok(())
    }

    /// Whether each point is inside any instance (1) or not (0), into `out`: by parity (the
    /// caller checked that every mesh is closed) or by winding number.
    pub fn contains(
        &self,
        scene: &Scene,
        points: Vec3s,
        precision: Precision,
        winding: bool,
        out: &mut [u8],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if out.len() != points.rows() {
            return Err(invalid_value(format!(
                "contains' output has {} entries for {} points",
                out.len(),
                points.rows()
            )));
        }
        self.engine.check_usable()?;
        if out.is_empty() {
            return Ok(());
        }
        if precision == Precision::Exact {
            if let Some(grid_use) = grid_contains::GridUse::of_engine(self.engine.limits().on_host) {
                if let Some(grid) = grid_contains::inside_grid(scene, winding, points.rows(), grid_use, interrupt)? {
                    scene.check_current()?;
                    let batch = PointBatch { scene, points, interrupt };
                    if self.engine.contains_through_grid(batch, &grid, winding, out)? {
                        return Ok(());
                    }
                    // The grid's pass checks the points; a far one lies beyond the grid (outside).
                    let exact = |rest: Vec3s, out: &mut [u8]| self.contains_exact(scene, rest, winding, out, interrupt);
                    let segments = grid_use.segments;
                    return grid_contains::contains_by_grid(
                        scene, &grid, points, winding, segments, out, interrupt, exact,
                    );
                }
            }
        }
        crate::geometry::arrays::check_points("points", points)?;
        // A point beyond f32's range (which rays cannot start from) outside the scene is outside.
        let moved = crate::geometry::rays::far_points_moved_in(points, scene.bounds(), scene.center)?;
        let points = moved.as_deref().map_or(points, Vec3s::F64);
        if precision == Precision::Exact {
            return self.contains_exact(scene, points, winding, out, interrupt);
        }
        match precision {
            Precision::Reference => {
                let _in_use = scene.hold_meshes();
                scene.check_current()?;
                host_tiers::contains(scene, points, winding, out, interrupt)
            }
            _ => Err(Error::Unsupported(
                "contains answers at precision='exact' (the f64 test on the GPU: each crossing counted once) or \
                 'reference' (on the CPU); the f32 tiers could count a crossing at an edge twice or not at all"
                    .into(),
            )),
        }
    }

    /// `contains` at the exact tier: the engine's f64 test; the host's where the engine has no
    /// f64 winding numbers, or the scene holds spheres (the GPU's f64 structures hold triangles).
    fn contains_exact(
        &self,
        scene: &Scene,
        points: Vec3s,
        winding: bool,
        out: &mut [u8],
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if (!winding || self.engine.limits().f64_tests) && !scene.has_spheres() {
            return self.engine.contains(PointBatch { scene, points, interrupt }, winding, out);
        }
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        host_tiers::contains(scene, points, winding, out, interrupt)
    }
}

/// Closest points on spheres are measured in the scene's frame, where an instance must keep a
/// sphere round: its transform a rotation (or mirror) and one scale.
fn check_spheres_round(scene: &Scene) -> Result<()> {
    for (i, placement) in scene.placements.iter().enumerate().filter(|(_, p)| p.triangles.is_spheres()) {
        let m = placement.to_scene.linear;
        let scale = m.x_axis.length_squared();
        let tolerance = 1e-9 * scale;
        let round =
            [m.y_axis.length_squared(), m.z_axis.length_squared()].iter().all(|l| (l - scale).abs() <= tolerance)
                && [m.x_axis.dot(m.y_axis), m.x_axis.dot(m.z_axis), m.y_axis.dot(m.z_axis)]
                    .iter()
                    .all(|d| d.abs() <= tolerance);
        if !round {
            return Err(Error::Unsupported(format!(
                "closest points and distances of spheres need instances that keep them round: instance {i}'s transform \
                 stretches its spheres into ellipsoids (a rotation, a mirror and one scale keep them spheres)"
            )));
        }
    }
    Ok(())
}

/// Contacts (closed triangles) are the exact tier's alone.
fn check_contacts(request: Request) -> Result<()> {
    if request.contacts && request.precision != Precision::Exact {
        return Err(Error::Unsupported("contacts are answered at precision='exact'".into()));
    }
    Ok(())
}

/// Checks what a query asks before any work: array sizes, fields the query can write, tiers the
/// scene can be traced in.
fn check_request(rays: &Rays, request: Request, sink: &HitSink) -> Result<()> {
    rays.check_shapes()?;
    check_contacts(request)?;
    let n = rays.len();
    let wide = request.precision.is_f64();
    for field in FIELDS {
        if let Some(out) = sink.field(field) {
            if out.len() != n * field.bytes_per_ray(wide) {
                return Err(invalid_value(format!("output for {} has {} bytes for {n} rays", field.name(), out.len())));
            }
        }
    }
    if let Some(out) = &sink.position {
        if out.len() != n * position_bytes_per_ray(wide) {
            return Err(invalid_value(format!("output for position has {} bytes for {n} rays", out.len())));
        }
    }
    if let Some(out) = &sink.hit {
        if out.len() != n {
            return Err(invalid_value(format!("output for hit has {} bytes for {n} rays", out.len())));
        }
        if !matches!(request.query, Query::Closest | Query::Occluded) {
            return Err(invalid_value("hit (whether a ray hit anything) is an output of closest and occluded queries"));
        }
    }
    // Occlusion stops at any hit, so it knows only whether there was one; a count writes the
    // number alone (in prim_id's place).
    let answerable = sink.outputs() & !Field::Prim.bit() == 0 && sink.position.is_none();
    if request.query == Query::Occluded && !answerable {
        return Err(invalid_value("an occlusion query writes prim_id alone (>= 0 where the ray is blocked)"));
    }
    let gpu_tier = matches!(request.precision, Precision::Fast | Precision::Exact);
    if request.query == Query::Count && (!answerable || !gpu_tier) {
        return Err(Error::Unsupported(
            "a count on the GPU is answered at precision='fast' or 'exact', into one int32 a ray".into(),
        ));
    }
    if request.query == Query::All {
        return Err(invalid_value("all hits are traced by Tracer::trace_all"));
    }
    if request.query == Query::Transmit && (sink.outputs() != Field::T.bit() || sink.position.is_some()) {
        return Err(invalid_value("a transmittance query writes t alone (the light each ray keeps)"));
    }
    if request.query == Query::Parity && (!answerable || request.precision != Precision::Exact) {
        return Err(invalid_value("a parity query is answered at precision='exact', into one int32 a ray"));
    }
    let crossings_and_t = sink.outputs() == Field::Prim.bit() | Field::T.bit() && sink.position.is_none();
    if request.query == Query::Winding && (!crossings_and_t || request.precision != Precision::Exact) {
        return Err(invalid_value(
            "a winding query is answered at precision='exact', into one int32 (prim_id) and one f64 (t) a ray",
        ));
    }
    Ok(())
}

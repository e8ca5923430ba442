//! Closest points on the GPU (tiers "exact" and "fast"): shaders/closest_point.comp searches the
//! reference tier's own hierarchies (`scene::ClosestScene`) best first, one invocation per point,
//! with the CPU's f64 operations: the reference tier's answers, on the device's cores. Points go
//! through in chunks, two in flight, as rays do (`chunks.rs`); only the distances travel back
//! when only distances are asked.

use std::sync::Arc;
use std::time::Instant;

use ash::vk;
use glam::DVec3;
use rayon::prelude::*;

use super::cap_winding::{CapChunk, CapPass};
use super::shared::Shared;
use super::staging::pair_bytes;
use super::timestamps::{start_stamps, Stamp, Stamps};
use super::variants::Variant;
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::geometry::parallel::try_vec;
use crate::geometry::reference::ReferenceHit;
use crate::geometry::winding::CAP_MARGIN_DIVISOR;
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::{Backend, Commands, Context};
use crate::gpu::memory::{memory_barrier, upload_staging, Buffer, MemoryLocation};
use crate::gpu::records::{
    Params, PointHit, PointOrderParams, PointParams, PointRays, SignPointsParams, POINT_ORDER_COUNT, POINT_ORDER_SCAN,
    POINT_ORDER_SCAN_BLOCKS, POINT_ORDER_SCATTER,
};
use crate::gpu::shaders;
use crate::scene::{ClosestScene, Scene, VulkanScene, WindingScene, WINDING_MARGIN, WINDING_TERM_ERROR};
use crate::trace::hit_fields::{Field, HitSink};
use crate::trace::host_tiers;
use crate::trace::idle::{Held, Idle, IdleMemory, IdlePool};
use crate::trace::pacer::ChunkPacer;
use crate::trace::profile::TraceProfile;
use crate::trace::request::{PointBatch, Precision};

/// Points per chunk at most on a software device (two chunks in flight: the copies of one
/// overlap the search of the other), so that Ctrl-C and progress come between chunks of seconds,
/// not tens of seconds: 2 × 20 MB of staging at full outputs.
const CHUNK_POINTS: usize = 1 << 18;
/// Points per chunk at most on a hardware GPU: denser chunks put nearer neighbours side by side
/// in the grid order (docs/benchmarks.md): 1M closest points on fandisk took 10.5 ms of an H200's
/// time in chunks of 2^18 points, 6.2 in one of 2^20. 2 × 32 MB of staging for distances and
/// winding numbers, 2 × 80 MB at full outputs.
const LEAN_CHUNK_POINTS: usize = 1 << 20;
/// Cells per axis of the grid that orders each chunk's points (point_order.comp's GRID): 64³
/// cells (1 MB of counters), a few points each at full chunks; points crowded near a surface
/// then spread over enough cells that their counters' atomics do not queue.
const ORDER_GRID: u32 = crate::geometry::morton::POINT_GRID;
/// Chunks of fewer points are searched as they come (ordering them would cost more than it buys).
pub(super) const ORDER_MIN_POINTS: usize = 4096;

/// The point queries' shaders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum PointShader {
    /// Closest points measured in f64.
    Closest,
    /// Closest points measured in f32 (the fast tier).
    ClosestF32,
    /// Winding numbers.
    Winding,
}

/// Two slots serve one query: keep as many as ran at once, at least two queries' worth (slots
/// with and without full outputs or signs) and at most eight.
const IDLE_POINT_SLOTS: (usize, usize) = (4, 16);

/// The point queries' pipelines of one device (compiled on first use) and their staging.
pub struct PointPipelines {
    ctx: Arc<Context>,
    /// closest_point.comp, winding.comp (both in f64: loaded only with shaderFloat64).
    kernels: [ComputeKernel; 2],
    /// point_order.comp.
    order: ComputeKernel,
    /// sign_points.comp.
    pub(super) sign: ComputeKernel,
    idle: IdlePool<PointSlot>,
}

impl PointPipelines {
    pub fn new(ctx: &Arc<Context>) -> Result<PointPipelines> {
        let needs = "point queries on the GPU need; precision='reference' gives the same answers on the CPU";
        let kernel = |spirv| ComputeKernel::new(ctx, spirv, std::mem::size_of::<PointParams>(), Some(needs));
        Ok(PointPipelines {
            ctx: ctx.clone(),
            kernels: [kernel(shaders::CLOSEST_POINT)?, kernel(shaders::WINDING)?],
            order: ComputeKernel::new(ctx, shaders::POINT_ORDER, std::mem::size_of::<PointOrderParams>(), Some(needs))?,
            sign: ComputeKernel::new(ctx, shaders::SIGN_POINTS, std::mem::size_of::<SignPointsParams>(), Some(needs))?,
            idle: IdlePool::new(IDLE_POINT_SLOTS.0, IDLE_POINT_SLOTS.1),
        })
    }

    pub(super) fn kernel(&self, shader: PointShader) -> &ComputeKernel {
        &self.kernels[(shader == PointShader::Winding) as usize]
    }

    /// The pipeline of `shader`.
    pub(super) fn pipeline(&self, shader: PointShader) -> Result<vk::Pipeline> {
        match shader {
            // closest_point.comp's constant 1: measure in f32.
            PointShader::Closest | PointShader::ClosestF32 => {
                self.kernel(shader).pipeline(&[(shader == PointShader::ClosestF32) as u32])
            }
            // winding.comp's constant 2 (1 is unused).
            PointShader::Winding => self.kernel(shader).pipeline(&[0, CAP_MARGIN_DIVISOR]),
        }
    }

    /// Two slots of at least `capacity` points with room for full outputs where `full` and for
    /// the sign's crossings where `signs`: idle ones where they fit, new ones (allocated outside
    /// the lock) otherwise.
    pub(super) fn take_slots(&self, capacity: usize, full: bool, signs: bool) -> Result<[PointSlot; 2]> {
        let fits = |s: &PointSlot| s.capacity >= capacity && (s.full || !full) && (s.signs || !signs);
        let mut found = self.idle.take(2, fits, |_| true);
        while found.len() < 2 {
            match PointSlot::new(&self.ctx, capacity, full, signs) {
                Ok(slot) => found.push(slot),
                Err(error) => {
                    self.idle.give_back(2, found);
                    return Err(error);
                }
            }
        }
        let second = found.pop().expect("two slots");
        Ok([found.pop().expect("two slots"), second])
    }

    pub(super) fn give_back(&self, slots: [PointSlot; 2]) {
        self.idle.give_back(2, slots);
    }
}

impl Idle for PointPipelines {
    fn memory(&self) -> IdleMemory {
        self.idle.memory()
    }

    fn clear(&self) {
        self.idle.clear();
    }
}

/// Staging for one chunk of points in flight: the points (xyz, f32 or f64 as the caller's) in, the distances (and, for
/// full outputs, a `PointHit` each; for signs, a bit a point: unsure) out; device copies on
/// discrete GPUs, where the signs' crossings and cap winding numbers stay.
pub(super) struct PointSlot {
    points_host: Buffer,
    pub(super) results_host: Buffer,
    device: Option<(Buffer, Buffer)>,
    /// point_order.comp's cells (u32 each) and order (u32 per point).
    cells: Buffer,
    order: Buffer,
    /// Signs: the `PointRays` record the sign's trace reads (device memory, written by the chunk's
    /// commands).
    rays_record: Option<Buffer>,
    pub(super) capacity: usize,
    full: bool,
    signs: bool,
    stamps: Option<Stamps>,
    /// The points packed last are f32 (else f64): their address carries `POINTS_F32_TAG`.
    points_f32: bool,
    /// The chunk's points where they already lie on the device (tagged as `points_address`),
    /// neither packed nor uploaded: memory shared with CUDA.
    points_on_device: Option<u64>,
}

/// Bit 0 of a points address (shaders/points.glsl): the points are f32 xyz, not f64. An f32
/// caller's points travel as they are, 12 bytes a point rather than 24 (a million points: 12 MB
/// less to pack, 0.8 → 0.4 ms on an H200's 16 cores), and the shaders widen them
/// exactly, subnormals included (shaders/widen.glsl), as the host's f64 would.
const POINTS_F32_TAG: u64 = 1;

impl Held for PointSlot {
    fn bytes(&self) -> u64 {
        let own =
            [&self.points_host, &self.results_host, &self.cells, &self.order].map(|b| b.size()).iter().sum::<u64>();
        own + pair_bytes(&self.device) + self.rays_record.as_ref().map_or(0, Buffer::size)
    }
}

impl PointSlot {
    fn new(ctx: &Arc<Context>, capacity: usize, full: bool, signs: bool) -> Result<PointSlot> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let points = (24 * capacity) as u64;
        let results = PointSlot::layout(capacity, full, signs).total as u64;
        let (points_host, results_host, device) = if ctx.unified_memory {
            (
                Buffer::new(ctx, points, storage, MemoryLocation::CpuToGpu, "points")?,
                // TRANSFER_SRC: `contains` of CUDA points copies its answers out of it.
                Buffer::new(
                    ctx,
                    results,
                    storage | U::TRANSFER_SRC | U::TRANSFER_DST,
                    MemoryLocation::GpuToCpu,
                    "closest points",
                )?,
                None,
            )
        } else {
            (
                Buffer::new(ctx, points, U::TRANSFER_SRC, upload_staging(), "points staging")?,
                Buffer::new(ctx, results, U::TRANSFER_DST, MemoryLocation::GpuToCpu, "closest points readback")?,
                Some((
                    Buffer::new(ctx, points, storage | U::TRANSFER_DST, MemoryLocation::GpuOnly, "points")?,
                    Buffer::new(
                        ctx,
                        results,
                        storage | U::TRANSFER_SRC | U::TRANSFER_DST,
                        MemoryLocation::GpuOnly,
                        "closest points",
                    )?,
                )),
            )
        };
        // The cells' counters, then their blocks' (point_order.comp: at most one a 64 cells).
        let cells = (4 * (ORDER_GRID.pow(3) + ORDER_GRID.pow(3) / 64)) as u64;
        let cells = Buffer::new(ctx, cells, storage | U::TRANSFER_DST, MemoryLocation::GpuOnly, "point order cells")?;
        let order = Buffer::new(ctx, 4 * capacity as u64, storage, MemoryLocation::GpuOnly, "point order")?;
        let rays_record = match signs {
            true => Some(Buffer::new(
                ctx,
                std::mem::size_of::<PointRays>() as u64,
                storage | U::TRANSFER_DST,
                MemoryLocation::GpuOnly,
                "point rays",
            )?),
            false => None,
        };
        Ok(PointSlot {
            points_host,
            results_host,
            device,
            cells,
            order,
            rays_record,
            capacity,
            full,
            signs,
            stamps: Stamps::new(ctx)?,
            points_f32: false,
            points_on_device: None,
        })
    }

    /// Where each output lies in the results buffer.
    fn layout(capacity: usize, full: bool, signs: bool) -> ResultsLayout {
        let hits = 8 * capacity;
        let crossings = hits + if full { size_of_hit() * capacity } else { 0 };
        // f64s: 8-byte aligned.
        let cap_winding = crossings + if signs { 4 * capacity.next_multiple_of(2) } else { 0 };
        let unsure = cap_winding + if signs { 8 * capacity } else { 0 };
        let total = unsure + if signs { 4 * capacity.div_ceil(32) } else { 0 };
        ResultsLayout { hits, crossings, cap_winding, unsure, total }
    }

    /// Where this slot's outputs lie in its results buffer.
    pub(super) fn results_layout(&self) -> ResultsLayout {
        PointSlot::layout(self.capacity, self.full, self.signs)
    }

    /// Signs: the `PointRays` record's buffer.
    pub(super) fn rays_record(&self) -> Option<&Buffer> {
        self.rays_record.as_ref()
    }

    /// The packed points' address, tagged (`POINTS_F32_TAG`) where they are f32.
    pub(super) fn points_address(&self) -> u64 {
        if let Some(address) = self.points_on_device {
            return address;
        }
        let base = self.device.as_ref().map_or(self.points_host.address(), |(points, _)| points.address());
        debug_assert_eq!(base & POINTS_F32_TAG, 0, "buffer addresses are aligned");
        base | if self.points_f32 { POINTS_F32_TAG } else { 0 }
    }

    /// Bytes of `len` packed points.
    fn points_bytes(&self, len: usize) -> usize {
        len * if self.points_f32 { 12 } else { 24 }
    }

    /// The buffer the device writes the results into (`results_address`'s).
    pub(super) fn results_buffer(&self) -> vk::Buffer {
        self.device.as_ref().map_or(&self.results_host, |(_, results)| results).raw()
    }

    pub(super) fn results_address(&self) -> u64 {
        self.device.as_ref().map_or(self.results_host.address(), |(_, results)| results.address())
    }
}

/// Byte offsets of a point slot's outputs: the distances (f64 each) at 0, then the `PointHit`s
/// (full outputs), then (signs) the crossings of each point's ray (`Crossings`, one i32 each),
/// the cap's winding numbers (f64 each) and the unsure points' bits (u32 per 32 points).
#[derive(Clone, Copy)]
pub(super) struct ResultsLayout {
    pub hits: usize,
    pub crossings: usize,
    pub cap_winding: usize,
    pub unsure: usize,
    pub total: usize,
}

/// The sign's trace of a signed distance (`signed.rs`), recorded after each chunk's search: one
/// exact ray from each point (RAYS_FROM_POINTS), its crossings counted (`Query::Parity`, or
/// `Query::Winding` through the cap).
pub(super) struct SignTrace<'a> {
    pub variant: &'a Variant,
    /// The trace's push constants but for the chunk's own: the structures, the cap, the mask.
    pub params: Params,
    /// The rays' direction, in the scene's frame.
    pub direction: [f64; 3],
    /// The cap whose winding numbers are written too (`Query::Winding`), and their pass.
    pub cap: Option<CapPass<'a>>,
    /// The scene's inside grid on the device (`InsideGridBuffer`'s address), or 0: the points
    /// whose cells it decides cast no ray.
    pub grid: u64,
    /// sign_points.comp's pipeline, and the band about 1/2 its winding numbers leave unsure.
    pub combine: vk::Pipeline,
    pub band: f64,
    /// What the chunk answers: signed distances, or `contains`.
    pub answers: SignAnswers,
}

/// What a chunk's sign's trace answers.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum SignAnswers {
    /// The search's distances, negated inside.
    Distances,
    /// `contains`, with no search: a byte a point (1 inside) at the results' start, read back,
    /// or copied into `into` (memory shared with CUDA) at the chunk's first row.
    Inside { into: Option<vk::Buffer> },
}

/// A point query's points: the caller's on the host, or already on the device.
#[derive(Clone, Copy)]
pub(super) enum JobPoints<'a> {
    Host(Vec3s<'a>),
    /// `rows` xyz rows at a device address, f32 (12 bytes a row) or f64 (24), packed.
    Device {
        address: u64,
        f32: bool,
        rows: usize,
    },
}

impl JobPoints<'_> {
    pub(super) fn rows(&self) -> usize {
        match self {
            JobPoints::Host(points) => points.rows(),
            JobPoints::Device { rows, .. } => *rows,
        }
    }
}

/// What the chunks of one query share.
pub(super) struct PointJob<'a> {
    pub(super) points: JobPoints<'a>,
    pub(super) structures: &'a ClosestScene,
    /// Winding numbers' boundaries (winding.comp), or none (closest_point.comp).
    pub(super) boundaries: Option<&'a WindingScene>,
    /// The shader's kernel, and the pipeline specialized from it.
    pub(super) kernel: &'a ComputeKernel,
    pub(super) pipeline: vk::Pipeline,
    pub(super) center: DVec3,
    pub(super) max_distance: f64,
    pub(super) full: bool,
    /// How point_order.comp orders the points, or none: as they come.
    pub(super) grid: Option<OrderGrid>,
    /// The sign's trace after each chunk's search, or none.
    pub(super) sign: Option<SignTrace<'a>>,
}

/// The grid point_order.comp orders a query's points by, and its pipeline.
#[derive(Clone, Copy)]
pub(super) struct OrderGrid {
    /// World.
    corner: [f64; 3],
    /// Cells per unit along each axis.
    scale: [f64; 3],
    pipeline: vk::Pipeline,
}

/// The closest-points path: the point kernels (closest points in f32 or f64, winding numbers,
/// signs, grid order) and their idle staging.
pub struct ClosestPoints {
    shared: Arc<Shared>,
    points: Arc<PointPipelines>,
}

impl ClosestPoints {
    pub fn new(shared: &Arc<Shared>, points: &Arc<PointPipelines>) -> ClosestPoints {
        ClosestPoints { shared: shared.clone(), points: points.clone() }
    }

    /// The point kernels and their idle staging.
    pub(super) fn pipelines(&self) -> &PointPipelines {
        &self.points
    }

    /// The surface point nearest to each point within `max_distance`, on the GPU, its fields
    /// written into `sink`: measured in f64 (`Precision::Exact`, the reference tier's answers) or
    /// in f32 (`Fast`).
    pub fn run(&self, batch: PointBatch, max_distance: f64, precision: Precision, sink: &mut HitSink) -> Result<()> {
        let PointBatch { scene, points, interrupt } = batch;
        let n = points.rows();
        let structures = VulkanScene::of(scene)?.closest(scene)?;
        let full = sink.position.is_some()
            || [Field::Prim, Field::Instance, Field::Custom, Field::Uv, Field::Normal, Field::Geometry]
                .iter()
                .any(|f| sink.field(*f).is_some());
        let job = self.closest_job(scene, &structures, points, max_distance, precision, full)?;
        let mut distances = sink.take(Field::T);
        let capacity = self.point_capacity(n);
        let mut slots = self.shared.with_memory(|| self.points.take_slots(capacity, full, false))?;
        // Each chunk's fields are written from its readback as it finishes (while the next one is
        // searched), straight into the caller's arrays.
        let result = self.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            let results = slot.results_host.mapped().expect("readback is host-visible");
            let found = &results[..8 * len];
            if let Some(out) = distances.as_deref_mut() {
                parallel::copy(&mut out[8 * start..8 * (start + len)], found);
            }
            if full {
                let from = slot.results_layout().hits;
                let records: &[PointHit] = bytemuck::cast_slice(&results[from..from + len * size_of_hit()]);
                let found: &[f64] = bytemuck::cast_slice(found);
                host_tiers::write_closest(scene, &mut sink.rows(start, len, n), |k| {
                    let h = &records[k];
                    (h.instance >= 0).then(|| {
                        let record =
                            ReferenceHit { t: found[k], u: h.u, v: h.v, instance: h.instance as u32, prim: h.prim };
                        (record, DVec3::from_array(h.position))
                    })
                });
            }
        });
        self.points.give_back(slots);
        result?;
        if let Some(out) = distances {
            sink.set(Field::T, out);
        }
        Ok(())
    }

    /// The closest-point search's job over `scene`'s `structures`: measured in f32 at
    /// `Precision::Fast`, else in f64; `full` outputs or distances only; no sign's trace.
    pub(super) fn closest_job<'a>(
        &'a self,
        scene: &Scene,
        structures: &'a ClosestScene,
        points: Vec3s<'a>,
        max_distance: f64,
        precision: Precision,
        full: bool,
    ) -> Result<PointJob<'a>> {
        let f32 = precision == Precision::Fast && f32_measurable(scene, points);
        let shader = if f32 { PointShader::ClosestF32 } else { PointShader::Closest };
        Ok(PointJob {
            points: JobPoints::Host(points),
            structures,
            boundaries: None,
            kernel: self.points.kernel(shader),
            pipeline: self.points.pipeline(shader)?,
            center: scene.center,
            max_distance,
            full,
            grid: self.order_grid(scene)?,
            sign: None,
        })
    }

    /// `contains` by winding number with the GPU's help: each instance's winding number about
    /// each point on the GPU (f64 terms, f32 arctangents), decided on the host: inside at 1/2 or
    /// more; points whose number lies within the GPU's error of 1/2, on the CPU in f64; points
    /// outside, unless on a surface (the CPU's test). The reference tier's answers.
    pub fn contains_by_winding(&self, batch: PointBatch, out: &mut [u8]) -> Result<()> {
        let PointBatch { scene, points, interrupt } = batch;
        let n = points.rows();
        let vulkan = VulkanScene::of(scene)?;
        let structures = vulkan.closest(scene)?;
        let boundaries = vulkan.winding(scene)?;
        let job = PointJob {
            points: JobPoints::Host(points),
            structures: &structures,
            boundaries: Some(&boundaries),
            kernel: self.points.kernel(PointShader::Winding),
            pipeline: self.points.pipeline(PointShader::Winding)?,
            center: scene.center,
            max_distance: 0.0,
            full: false,
            grid: self.order_grid(scene)?,
            sign: None,
        };
        let mut winding = try_vec(n, 0.0f64, "winding numbers")?;
        let capacity = self.point_capacity(n);
        let mut slots = self.shared.with_memory(|| self.points.take_slots(capacity, false, false))?;
        let result = self.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            let results = slot.results_host.mapped().expect("readback is host-visible");
            parallel::copy(bytemuck::cast_slice_mut(&mut winding[start..start + len]), &results[..8 * len]);
        });
        self.points.give_back(slots);
        result?;
        let most = scene.placements.iter().map(|p| p.triangles.faces.len()).max().unwrap_or(0);
        host_tiers::inside_by_winding(
            scene,
            points,
            &winding,
            WINDING_TERM_ERROR * most as f64 + WINDING_MARGIN,
            out,
            interrupt,
        )
    }

    /// Points per chunk for a query of `n` points.
    pub(super) fn point_capacity(&self, n: usize) -> usize {
        let most = if self.shared.ctx.info.is_software { CHUNK_POINTS } else { LEAN_CHUNK_POINTS };
        let most = chunk_points_asked().unwrap_or(most);
        most.min(self.points.kernels[0].max_invocations()).min(n).max(1)
    }

    /// Runs every chunk of `job` through the two `slots`, handing each finished one to `unpack`
    /// (its first point, its length, its slot); where the time went goes to `last_profile`.
    pub(super) fn closest_chunks(
        &self,
        job: &PointJob,
        slots: &mut [PointSlot; 2],
        capacity: usize,
        interrupt: &dyn Interrupt,
        mut unpack: impl FnMut(usize, usize, &PointSlot),
    ) -> Result<()> {
        let n = job.points.rows();
        let started = Instant::now();
        let mut profile = TraceProfile { rays: n, ..Default::default() };
        let mut clock = Instant::now();
        let mut lap = |into: &mut f64| {
            let now = Instant::now();
            *into += (now - clock).as_secs_f64();
            clock = now;
        };
        // Dropping these on an error waits for the chunks in flight before their memory goes.
        let mut commands = [Commands::new(&self.shared.ctx)?, Commands::new(&self.shared.ctx)?];
        let mut in_flight: [Option<(usize, usize)>; 2] = [None, None];
        let mut finished = 0;
        let mut finish = |slot: &PointSlot, (start, len): (usize, usize), profile: &mut TraceProfile| -> Result<()> {
            if let Some(stamps) = &slot.stamps {
                stamps.add_to(profile)?;
            }
            unpack(start, len, slot);
            finished += len;
            interrupt.progress(finished, n);
            Ok(())
        };
        let mut pacer = ChunkPacer::on_device(capacity, self.shared.ctx.info.is_software);
        let (mut chunk, mut start) = (0, 0);
        while start < n {
            interrupt.check()?;
            let s = chunk % 2;
            lap(&mut profile.submit);
            commands[s].wait()?;
            lap(&mut profile.wait);
            if let Some(done) = in_flight[s].take() {
                pacer.finished(done.1);
                finish(&slots[s], done, &mut profile)?;
            }
            let len = pacer.next_len(n - start);
            lap(&mut profile.unpack);
            match job.points {
                JobPoints::Host(points) => pack_points(points, start, len, &mut slots[s]),
                JobPoints::Device { address, f32, .. } => {
                    let row = if f32 { 12 } else { 24 };
                    let tag = if f32 { POINTS_F32_TAG } else { 0 };
                    slots[s].points_on_device = Some((address + (row * start) as u64) | tag);
                }
            }
            lap(&mut profile.pack);
            profile.chunks += 1;
            commands[s].begin()?;
            self.record_points(commands[s].buffer, job, &slots[s], start, len);
            commands[s].submit()?;
            pacer.started();
            in_flight[s] = Some((start, len));
            (chunk, start) = (chunk + 1, start + len);
        }
        lap(&mut profile.submit);
        for s in 0..2 {
            commands[s].wait()?;
            lap(&mut profile.wait);
            if let Some(done) = in_flight[s].take() {
                finish(&slots[s], done, &mut profile)?;
            }
            lap(&mut profile.unpack);
        }
        profile.total = started.elapsed().as_secs_f64();
        self.shared.keep_profile(profile);
        Ok(())
    }

    /// Records one chunk (its first point `start`): its upload (discrete GPUs, host points), the
    /// search (but for `contains`), the sign's trace, its readback.
    fn record_points(&self, cmd: vk::CommandBuffer, job: &PointJob, slot: &PointSlot, start: usize, len: usize) {
        let ctx = &self.shared.ctx;
        let device = &ctx.device;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        let stamp = start_stamps(slot.stamps.as_ref(), cmd);
        let answers = job.sign.as_ref().map_or(SignAnswers::Distances, |sign| sign.answers);
        if let (Some((points_device, _)), None) = (&slot.device, slot.points_on_device) {
            let region = [vk::BufferCopy::default().size(slot.points_bytes(len) as u64)];
            // SAFETY: `cmd` is recording; both buffers hold `capacity` points.
            unsafe { device.cmd_copy_buffer(cmd, slot.points_host.raw(), points_device.raw(), &region) };
            memory_barrier(
                ctx,
                cmd,
                (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
                (compute, vk::AccessFlags::SHADER_READ),
            );
        }
        let order = match job.grid {
            Some(grid) if len >= ORDER_MIN_POINTS => {
                self.record_order(cmd, slot, len, grid);
                slot.order.address()
            }
            _ => 0,
        };
        stamp(Stamp::Uploaded);
        let [nodes, triangles, instances, top_nodes, top_items] = job.structures.addresses();
        let [spans, edges] = job.boundaries.map_or([0, 0], WindingScene::addresses);
        let results = slot.results_address();
        let params = PointParams {
            points: slot.points_address(),
            distances: results,
            hits: if job.full { results + slot.results_layout().hits as u64 } else { 0 },
            nodes,
            triangles,
            instances,
            top_nodes,
            top_items,
            spans,
            edges,
            order,
            center: job.center.to_array(),
            max_distance: job.max_distance,
            count: len as u32,
            instance_count: job.structures.instance_count,
        };
        // `contains` searches nothing: its sign's trace answers.
        if answers == SignAnswers::Distances {
            // SAFETY: `cmd` is recording; the pipeline and its layout are live; the push constants
            // cover exactly the layout's range; the group count is within
            // maxComputeWorkGroupCount (the chunk's capacity is).
            unsafe {
                device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, job.pipeline);
                device.cmd_push_constants(
                    cmd,
                    job.kernel.layout(),
                    vk::ShaderStageFlags::COMPUTE,
                    0,
                    bytemuck::bytes_of(&params),
                );
                device.cmd_dispatch(cmd, (len as u32).div_ceil(job.kernel.local_size), 1, 1);
            }
        }
        // The stages whose writes the readback waits for: the search's, and the sign's trace's.
        let written = match &job.sign {
            Some(sign) => compute | self.record_sign_trace(cmd, sign, slot, job.center, order, len),
            None => compute,
        };
        stamp(Stamp::Traced);
        let host = (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ);
        let into = match answers {
            SignAnswers::Inside { into } => into,
            SignAnswers::Distances => None,
        };
        if slot.device.is_none() && into.is_none() {
            memory_barrier(ctx, cmd, (written, vk::AccessFlags::SHADER_WRITE), host);
            stamp(Stamp::ReadBack);
            return;
        }
        memory_barrier(
            ctx,
            cmd,
            (written, vk::AccessFlags::SHADER_WRITE),
            (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_READ),
        );
        if let Some(into) = into {
            let region = [vk::BufferCopy::default().dst_offset(start as u64).size(len as u64)];
            // SAFETY: `cmd` is recording; the results hold the chunk's `len` answers at 0 and
            // `into` (TRANSFER_DST) the query's, this chunk's at `start`.
            unsafe { device.cmd_copy_buffer(cmd, slot.results_buffer(), into, &region) };
        }
        let Some((_, results_device)) = &slot.device else {
            let written = (written | vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::MEMORY_WRITE);
            memory_barrier(ctx, cmd, written, host);
            stamp(Stamp::ReadBack);
            return;
        };
        let layout = slot.results_layout();
        let region = |at: usize, bytes: usize| {
            vk::BufferCopy::default().src_offset(at as u64).dst_offset(at as u64).size((len * bytes) as u64)
        };
        let mut regions = match answers {
            SignAnswers::Distances => vec![region(0, 8)],
            SignAnswers::Inside { into: None } => vec![region(0, 1)],
            SignAnswers::Inside { into: Some(_) } => Vec::new(),
        };
        if job.full {
            regions.push(region(layout.hits, size_of_hit()));
        }
        if job.sign.is_some() {
            regions.push(region(layout.unsure, 0).size(4 * len.div_ceil(32) as u64));
        }
        // SAFETY: `cmd` is recording; both buffers share one layout and hold `capacity` points.
        unsafe { device.cmd_copy_buffer(cmd, results_device.raw(), slot.results_host.raw(), &regions) };
        memory_barrier(ctx, cmd, (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE), host);
        stamp(Stamp::ReadBack);
    }
    /// Records the sign's trace of a chunk after its search: the chunk's `PointRays` record,
    /// then one ray from each of its `len` points, in the search's `order` (its address, or 0:
    /// as they come), then sign_points.comp over the chunk. Returns the stage whose writes the
    /// readback waits for.
    pub(super) fn record_sign_trace(
        &self,
        cmd: vk::CommandBuffer,
        sign: &SignTrace,
        slot: &PointSlot,
        center: DVec3,
        order: u64,
        len: usize,
    ) -> vk::PipelineStageFlags {
        let ctx = &self.shared.ctx;
        let stage = match ctx.backend {
            Backend::RayQuery => vk::PipelineStageFlags::COMPUTE_SHADER,
            Backend::Pipeline => vk::PipelineStageFlags::RAY_TRACING_SHADER_KHR,
        };
        let record_buffer = slot.rays_record().expect("a slot for signs has a rays record");
        let layout = slot.results_layout();
        let results = slot.results_address();
        // SAFETY: `cmd` is recording outside a render pass; the results buffer is TRANSFER_DST
        // and holds the unsure bits' words at this 4-aligned offset (ResultsLayout).
        unsafe {
            ctx.device.cmd_fill_buffer(cmd, slot.results_buffer(), layout.unsure as u64, 4 * len.div_ceil(32) as u64, 0)
        };
        let record = PointRays {
            points: slot.points_address(),
            order,
            shift: center.to_array(),
            direction: sign.direction,
            tmin: 0.0,
            tmax: f64::INFINITY,
            grid: sign.grid,
        };
        // SAFETY: `cmd` is recording outside a render pass; the buffer is TRANSFER_DST, holds one
        // record, and the record is a multiple of 4 bytes and at most 65,536.
        unsafe { ctx.device.cmd_update_buffer(cmd, record_buffer.raw(), 0, bytemuck::bytes_of(&record)) };
        // The record (and, on discrete GPUs, the points' upload; and the order) before the rays
        // read them.
        memory_barrier(
            ctx,
            cmd,
            (
                vk::PipelineStageFlags::TRANSFER | vk::PipelineStageFlags::COMPUTE_SHADER,
                vk::AccessFlags::TRANSFER_WRITE | vk::AccessFlags::SHADER_WRITE,
            ),
            (stage, vk::AccessFlags::SHADER_READ),
        );
        let mut params = Params { rays: record_buffer.address(), count: len as u32, ..sign.params };
        params.outputs[Field::Prim as usize] = results + layout.crossings as u64;
        if sign.cap.is_some() {
            params.outputs[Field::T as usize] = results + layout.cap_winding as u64;
        }
        self.shared.record_trace(cmd, sign.variant, &params, len);
        if let Some(cap) = sign.cap {
            // The rays' origins are the chunk's points, as the trace read them (RAYS_FROM_POINTS).
            let chunk = CapChunk {
                origins: record.points,
                shift: center,
                counts: params.outputs[Field::Prim as usize],
                winding: params.outputs[Field::T as usize],
                len,
            };
            cap.record(ctx, cmd, &chunk, stage);
        }
        self.record_sign_points(cmd, sign, slot, stage, len);
        vk::PipelineStageFlags::COMPUTE_SHADER
    }

    /// Records sign_points.comp over a chunk whose distances and crossings were written (by
    /// `stage`'s shaders, and its unsure bits cleared by a copy).
    fn record_sign_points(
        &self,
        cmd: vk::CommandBuffer,
        sign: &SignTrace,
        slot: &PointSlot,
        stage: vk::PipelineStageFlags,
        len: usize,
    ) {
        let ctx = &self.shared.ctx;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(
            ctx,
            cmd,
            (
                compute | stage | vk::PipelineStageFlags::TRANSFER,
                vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE,
            ),
            (compute, vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE),
        );
        let layout = slot.results_layout();
        let results = slot.results_address();
        let inside = matches!(sign.answers, SignAnswers::Inside { .. });
        let params = SignPointsParams {
            distances: results,
            crossings: results + layout.crossings as u64,
            cap_winding: if sign.cap.is_some() { results + layout.cap_winding as u64 } else { 0 },
            unsure: results + layout.unsure as u64,
            // As host_tiers::mark_by_crossings computes them.
            inside_from: 0.5 + sign.band,
            outside_below: 0.5 - sign.band,
            points: slot.points_address(),
            // The answers' bytes over the distances' place (no search ran).
            inside: if inside { results } else { 0 },
            count: len as u32,
            unused: 0,
        };
        // `contains`: four points an invocation.
        let invocations = if inside { len.div_ceil(4) } else { len };
        let kernel = &self.points.sign;
        // SAFETY: `cmd` is recording; the pipeline and its layout are live; the push constants
        // cover exactly the layout's range; the group count is within maxComputeWorkGroupCount
        // (the chunk's capacity is, `point_capacity`).
        unsafe {
            ctx.device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, sign.combine);
            ctx.device.cmd_push_constants(
                cmd,
                kernel.layout(),
                vk::ShaderStageFlags::COMPUTE,
                0,
                bytemuck::bytes_of(&params),
            );
            ctx.device.cmd_dispatch(cmd, (invocations as u32).div_ceil(kernel.local_size), 1, 1);
        }
    }
}

impl ClosestPoints {
    /// Records point_order.comp's three passes over a chunk's points (already on the device):
    /// the slot's `order` then lists them cell by cell along a Morton curve over `grid`.
    fn record_order(&self, cmd: vk::CommandBuffer, slot: &PointSlot, len: usize, grid: OrderGrid) {
        let ctx = &self.shared.ctx;
        let kernel = &self.points.order;
        let OrderGrid { corner, scale, pipeline } = grid;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        let read_write = vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE;
        // SAFETY: `cmd` is recording; the cells buffer is the slot's, TRANSFER_DST, 4-aligned.
        unsafe { ctx.device.cmd_fill_buffer(cmd, slot.cells.raw(), 0, vk::WHOLE_SIZE, 0) };
        memory_barrier(
            ctx,
            cmd,
            (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
            (compute, read_write),
        );
        let points_address = slot.points_address();
        let pass = |pass: u32, groups: u32| {
            let params = PointOrderParams {
                points: points_address,
                cells: slot.cells.address(),
                order: slot.order.address(),
                corner,
                scale,
                count: len as u32,
                pass,
            };
            // SAFETY: `cmd` is recording; the pipeline and its layout are live; the push
            // constants cover exactly the layout's range; `groups` is within
            // maxComputeWorkGroupCount (the chunk's capacity is).
            unsafe {
                ctx.device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, pipeline);
                ctx.device.cmd_push_constants(
                    cmd,
                    kernel.layout(),
                    vk::ShaderStageFlags::COMPUTE,
                    0,
                    bytemuck::bytes_of(&params),
                );
                ctx.device.cmd_dispatch(cmd, groups, 1, 1);
            }
            memory_barrier(ctx, cmd, (compute, vk::AccessFlags::SHADER_WRITE), (compute, read_write));
        };
        let groups = (len as u32).div_ceil(kernel.local_size);
        pass(POINT_ORDER_COUNT, groups);
        pass(POINT_ORDER_SCAN, order_blocks(kernel.local_size));
        pass(POINT_ORDER_SCAN_BLOCKS, 1);
        pass(POINT_ORDER_SCATTER, groups);
    }

    /// The grid point_order.comp sorts a scene's points by: its bounds (world), ORDER_GRID cells
    /// a side; none for an empty scene, or where VKRAY_POINT_ORDER=input asks to search points as
    /// they come (to measure what the order buys).
    pub(super) fn order_grid(&self, scene: &Scene) -> Result<Option<OrderGrid>> {
        if points_as_they_come() {
            return Ok(None);
        }
        let bounds = scene.bounds();
        let extent = bounds.extent();
        if !(bounds.min.is_finite() && extent.is_finite()) {
            return Ok(None);
        }
        let scale = DVec3::select(extent.cmpgt(DVec3::ZERO), ORDER_GRID as f64 / extent, DVec3::ZERO);
        Ok(Some(OrderGrid {
            corner: (bounds.min + scene.center).to_array(),
            scale: scale.to_array(),
            pipeline: self.points.order.pipeline(&[ORDER_GRID])?,
        }))
    }
}

/// Blocks of cells point_order.comp's POINT_ORDER_SCAN scans, a workgroup of `local_size` each
/// (its BLOCK: 16 cells a thread).
fn order_blocks(local_size: u32) -> u32 {
    ORDER_GRID.pow(3).div_ceil(16 * local_size)
}

fn size_of_hit() -> usize {
    std::mem::size_of::<PointHit>()
}

/// Points `start..start + len` into the slot's staging as they are (f32 or f64 xyz), on all
/// cores.
fn pack_points(points: Vec3s, start: usize, len: usize, slot: &mut PointSlot) {
    // The slot's own points now, whatever a query of points on the device left in it.
    slot.points_on_device = None;
    slot.points_f32 = matches!(points, Vec3s::F32(_));
    let bytes = slot.points_bytes(len);
    let staging = slot.points_host.mapped_mut().expect("point staging is host-visible");
    let values: &[u8] = match points {
        Vec3s::F64(values) => bytemuck::cast_slice(&values[3 * start..3 * (start + len)]),
        Vec3s::F32(values) => bytemuck::cast_slice(&values[3 * start..3 * (start + len)]),
    };
    parallel::copy(&mut staging[..bytes], values);
}

/// VKRAY_POINT_CHUNK: points per chunk asked for (to measure what the chunks' size buys).
fn chunk_points_asked() -> Option<usize> {
    std::env::var("VKRAY_POINT_CHUNK").ok()?.parse().ok().filter(|&n| n > 0)
}

/// Whether VKRAY_POINT_ORDER=input asks for points searched (and their rays cast) as they come,
/// to measure what the order buys.
pub(super) fn points_as_they_come() -> bool {
    std::env::var("VKRAY_POINT_ORDER").is_ok_and(|v| v == "input")
}

/// Whether VKRAY_POINT_ORDER=grid asks for points' rays cast in grid order even on a hardware
/// GPU (where by default they are not: the host's sort costs more than the trace gains).
pub(super) fn points_in_grid_order() -> bool {
    std::env::var("VKRAY_POINT_ORDER").is_ok_and(|v| v == "grid")
}

/// Whether the fast tier's f32 kernel can measure these points against `scene`: every coordinate,
/// the points' and the scene's bounds', relative to the scene's centre, within 2^±30 (the f32
/// kernel's products of four lengths overflow beyond, and underflow below). Elsewhere the f64
/// kernel measures them (its answers are then rounded to f32 as the fast tier's are).
fn f32_measurable(scene: &Scene, points: Vec3s) -> bool {
    const HIGH: f64 = 1_073_741_824.0; // 2^30
    const LOW: f64 = 9.313_225_746_154_785e-10; // 2^-30
    let center = scene.center.to_array();
    let bounds = scene.bounds();
    let scene_extent =
        (0..3).map(|k| (bounds.min[k] - center[k]).abs().max((bounds.max[k] - center[k]).abs())).fold(0.0, f64::max);
    let point_extent = match points {
        Vec3s::F32(v) => parallel::install(|| {
            v.par_chunks(3)
                .map(|p| (0..3).map(|k| (p[k] as f64 - center[k]).abs()).fold(0.0, f64::max))
                .reduce(|| 0.0, f64::max)
        }),
        Vec3s::F64(v) => parallel::install(|| {
            v.par_chunks(3)
                .map(|p| (0..3).map(|k| (p[k] - center[k]).abs()).fold(0.0, f64::max))
                .reduce(|| 0.0, f64::max)
        }),
    };
    let extent = scene_extent.max(point_extent);
    (LOW..=HIGH).contains(&extent)
}

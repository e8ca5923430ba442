//! Rays that live in CUDA memory (torch, cupy, jax through DLPack) and hits that stay there: the
//! caller's arrays are copied device to device on vkray's CUDA stream into memory Vulkan shares
//! with CUDA, the GPU packs and traces them (`device_rays`), and the hits are copied into fresh
//! CUDA allocations. A timeline semaphore orders Vulkan's work between the two copies; the host
//! waits only for Vulkan's part (to report an invalid ray as the numpy path does).

use std::sync::{Arc, Mutex, OnceLock};

use super::packed_rays::{DeviceArray, DeviceBound, DeviceOutputs, DeviceQuery, DeviceRays, Ordering, PackedRays};
use super::shared::Shared;
use crate::error::{invalid_value, Error, Result};
use crate::geometry::align::align_up;
use crate::geometry::interrupt::Interrupt;
use crate::gpu::context::Timeline;
use crate::gpu::cuda::{Cuda, CudaAllocation, Event, SharedBuffer, SharedSemaphore, Stream};
use crate::scene::Scene;
use crate::trace::hit_fields::{Field, FIELD_COUNT};
use crate::trace::idle::{Held, Idle, IdleMemory, IdlePool};
use crate::trace::request::Request;
use ash::vk;

/// One of the caller's CUDA arrays: `rows` rows of `columns` numbers (f32, or f64 where `wide`),
/// with byte strides between rows and between a row's numbers (a stride of 0 repeats one row).
#[derive(Clone, Copy, Debug)]
pub struct CudaArray {
    pub pointer: u64,
    pub rows: usize,
    pub columns: usize,
    pub wide: bool,
    pub row_stride: usize,
    pub column_stride: usize,
}

impl CudaArray {
    fn element_bytes(&self) -> usize {
        if self.wide {
            8
        } else {
            4
        }
    }

    /// Bytes of the array once copied tightly packed.
    fn packed_bytes(&self) -> usize {
        self.rows * self.packed_row_bytes()
    }

    /// Bytes of one row once copied tightly packed.
    fn packed_row_bytes(&self) -> usize {
        self.columns * self.element_bytes()
    }

    /// The part of this array rays `start..stop` of `count` read: those rows, or its one row
    /// (shared by every ray) for the first chunk only; None where nothing is left to copy.
    fn rows_of_chunk(&self, start: usize, stop: usize, count: usize) -> Option<CudaArray> {
        if self.rows != count || self.rows == 1 {
            return (start == 0).then_some(*self);
        }
        Some(CudaArray { pointer: self.pointer + (start * self.row_stride) as u64, rows: stop - start, ..*self })
    }
}

/// A bound of the caller's rays' intervals: one for all, or a CUDA array.
#[derive(Clone, Copy, Debug)]
pub enum CudaBound {
    All(f64),
    Each(CudaArray),
}

/// The caller's rays in CUDA memory.
#[derive(Clone, Copy, Debug)]
pub struct CudaRays {
    pub count: usize,
    pub origins: CudaArray,
    pub directions: CudaArray,
    pub tmin: CudaBound,
    pub tmax: CudaBound,
    pub mask: u8,
}

/// A query's hits in CUDA memory: one allocation per requested field, written once `ready` is
/// reached (streams that read them wait for it).
pub struct CudaHits {
    pub fields: Vec<(Field, CudaAllocation)>,
    pub ready: Arc<Event>,
    /// `t` and `uv` are f64 (the exact tier's).
    pub wide: bool,
}

/// What one GPU-resident query at a time uses: vkray's CUDA stream, the semaphore that orders
/// Vulkan's work on it, and the shared memory the rays and hits pass through (grown as needed).
pub struct CudaLease {
    pub stream: Stream,
    semaphore: SharedSemaphore,
    /// The semaphore's last value.
    value: u64,
    input: Option<SharedBuffer>,
    output: Option<SharedBuffer>,
}

impl Held for CudaLease {
    fn bytes(&self) -> u64 {
        [&self.input, &self.output].iter().filter_map(|b| b.as_ref()).map(|b| b.vulkan.size()).sum()
    }
}

impl CudaLease {
    /// The stream's handle, for DLPack's `__dlpack__(stream=...)`: the caller's producer orders
    /// its pending writes before this stream's work.
    pub fn stream_handle(&self) -> usize {
        self.stream.raw as usize
    }

    /// Makes the shared output at least `bytes` (a larger one replaces it once the stream's
    /// copies out of it are done).
    pub fn grow_output(&mut self, shared: &Shared, cuda: &Arc<Cuda>, bytes: u64) -> Result<()> {
        let stream = &self.stream;
        shared.with_memory(|| grow(&shared.ctx, cuda, stream, &mut self.output, bytes, "hits shared with CUDA"))
    }

    /// The shared output (`grow_output` made it).
    pub fn output(&self) -> &SharedBuffer {
        self.output.as_ref().expect("grown before use")
    }

    /// The semaphore's next value, taken.
    pub fn next_value(&mut self) -> u64 {
        self.value += 1;
        self.value
    }

    /// The Vulkan side of the semaphore that orders the lease's work.
    pub fn vulkan_semaphore(&self) -> vk::Semaphore {
        self.semaphore.vulkan.semaphore
    }

    /// Makes the stream wait until the semaphore reaches `value` (Vulkan's work done).
    pub fn wait_on_stream(&self, value: u64) -> Result<()> {
        self.semaphore.wait(&self.stream, value)
    }

    /// Signals the semaphore at `value` once the stream's work queued so far is done.
    pub fn signal_on_stream(&self, value: u64) -> Result<()> {
        self.semaphore.signal(&self.stream, value)
    }
}

impl Drop for CudaLease {
    fn drop(&mut self) {
        // Its stream's queued waits and copies use the semaphore and the shared buffers, which
        // go with it.
        let _ = self.stream.synchronize();
    }
}

/// The CUDA side of a tracer: its device (looked up once) and idle leases.
pub struct CudaState {
    cuda: OnceLock<Option<Arc<Cuda>>>,
    idle: IdlePool<CudaLease>,
}

/// Idle leases kept: as many as queries used at once, at least four, at most eight.
const IDLE_LEASES: (usize, usize) = (4, 8);

impl Idle for CudaState {
    fn memory(&self) -> IdleMemory {
        self.idle.memory()
    }

    /// Drops the idle leases (each waits for its stream's work).
    fn clear(&self) {
        self.idle.clear();
    }
}

impl Default for CudaState {
    fn default() -> CudaState {
        CudaState { cuda: OnceLock::new(), idle: IdlePool::new(IDLE_LEASES.0, IDLE_LEASES.1) }
    }
}

/// Alignment of each array within the shared buffers.
const SHARED_ALIGN: u64 = 256;

/// The CUDA rays path: rays and hits in memory shared with CUDA, packed and traced by the
/// GPU-packed rays path, ordered against the caller's CUDA streams. Owns the CUDA device and its
/// idle leases.
pub struct CudaRaysPath {
    shared: Arc<Shared>,
    packed: Arc<PackedRays>,
    cuda: Arc<CudaState>,
}

impl CudaRaysPath {
    pub fn new(shared: &Arc<Shared>, packed: &Arc<PackedRays>, cuda: &Arc<CudaState>) -> CudaRaysPath {
        CudaRaysPath { shared: shared.clone(), packed: packed.clone(), cuda: cuda.clone() }
    }

    /// The CUDA device that is this Vulkan device, where there is one (an NVIDIA GPU with the
    /// CUDA driver, and Vulkan able to share memory and semaphores with it).
    pub fn cuda(&self) -> Result<Option<Arc<Cuda>>> {
        if let Some(found) = self.cuda.cuda.get() {
            return Ok(found.clone());
        }
        let found = if self.shared.ctx.interop.export_fd && self.packed.packs_rays() {
            Cuda::open(self.shared.ctx.interop.device_uuid)?
        } else {
            None
        };
        Ok(self.cuda.cuda.get_or_init(|| found).clone())
    }

    /// The CUDA device, where it was opened already (`cuda` opens it): nothing is started.
    pub fn opened_cuda(&self) -> Option<Arc<Cuda>> {
        self.cuda.cuda.get().cloned().flatten()
    }

    /// A lease for one GPU-resident query: an idle one, or a new one.
    pub fn cuda_lease(&self) -> Result<CudaLease> {
        if let Some(lease) = self.cuda.idle.take(1, |_| true, |_| true).pop() {
            return Ok(lease);
        }
        self.shared.with_memory(|| self.new_lease()).inspect_err(|_| self.cuda.idle.give_back(1, []))
    }

    fn new_lease(&self) -> Result<CudaLease> {
        let Some(cuda) = self.cuda()? else {
            return Err(Error::Unsupported(format!(
                "{} cannot share memory with CUDA (it is not an NVIDIA GPU with the CUDA driver and Vulkan's \
                 external memory and semaphore extensions)",
                self.shared.ctx.info.name
            )));
        };
        let semaphore = SharedSemaphore::new(&self.shared.ctx, &cuda)?;
        Ok(CudaLease { stream: Stream::new(&cuda)?, semaphore, value: 0, input: None, output: None })
    }

    /// Returns a lease for the next query (its stream's work may still be running: the next
    /// query queues after it on the same stream).
    /// A lease beyond those kept is dropped, which waits for its stream's work, with no lock held.
    pub fn give_back_lease(&self, lease: CudaLease) {
        self.cuda.idle.give_back(1, [lease]);
    }

    /// Traces `rays` (CUDA memory, ordered before `lease`'s stream by the caller's producer)
    /// against `scene` in the fast tier, writing the `fields` asked into new CUDA allocations.
    /// Errors name the first invalid ray as the numpy path does (its values read back).
    pub fn trace_cuda_rays(
        &self,
        scene: &Scene,
        lease: &mut CudaLease,
        rays: &CudaRays,
        request: Request,
        fields: &[Field],
        interrupt: &dyn Interrupt,
    ) -> Result<CudaHits> {
        let cuda = self.cuda()?.expect("a lease implies CUDA");
        let places = CudaPlaces { home: &cuda, after: None, into: None };
        self.trace_cuda_placed(scene, lease, rays, &places, request, fields, interrupt)
    }

    /// Traces rows `start..stop` of `batch` (rays on `batch.home`, maybe another GPU) on this
    /// device, writing their hits into the batch's rows; returns once Vulkan's part is done, with
    /// the copies of the hits queued (`batch.finish` orders the batch's readers after them).
    pub fn trace_cuda_piece(
        &self,
        scene: &Scene,
        lease: &mut CudaLease,
        batch: &CudaBatch,
        (start, stop): (usize, usize),
        request: Request,
        interrupt: &dyn Interrupt,
    ) -> Result<()> {
        if start >= stop || stop > batch.rays.count {
            return Err(invalid_value(format!("rows {start}..{stop} are not a piece of {} rays", batch.rays.count)));
        }
        let cuda = self.cuda()?.expect("a lease implies CUDA");
        cuda.reach(&batch.home)?;
        batch.home.share_with(&cuda)?;
        let rays = batch.rays.rows(start, stop);
        let into = batch.rows_at(start)?; // counts the piece in flight until `written`
        let places = CudaPlaces { home: &batch.home, after: Some(&batch.start), into: Some(&into) };
        let traced = self.trace_cuda_placed(scene, lease, &rays, &places, request, &batch.fields, interrupt);
        batch.written(traced.as_ref().ok().map(|hits| hits.ready.clone()));
        traced.map(|_| ())
    }

    /// The GPU-resident path: the rays copied from `places.home` into memory this device shares
    /// with CUDA, packed and traced by Vulkan, the hits copied to `places.into` (or into new
    /// allocations); the host waits for Vulkan's part only.
    #[allow(clippy::too_many_arguments)]
    fn trace_cuda_placed(
        &self,
        scene: &Scene,
        lease: &mut CudaLease,
        rays: &CudaRays,
        places: &CudaPlaces,
        request: Request,
        fields: &[Field],
        interrupt: &dyn Interrupt,
    ) -> Result<CudaHits> {
        if let Some(why) = super::packed_rays::device_rays_refusal(request) {
            return Err(invalid_value(why));
        }
        let cuda = self.cuda()?.expect("a lease implies CUDA");
        // The exact tier's t and uv are f64.
        let wide = request.precision.is_f64();
        let output_bytes = layout_bytes(fields.iter().map(|f| rays.count * f.bytes_per_ray(wide)));
        lease.grow_output(&self.shared, &cuda, output_bytes)?;
        let chunk_rays = self.packed.device_chunk_capacity(rays.count);
        let (device_rays, wait) = self.copy_rays_in(&cuda, lease, rays, places, chunk_rays)?;
        let signal = lease.next_value();
        let _current = cuda.enter()?;
        let output = lease.output.as_ref().expect("grown");
        let mut outputs: DeviceOutputs = [0; FIELD_COUNT];
        let mut offsets = Vec::new();
        let mut at = 0u64;
        for field in fields {
            outputs[*field as usize] = output.vulkan.address() + at;
            offsets.push(at);
            at = align_up(at + (rays.count * field.bytes_per_ray(wide)) as u64, SHARED_ALIGN);
        }
        let mut hits = Vec::new();
        let (stream, semaphore) = (&lease.stream, &lease.semaphore);
        // Right after Vulkan's submission: the stream waits for its hits and copies them out.
        let mut after_submit = || -> Result<()> {
            semaphore.wait(stream, signal)?;
            for (k, (field, offset)) in fields.iter().zip(&offsets).enumerate() {
                let bytes = rays.count * field.bytes_per_ray(wide);
                let src = (&*cuda, output.pointer + offset, bytes);
                if let Some(into) = places.into {
                    // SAFETY: `into[k]` has room for this piece's rows of the field in the home
                    // device's memory (`CudaBatch::rows_at`), which outlives the copy (the batch
                    // waits for it before it lets the memory go); the shared buffer stays in the
                    // lease, whose later users queue on the same stream.
                    unsafe { stream.copy_2d_between((places.home, into[k], bytes), src, bytes, 1)? };
                    continue;
                }
                let allocation = self.shared.with_memory(|| CudaAllocation::new(stream, bytes))?;
                // SAFETY: both are device memory of this context, live until the copy runs (the
                // allocation is the caller's from now on, the shared buffer stays in the lease,
                // whose later users queue on the same stream).
                unsafe { stream.copy_2d(allocation.pointer, bytes, output.pointer + offset, bytes, bytes, 1)? };
                hits.push((*field, allocation));
            }
            Ok(())
        };
        let timeline = Timeline { semaphore: semaphore.vulkan.semaphore, wait, signal: Some(signal) };
        let order = Ordering { timeline, after_submit: &mut after_submit, chunk_rays: Some(chunk_rays) };
        let query = DeviceQuery { scene, rays: &device_rays, request, outputs: &outputs };
        let traced = self.packed.trace_device_rays(query, Some(order), interrupt);
        let failure = match traced {
            Ok(None) => None,
            Ok(Some(row)) => Some(invalid_ray(places.home, rays, row)),
            Err(e) => Some(e),
        };
        if let Some(error) = failure {
            // The copies out may be queued: they finish before their allocations are freed.
            let _ = lease.stream.synchronize();
            drop(hits);
            return Err(error);
        }
        let ready = Arc::new(lease.stream.record()?);
        Ok(CudaHits { fields: hits, ready, wide })
    }
}

impl CudaRaysPath {
    /// Queues the copy of `rays` (CUDA memory of `places.home`) into the lease's shared input,
    /// tightly packed (each array in one place), in the lease stream's order (after
    /// `places.after`), in chunks of `chunk_rays`: chunk k signals the lease's semaphore at
    /// `wait + k`, so that tracing one chunk overlaps copying the next (over NVLink from another
    /// GPU). Returns the rays as the GPU reads them there, and `wait`; the lease's value is then
    /// the last chunk's.
    pub fn copy_rays_in(
        &self,
        cuda: &Arc<Cuda>,
        lease: &mut CudaLease,
        rays: &CudaRays,
        places: &CudaPlaces,
        chunk_rays: usize,
    ) -> Result<(DeviceRays, u64)> {
        let arrays = arrays_of(rays);
        let input_bytes = layout_bytes(arrays.iter().map(|a| a.packed_bytes()));
        let stream = &lease.stream;
        self.shared.with_memory(|| {
            grow(&self.shared.ctx, cuda, stream, &mut lease.input, input_bytes, "rays shared with CUDA")
        })?;
        let input = lease.input.as_ref().expect("grown");
        let _current = cuda.enter()?;
        let chunks = rays.count.div_ceil(chunk_rays.max(1)).max(1) as u64;
        let wait = lease.value + 1;
        lease.value += chunks;
        let mut placed = Vec::new();
        let mut at = 0u64;
        for array in &arrays {
            placed.push(at);
            at = align_up(at + array.packed_bytes() as u64, SHARED_ALIGN);
        }
        let copied = (|| -> Result<()> {
            if let Some(event) = places.after {
                lease.stream.wait_for(event)?;
            }
            for k in 0..chunks {
                let start = k as usize * chunk_rays;
                let stop = (start + chunk_rays).min(rays.count);
                for (array, at) in arrays.iter().zip(&placed) {
                    let Some(rows) = array.rows_of_chunk(start, stop, rays.count) else { continue };
                    let dst = input.pointer + at + (start.min(array.rows - 1) * array.packed_row_bytes()) as u64;
                    copy_packed(&lease.stream, (cuda, dst), (places.home, &rows))?;
                }
                lease.semaphore.signal(&lease.stream, wait + k)?;
            }
            Ok(())
        })();
        if let Err(error) = copied {
            // Copies already queued read the caller's memory: done before the caller lets it go.
            let _ = lease.stream.synchronize();
            return Err(error);
        }
        Ok((device_rays_in(rays, input.vulkan.address(), &placed), wait))
    }
}

impl CudaRaysPath {
    /// Copies `points` (CUDA memory of this device, ordered before the lease's stream by the
    /// caller's producer) into the lease's shared input, packed (12 or 24 bytes a row), and waits
    /// for the copy. Returns their address as Vulkan reads them.
    pub fn copy_points_in(&self, cuda: &Arc<Cuda>, lease: &mut CudaLease, points: &CudaArray) -> Result<u64> {
        let stream = &lease.stream;
        let bytes = points.packed_bytes() as u64;
        self.shared
            .with_memory(|| grow(&self.shared.ctx, cuda, stream, &mut lease.input, bytes, "points shared with CUDA"))?;
        let input = lease.input.as_ref().expect("grown");
        let _current = cuda.enter()?;
        let copied = copy_packed(&lease.stream, (cuda, input.pointer), (cuda, points));
        // Also after a failed copy: one already queued reads the caller's memory.
        lease.stream.synchronize()?;
        copied?;
        Ok(input.vulkan.address())
    }
}

/// Where a GPU-resident query's rays are read and its hits written.
pub struct CudaPlaces<'a> {
    /// The CUDA device whose memory holds the rays (and `into`): this device, or a peer.
    pub home: &'a Arc<Cuda>,
    /// What the lease's stream waits for before it reads the rays (a batch's start).
    pub after: Option<&'a Event>,
    /// Each field's destination in `home`'s memory; None: new allocations on this device.
    pub into: Option<&'a [u64]>,
}

/// One batch of CUDA rays split over several devices (a `DeviceGroup`): the caller's rays and
/// the hits' allocations on the GPU that holds the rays (`home`), written piece by piece by each
/// device (`Tracer::trace_cuda_piece`, rows copied between GPUs), then handed over at once.
pub struct CudaBatch {
    pub home: Arc<Cuda>,
    /// Orders the batch on the home GPU: the producer's writes before `start`, then the pieces'.
    stream: Stream,
    /// The whole batch's rays.
    pub rays: CudaRays,
    pub fields: Vec<Field>,
    /// Each field's allocation (taken by `finish`).
    allocations: Mutex<Option<Vec<CudaAllocation>>>,
    /// Reached once the rays are written (the caller's producer) and the allocations exist.
    start: Event,
    /// One event per piece traced, after which its hits are written; and the pieces begun and
    /// not yet done (their copies not yet queued).
    written: Mutex<(Vec<Arc<Event>>, usize)>,
}

impl CudaBatch {
    /// The batch of `rays` on `home`, its producer's writes ordered before `stream` (the caller
    /// passed `stream`'s handle to `__dlpack__`): allocates the hits of `fields`.
    pub fn new(stream: Stream, rays: CudaRays, fields: &[Field]) -> Result<CudaBatch> {
        let home = stream.cuda().clone();
        let current = home.enter()?;
        let allocations = fields
            .iter()
            .map(|field| CudaAllocation::new(&stream, rays.count * field.bytes_per_ray(false)))
            .collect::<Result<Vec<_>>>()?;
        let start = stream.record()?;
        drop(current);
        Ok(CudaBatch {
            home,
            stream,
            rays,
            fields: fields.to_vec(),
            allocations: Mutex::new(Some(allocations)),
            start,
            written: Mutex::new((Vec::new(), 0)),
        })
    }

    /// The stream's handle, for DLPack's `__dlpack__(stream=...)`.
    pub fn stream_handle(&self) -> usize {
        self.stream.raw as usize
    }

    /// Each field's address of row `start` in the batch's allocations, for a piece that begins
    /// (and reports `written` when done).
    fn rows_at(&self, start: usize) -> Result<Vec<u64>> {
        let allocations = self.allocations.lock().unwrap_or_else(|e| e.into_inner());
        let Some(allocations) = allocations.as_ref() else {
            return Err(invalid_value("this batch of CUDA rays is finished: its hits were handed over".to_string()));
        };
        self.written.lock().unwrap_or_else(|e| e.into_inner()).1 += 1;
        Ok(self
            .fields
            .iter()
            .zip(allocations)
            .map(|(field, allocation)| allocation.pointer + (start * field.bytes_per_ray(false)) as u64)
            .collect())
    }

    /// A piece begun by `rows_at` is done: its hits are written after `event` (None: it failed,
    /// and nothing of it is queued).
    fn written(&self, event: Option<Arc<Event>>) {
        let mut written = self.written.lock().unwrap_or_else(|e| e.into_inner());
        written.0.extend(event);
        written.1 -= 1;
    }

    /// The batch's hits, readable by streams ordered after `ready` (every piece's copies).
    pub fn finish(&self) -> Result<CudaHits> {
        let mut allocations = self.allocations.lock().unwrap_or_else(|e| e.into_inner());
        let written = self.written.lock().unwrap_or_else(|e| e.into_inner());
        if written.1 > 0 {
            return Err(invalid_value(format!(
                "{} pieces of this batch of CUDA rays are still being traced",
                written.1
            )));
        }
        let Some(allocations) = allocations.take() else {
            return Err(invalid_value("this batch of CUDA rays is finished already".to_string()));
        };
        let _current = self.home.enter()?;
        for event in &written.0 {
            self.stream.wait_for(event)?;
        }
        let ready = Arc::new(self.stream.record()?);
        // A batch traced in pieces is the fast tier's (`trace_cuda_piece`).
        Ok(CudaHits { fields: self.fields.iter().copied().zip(allocations).collect(), ready, wide: false })
    }
}

impl Drop for CudaBatch {
    fn drop(&mut self) {
        // Unfinished (a piece failed): the pieces' copies into the allocations finish before
        // they are freed. Finished: the allocations are the caller's, freed after `ready`.
        if self.allocations.get_mut().unwrap_or_else(|e| e.into_inner()).is_some() {
            let _ = self.stream.synchronize(); // the allocations are made in its order
            for event in &self.written.get_mut().unwrap_or_else(|e| e.into_inner()).0 {
                let _ = event.synchronize();
            }
        }
    }
}

impl CudaRays {
    /// Rows `start..stop` of these rays (arrays of one row, shared by every ray, stay whole).
    pub fn rows(&self, start: usize, stop: usize) -> CudaRays {
        let count = self.count;
        let cut = |a: CudaArray| {
            if a.rows != count || a.rows == 1 {
                return a; // one row, shared by every ray
            }
            a.rows_of_chunk(start, stop, count).expect("rows of every ray")
        };
        let bound = |b: CudaBound| match b {
            CudaBound::Each(a) => CudaBound::Each(cut(a)),
            all => all,
        };
        CudaRays {
            count: stop - start,
            origins: cut(self.origins),
            directions: cut(self.directions),
            tmin: bound(self.tmin),
            tmax: bound(self.tmax),
            mask: self.mask,
        }
    }
}

/// The arrays of `rays`, in the order they are placed in the shared buffer.
fn arrays_of(rays: &CudaRays) -> Vec<CudaArray> {
    let mut arrays = vec![rays.origins, rays.directions];
    for bound in [rays.tmin, rays.tmax] {
        if let CudaBound::Each(array) = bound {
            arrays.push(array);
        }
    }
    arrays
}

/// Bytes of arrays of these sizes placed one after another, each aligned.
fn layout_bytes(sizes: impl Iterator<Item = usize>) -> u64 {
    sizes.fold(0, |at, bytes| align_up(at + bytes as u64, SHARED_ALIGN)).max(1)
}

/// Makes `buffer` a shared buffer of at least `bytes` (replacing a smaller one).
fn grow(
    ctx: &Arc<crate::gpu::context::Context>,
    cuda: &Arc<Cuda>,
    stream: &Stream,
    buffer: &mut Option<SharedBuffer>,
    bytes: u64,
    name: &str,
) -> Result<()> {
    if buffer.as_ref().is_some_and(|b| b.vulkan.size() >= bytes) {
        return Ok(());
    }
    // The last query's copy out of the old buffer may still be queued on the stream.
    if buffer.is_some() {
        stream.synchronize()?;
    }
    *buffer = None;
    *buffer = Some(SharedBuffer::new(ctx, cuda, bytes.next_power_of_two(), name)?);
    Ok(())
}

/// Queues the copy of `array` (memory of `src_cuda`, maybe another GPU) into `dst` (memory of
/// `dst_cuda`, the stream's), tightly packed (rows of `columns` numbers).
fn copy_packed(stream: &Stream, (dst_cuda, dst): (&Cuda, u64), (src_cuda, array): (&Cuda, &CudaArray)) -> Result<()> {
    let element = array.element_bytes();
    let row_bytes = array.columns * element;
    if array.column_stride == element || array.columns == 1 {
        // SAFETY: the caller's array is CUDA memory of `src_cuda` (DLPack's contract) of these
        // rows and strides; `dst` has room for the packed copy (`grow`).
        return unsafe {
            stream.copy_2d_between(
                (dst_cuda, dst, row_bytes),
                (src_cuda, array.pointer, array.row_stride.max(row_bytes)),
                row_bytes,
                array.rows,
            )
        };
    }
    for column in 0..array.columns {
        let src = array.pointer + (column * array.column_stride) as u64;
        // SAFETY: as above, one column at a time.
        unsafe {
            stream.copy_2d_between(
                (dst_cuda, dst + (column * element) as u64, row_bytes),
                (src_cuda, src, array.row_stride.max(element)),
                element,
                array.rows,
            )?
        };
    }
    Ok(())
}

/// The rays as the GPU packs them: each array where `placed` put it in the shared buffer.
fn device_rays_in(rays: &CudaRays, base: u64, placed: &[u64]) -> DeviceRays {
    let array = |a: &CudaArray, at: u64| DeviceArray {
        address: base + at,
        stride: if a.rows == 1 { 0 } else { (a.columns * a.element_bytes()) as u32 },
        wide: a.wide,
    };
    let mut next = 2;
    let mut bound = |b: CudaBound| match b {
        CudaBound::All(value) => DeviceBound::All(value),
        CudaBound::Each(a) => {
            next += 1;
            DeviceBound::Each(array(&a, placed[next - 1]))
        }
    };
    let (tmin, tmax) = (bound(rays.tmin), bound(rays.tmax));
    DeviceRays {
        count: rays.count,
        origins: array(&rays.origins, placed[0]),
        directions: array(&rays.directions, placed[1]),
        tmin,
        tmax,
        mask: rays.mask,
    }
}

/// Why ray `row` is invalid, from its values read back (the numpy path's message).
pub fn invalid_ray(home: &Cuda, rays: &CudaRays, row: usize) -> Error {
    let read = |array: &CudaArray| -> Result<Vec<f64>> {
        let row = if array.rows == 1 { 0 } else { row };
        // The rays were copied before Vulkan read them, so they are written by now.
        let _current = home.enter()?;
        let mut values = Vec::new();
        for column in 0..array.columns {
            let at = array.pointer + (row * array.row_stride + column * array.column_stride) as u64;
            values.push(crate::gpu::cuda::read_number(at, array.wide)?);
        }
        Ok(values)
    };
    let describe = || -> Result<Error> {
        let (origin, direction) = (read(&rays.origins)?, read(&rays.directions)?);
        let bound = |b: CudaBound| -> Result<f64> {
            match b {
                CudaBound::All(value) => Ok(value),
                CudaBound::Each(array) => Ok(read(&array)?[0]),
            }
        };
        let (tmin, tmax) = (bound(rays.tmin)?, bound(rays.tmax)?);
        Ok(crate::geometry::rays::describe_invalid_ray(row, &origin, &direction, tmin, tmax))
    };
    describe().unwrap_or_else(|e| e)
}

//! Where a trace's time went (`TraceProfile`): host clock phases and, where the engine has them,
//! the device's own times. Any engine fills it.

/// Where the time went in the last trace (seconds). The host clock splits the caller's wait;
/// with two chunks in flight, `wait` is the GPU time that packing and unpacking did not hide. The
/// device's own timestamps (where its queue has them) split the GPU's part, summed over chunks.
#[derive(Clone, Copy, Debug, Default)]
pub struct TraceProfile {
    pub rays: usize,
    pub chunks: usize,
    /// Checking rays and converting them into staging (the upload, on shared-memory devices).
    pub pack: f64,
    /// Recording and submitting command buffers.
    pub submit: f64,
    /// Waiting for the GPU.
    pub wait: f64,
    /// Copying hit fields from readback memory into the result arrays (side by side with the
    /// next chunk's `pack`: the two may add up to more than the time they took).
    pub unpack: f64,
    pub total: f64,
    /// GPU time copying rays from staging to device memory (0 on shared-memory devices).
    pub gpu_upload: Option<f64>,
    /// GPU time tracing (the dispatch or trace-rays command alone).
    pub gpu_trace: Option<f64>,
    /// GPU time copying hits to readback memory (0 on shared-memory devices).
    pub gpu_readback: Option<f64>,
    /// Host time in f64 work: refining hits (`"refined"`) or the CPU tracer (`"reference"`).
    pub host_f64: f64,
    /// All hits on the GPU: the storing passes (wall time preparing and submitting them, waiting
    /// for them and copying their hits out; the phases above cover both passes of each chunk).
    pub store: f64,
    /// `contains` in grid order: the host's sort of the points, gathering them in that order and
    /// scattering the answers back (outside `total`).
    pub order: f64,
    /// The threads the host passes ran on (the device's own, or the shared pool's).
    pub host_threads: usize,
    /// Bytes of rays the host packed into staging (the layouts of `RayLayout`; f64 rays in the
    /// exact tier), for the queries whose chunks it packs.
    pub ray_bytes: usize,
    /// All hits as columns: the chunks whose columns the GPU wrote (the host writes the others'
    /// from their records).
    pub gpu_columns: usize,
}

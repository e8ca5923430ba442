//! Embree's device, scenes and geometries as owned values: each released when dropped, each call
//! checked against the device's error code, and the bytes Embree holds counted as it allocates.

use std::ffi::c_void;
use std::sync::atomic::{AtomicIsize, Ordering};
use std::sync::Arc;

use super::api::{
    error_name, EmbreeApi, RtcArguments, RtcDevice, RtcGeometry, RtcRay, RtcRayHit, RtcRayHitPacket, RtcScene, RtcValid,
};
use crate::error::{Error, Result};

/// An Embree device: the library's functions and its one `RTCDevice`.
pub struct EmbreeDevice {
    pub api: EmbreeApi,
    raw: RtcDevice,
    /// Bytes Embree holds now (its memory monitor's running sum); boxed so that its address,
    /// which Embree keeps, never moves.
    held: Box<AtomicIsize>,
    /// Embree's version as a number (40400 for 4.4.0).
    pub version: u32,
    /// Taken by each build in turn (`measured`).
    builds: std::sync::Mutex<()>,
}

// SAFETY: Embree's device is thread-safe (its API may be called from any thread); `raw` is only
// released in `drop`, when no other reference exists.
unsafe impl Send for EmbreeDevice {}
// SAFETY: as above: Embree synchronizes its own state.
unsafe impl Sync for EmbreeDevice {}

/// Embree's memory monitor: keeps the running sum of what it allocates and frees.
unsafe extern "C" fn count_bytes(user: *mut c_void, bytes: isize, _post: bool) -> bool {
    // SAFETY: `user` is the address of the device's `held` counter, which outlives the device.
    let held = unsafe { &*(user as *const AtomicIsize) };
    held.fetch_add(bytes, Ordering::Relaxed);
    true
}

impl EmbreeDevice {
    /// Opens a device of `api` (on every core, through TBB) with its memory counted.
    pub fn new(api: EmbreeApi) -> Result<Arc<EmbreeDevice>> {
        // SAFETY: a null configuration string asks for the defaults.
        let raw = unsafe { (api.new_device)(std::ptr::null()) };
        if raw.is_null() {
            return Err(Error::NoDevice("Embree could not open a device on this CPU".into()));
        }
        let held = Box::new(AtomicIsize::new(0));
        // SAFETY: `raw` is a live device; the counter outlives it (dropped after the device is).
        let version = unsafe {
            (api.set_memory_monitor)(raw, Some(count_bytes), &*held as *const AtomicIsize as *mut c_void);
            (api.get_device_property)(raw, super::api::DEVICE_PROPERTY_VERSION) as u32
        };
        let device = EmbreeDevice { api, raw, held, version, builds: Default::default() };
        device.check("opening the device")?;
        Ok(Arc::new(device))
    }

    /// The widest packet Embree traces natively on this CPU (16 with AVX-512, 8 with AVX2), or 1.
    pub fn packet_width(&self) -> usize {
        let (avx512, avx2) = vector_widths();
        if avx512 && self.has(super::api::DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED) {
            16
        } else if avx2 && self.has(super::api::DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED) {
            8
        } else {
            1
        }
    }

    /// Bytes Embree holds now (scenes, geometries, their buffers and hierarchies).
    pub fn held_bytes(&self) -> u64 {
        self.held.load(Ordering::Relaxed).max(0) as u64
    }

    /// Runs `build` (Embree builds on every core) alone among this device's builds, and measures
    /// what Embree's memory grew by and how long it took.
    pub fn measured<R>(&self, build: impl FnOnce() -> Result<R>) -> Result<(R, u64, f64)> {
        // Builds take turns so that the memory each adds is its own; no query waits on this.
        let _turn = self.builds.lock().unwrap_or_else(|e| e.into_inner());
        let (before, started) = (self.held.load(Ordering::Relaxed), std::time::Instant::now());
        let built = build()?;
        let grew = (self.held.load(Ordering::Relaxed) - before).max(0) as u64;
        Ok((built, grew, started.elapsed().as_secs_f64()))
    }

    /// Whether the library has `property` (an `RTCDeviceProperty` that answers 0 or 1).
    pub fn has(&self, property: i32) -> bool {
        // SAFETY: `raw` is a live device.
        unsafe { (self.api.get_device_property)(self.raw, property) != 0 }
    }

    /// Fails with what Embree reports about the last calls on this device, naming `what`.
    pub fn check(&self, what: &str) -> Result<()> {
        // SAFETY: `raw` is a live device.
        let code = unsafe { (self.api.get_device_error)(self.raw) };
        match code {
            0 => Ok(()),
            4 => Err(Error::OutOfMemory(format!("Embree ran out of memory {what}"))),
            _ => Err(Error::Internal(format!("Embree reported {} {what}", error_name(code)))),
        }
    }

    /// A new, empty scene with `flags` and build `quality`.
    pub fn scene(self: &Arc<Self>, flags: u32, quality: u32) -> Result<EmbreeScene> {
        // SAFETY: `raw` is a live device; the scene keeps the device alive through `device`.
        let raw = unsafe { (self.api.new_scene)(self.raw) };
        if raw.is_null() {
            self.check("making a scene")?;
            return Err(Error::Internal("Embree made no scene".into()));
        }
        // SAFETY: `raw` is the new scene.
        unsafe {
            (self.api.set_scene_flags)(raw, flags);
            (self.api.set_scene_build_quality)(raw, quality);
        }
        Ok(EmbreeScene { device: self.clone(), raw })
    }

    /// A new geometry of `kind` (an `RTCGeometryType`), to fill and commit.
    pub fn geometry(self: &Arc<Self>, kind: u32) -> Result<EmbreeGeometry> {
        // SAFETY: `raw` is a live device.
        let raw = unsafe { (self.api.new_geometry)(self.raw, kind) };
        if raw.is_null() {
            self.check("making a geometry")?;
            return Err(Error::Internal("Embree made no geometry".into()));
        }
        Ok(EmbreeGeometry { device: self.clone(), raw })
    }
}

/// Whether this CPU has AVX-512 and AVX2 (Embree's 16- and 8-wide packets run natively).
fn vector_widths() -> (bool, bool) {
    #[cfg(target_arch = "x86_64")]
    {
        (std::arch::is_x86_feature_detected!("avx512f"), std::arch::is_x86_feature_detected!("avx2"))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        (false, false)
    }
}

impl Drop for EmbreeDevice {
    fn drop(&mut self) {
        // SAFETY: every scene and geometry holds an `Arc` of this device, so none is left.
        unsafe { (self.api.release_device)(self.raw) }
    }
}

/// An Embree scene: a hierarchy over the geometries attached to it, usable by any number of
/// threads at once once committed.
pub struct EmbreeScene {
    device: Arc<EmbreeDevice>,
    raw: RtcScene,
}

impl EmbreeScene {
    pub fn raw(&self) -> RtcScene {
        self.raw
    }

    /// Commits `geometry` under ray `mask` and attaches it under `id`.
    pub fn attach(&self, geometry: &EmbreeGeometry, id: u32, mask: u32) -> Result<()> {
        geometry.set_mask(mask);
        geometry.commit()?;
        // SAFETY: both are live; the scene takes its own reference to the geometry.
        unsafe { (self.device.api.attach_geometry_by_id)(self.raw, geometry.raw, id) };
        self.device.check("attaching a geometry")
    }

    /// Builds (or rebuilds) the scene's hierarchy over its geometries. The caller makes sure no
    /// query traces the scene meanwhile (a mesh's update holds it alone).
    pub fn commit(&self) -> Result<()> {
        // SAFETY: the scene is live; see above for the queries.
        unsafe { (self.device.api.commit_scene)(self.raw) };
        self.device.check("building a hierarchy")
    }

    /// The closest hit of `rayhit` (written into it).
    ///
    /// # Safety
    /// `args` must be null or a valid arguments record whose context and filter stay valid for
    /// the call.
    #[inline]
    pub unsafe fn intersect(&self, rayhit: &mut RtcRayHit, args: *mut RtcArguments) {
        // SAFETY: the scene is committed; the caller vouches for `args`.
        unsafe { (self.device.api.intersect1)(self.raw, rayhit, args) }
    }

    /// Whether `ray` is occluded: its `tfar` becomes -inf where it is.
    ///
    /// # Safety
    /// As `intersect`.
    #[inline]
    pub unsafe fn occluded(&self, ray: &mut RtcRay, args: *mut RtcArguments) {
        // SAFETY: the scene is committed; the caller vouches for `args`.
        unsafe { (self.device.api.occluded1)(self.raw, ray, args) }
    }
}

impl EmbreeScene {
    /// Traces a packet of `K` (8 or 16) rays, `valid` lanes only: their closest hits, or
    /// (`occlusion`) whether each is occluded (its `tfar` becomes -inf where it is).
    ///
    /// # Safety
    /// As `intersect`.
    #[inline]
    pub unsafe fn trace_packet<const K: usize>(
        &self,
        valid: &RtcValid<K>,
        packet: &mut RtcRayHitPacket<K>,
        args: *mut RtcArguments,
        occlusion: bool,
    ) {
        debug_assert!(K == 8 || K == 16);
        let api = &self.device.api;
        let call = match (K, occlusion) {
            (16, false) => api.intersect16,
            (16, true) => api.occluded16,
            (_, false) => api.intersect8,
            (_, true) => api.occluded8,
        };
        // SAFETY: the record is laid out as RTCRayHitK (its leading part as RTCRayK) and aligned;
        // the caller vouches for `args`.
        unsafe { call(valid.0.as_ptr(), self.raw, packet as *mut RtcRayHitPacket<K> as *mut c_void, args) }
    }
}

impl Drop for EmbreeScene {
    fn drop(&mut self) {
        // SAFETY: the scene is released once; geometries and instances hold their own references.
        unsafe { (self.device.api.release_scene)(self.raw) }
    }
}

/// An Embree geometry (triangles, spheres, an instance) being filled or committed.
pub struct EmbreeGeometry {
    device: Arc<EmbreeDevice>,
    raw: RtcGeometry,
}

// SAFETY: Embree's functions may be called from any thread, and a committed scene traced from
// many at once; scenes and geometries are changed (filled, attached, committed) only before they
// are shared or while their mesh is held alone (`Mesh::update`).
unsafe impl Send for EmbreeScene {}
// SAFETY: as above.
unsafe impl Sync for EmbreeScene {}
// SAFETY: as above.
unsafe impl Send for EmbreeGeometry {}
// SAFETY: as above.
unsafe impl Sync for EmbreeGeometry {}

impl EmbreeGeometry {
    /// A new buffer of `count` items of `stride` bytes (`format`) owned by the geometry, filled by
    /// `fill` (Embree pads it for its vector loads).
    pub fn buffer<T: bytemuck::Pod>(
        &self,
        kind: u32,
        format: u32,
        count: usize,
        fill: impl FnOnce(&mut [T]),
    ) -> Result<()> {
        let stride = std::mem::size_of::<T>();
        // SAFETY: the geometry is live; Embree returns `count * stride` writable bytes or null.
        let data = unsafe { (self.device.api.set_new_geometry_buffer)(self.raw, kind, 0, format, stride, count) };
        if data.is_null() {
            self.device.check("allocating a geometry buffer")?;
            return Err(Error::OutOfMemory("Embree could not allocate a geometry buffer".into()));
        }
        // SAFETY: `data` holds `count` items of `T` (4-byte aligned at least, as Embree aligns
        // buffers to 16), written here before the geometry is committed.
        let items = unsafe { std::slice::from_raw_parts_mut(data as *mut T, count) };
        fill(items);
        Ok(())
    }

    /// Reads the geometry's buffer of `kind` from `data` (`count` items of `stride` bytes in
    /// `format`), which the caller keeps alive and unmoved while the geometry lives.
    ///
    /// # Safety
    /// `data` must hold `count * stride` bytes plus 12 (Embree's vector loads read past the last
    /// item), and outlive the geometry.
    pub unsafe fn share_buffer(
        &self,
        kind: u32,
        format: u32,
        data: *const c_void,
        stride: usize,
        count: usize,
    ) -> Result<()> {
        // SAFETY: the caller vouches for `data`.
        unsafe { (self.device.api.set_shared_geometry_buffer)(self.raw, kind, 0, format, data, 0, stride, count) };
        self.device.check("sharing a geometry buffer")
    }

    /// Tells Embree the buffer of `kind` changed (a refit's vertices).
    pub fn buffer_changed(&self, kind: u32) -> Result<()> {
        // SAFETY: the geometry is live and has a buffer of `kind`.
        unsafe { (self.device.api.update_geometry_buffer)(self.raw, kind, 0) };
        self.device.check("updating a geometry buffer")
    }

    pub fn set_mask(&self, mask: u32) {
        // SAFETY: the geometry is live.
        unsafe { (self.device.api.set_geometry_mask)(self.raw, mask) }
    }

    pub fn set_build_quality(&self, quality: u32) {
        // SAFETY: the geometry is live.
        unsafe { (self.device.api.set_geometry_build_quality)(self.raw, quality) }
    }

    /// Lets the filter that a query passes in its arguments see this geometry's hits.
    pub fn enable_argument_filter(&self) {
        // SAFETY: the geometry is live.
        unsafe { (self.device.api.enable_filter_from_arguments)(self.raw, true) }
    }

    /// Makes this instance geometry place `scene` by `rows` (row-major 3×4, object to world).
    pub fn instance(&self, scene: &EmbreeScene, rows: &[f32; 12]) {
        // SAFETY: both are live; Embree copies the transform and references the scene.
        unsafe {
            (self.device.api.set_instanced_scene)(self.raw, scene.raw);
            (self.device.api.set_geometry_transform)(
                self.raw,
                0,
                super::api::FORMAT_FLOAT3X4_ROW_MAJOR,
                rows.as_ptr() as *const c_void,
            );
        }
    }

    pub fn commit(&self) -> Result<()> {
        // SAFETY: the geometry is live.
        unsafe { (self.device.api.commit_geometry)(self.raw) };
        self.device.check("committing a geometry")
    }
}

impl Drop for EmbreeGeometry {
    fn drop(&mut self) {
        // SAFETY: released once; scenes it is attached to hold their own references.
        unsafe { (self.device.api.release_geometry)(self.raw) }
    }
}

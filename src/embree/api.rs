//! Embree 4's C API as the CPU engine uses it: the records it shares with the library (laid out
//! as `embree4/rtcore_*.h` lays them out) and its functions, loaded at run time from the copy the
//! wheel carries (or the system's), so that nothing links against Embree at build time.

use std::ffi::{c_char, c_void};
use std::path::{Path, PathBuf};

use libloading::Library;

use crate::error::{Error, Result};

/// Opaque handles.
pub type RtcDevice = *mut c_void;
pub type RtcScene = *mut c_void;
pub type RtcGeometry = *mut c_void;

// `RTCGeometryType`.
pub const GEOMETRY_TYPE_TRIANGLE: u32 = 0;
pub const GEOMETRY_TYPE_SPHERE_POINT: u32 = 50;
pub const GEOMETRY_TYPE_INSTANCE: u32 = 121;
// `RTCBufferType`.
pub const BUFFER_TYPE_INDEX: u32 = 0;
pub const BUFFER_TYPE_VERTEX: u32 = 1;
// `RTCFormat`.
pub const FORMAT_UINT3: u32 = 0x5003;
pub const FORMAT_FLOAT3: u32 = 0x9003;
pub const FORMAT_FLOAT4: u32 = 0x9004;
pub const FORMAT_FLOAT3X4_ROW_MAJOR: u32 = 0x9134;
// `RTCBuildQuality`.
pub const BUILD_QUALITY_LOW: u32 = 0;
pub const BUILD_QUALITY_MEDIUM: u32 = 1;
pub const BUILD_QUALITY_HIGH: u32 = 2;
pub const BUILD_QUALITY_REFIT: u32 = 3;
// `RTCSceneFlags`.
pub const SCENE_FLAG_DYNAMIC: u32 = 1 << 0;
pub const SCENE_FLAG_COMPACT: u32 = 1 << 1;
pub const SCENE_FLAG_ROBUST: u32 = 1 << 2;
pub const SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS: u32 = 1 << 3;
// `RTCRayQueryFlags`.
pub const RAY_QUERY_FLAG_INCOHERENT: u32 = 0;
pub const RAY_QUERY_FLAG_COHERENT: u32 = 1;
pub const RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER: u32 = 1 << 1;
/// `RTC_FEATURE_FLAGS_ALL`.
pub const FEATURE_FLAGS_ALL: u32 = 0xffff_ffff;
/// `RTC_INVALID_GEOMETRY_ID`.
pub const INVALID_ID: u32 = u32::MAX;
// `RTCDeviceProperty`.
pub const DEVICE_PROPERTY_VERSION: i32 = 0;
pub const DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED: i32 = 33;
pub const DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED: i32 = 34;
pub const DEVICE_PROPERTY_RAY_MASK_SUPPORTED: i32 = 64;
pub const DEVICE_PROPERTY_FILTER_FUNCTION_SUPPORTED: i32 = 66;
pub const DEVICE_PROPERTY_POINT_GEOMETRY_SUPPORTED: i32 = 101;

/// `RTCRay`: one ray (origin, tnear, direction, time, tfar, mask, id, flags).
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, Default)]
pub struct RtcRay {
    pub org: [f32; 3],
    pub tnear: f32,
    pub dir: [f32; 3],
    pub time: f32,
    pub tfar: f32,
    pub mask: u32,
    pub id: u32,
    pub flags: u32,
}

/// `RTCHit` for one instance level, with room for `instPrimID` (builds with instance arrays have
/// it; the rest never write there).
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, Default)]
pub struct RtcHit {
    pub ng: [f32; 3],
    /// Barycentrics of vertices 1 and 2.
    pub uv: [f32; 2],
    pub prim_id: u32,
    pub geom_id: u32,
    pub inst_id: [u32; 1],
    pub inst_prim_id: [u32; 1],
}

/// `RTCRayHit`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct RtcRayHit {
    pub ray: RtcRay,
    pub hit: RtcHit,
}

/// `RTCRayHit8` / `RTCRayHit16` (`K` lanes, each field an array of lanes), with room for
/// `instPrimID` as `RtcHit`. Aligned for 16 lanes (Embree asks for the packet's width in bytes).
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug)]
pub struct RtcRayHitPacket<const K: usize> {
    pub org_x: [f32; K],
    pub org_y: [f32; K],
    pub org_z: [f32; K],
    pub tnear: [f32; K],
    pub dir_x: [f32; K],
    pub dir_y: [f32; K],
    pub dir_z: [f32; K],
    pub time: [f32; K],
    pub tfar: [f32; K],
    pub mask: [u32; K],
    pub id: [u32; K],
    pub flags: [u32; K],
    pub ng_x: [f32; K],
    pub ng_y: [f32; K],
    pub ng_z: [f32; K],
    pub u: [f32; K],
    pub v: [f32; K],
    pub prim_id: [u32; K],
    pub geom_id: [u32; K],
    pub inst_id: [u32; K],
    pub inst_prim_id: [u32; K],
}

impl<const K: usize> Default for RtcRayHitPacket<K> {
    fn default() -> Self {
        RtcRayHitPacket {
            org_x: [0.0; K],
            org_y: [0.0; K],
            org_z: [0.0; K],
            tnear: [0.0; K],
            dir_x: [0.0; K],
            dir_y: [0.0; K],
            dir_z: [0.0; K],
            time: [0.0; K],
            tfar: [0.0; K],
            mask: [0; K],
            id: [0; K],
            flags: [0; K],
            ng_x: [0.0; K],
            ng_y: [0.0; K],
            ng_z: [0.0; K],
            u: [0.0; K],
            v: [0.0; K],
            prim_id: [INVALID_ID; K],
            geom_id: [INVALID_ID; K],
            inst_id: [INVALID_ID; K],
            inst_prim_id: [INVALID_ID; K],
        }
    }
}

/// A packet's valid lanes (-1: traced; 0: not), aligned as Embree asks.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug)]
pub struct RtcValid<const K: usize>(pub [i32; K]);

/// `RTCRayQueryContext` for one instance level: Embree hands the pointer a query passes back to
/// its filter, so the CPU engine's own per-query state follows it in memory (`#[repr(C)]`, first
/// field).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct RtcRayQueryContext {
    pub inst_id: [u32; 1],
}

impl Default for RtcRayQueryContext {
    fn default() -> Self {
        RtcRayQueryContext { inst_id: [INVALID_ID] }
    }
}

/// `RTCFilterFunctionNArguments`: a packet of `n` candidate hits, SOA (`ray` and `hit` hold `n`
/// lanes of each field, as `RTCRayN`/`RTCHitN`).
#[repr(C)]
pub struct RtcFilterArguments {
    pub valid: *mut i32,
    pub geometry_user_ptr: *mut c_void,
    pub context: *mut RtcRayQueryContext,
    pub ray: *mut f32,
    pub hit: *mut f32,
    pub n: u32,
}

pub type RtcFilterFunction = unsafe extern "C" fn(args: *const RtcFilterArguments);

/// `RTCIntersectArguments` (also `RTCOccludedArguments`): the optional `intersect` callback and
/// `minWidthDistanceFactor` are always present here, null and zero, so the record is right for a
/// library built with or without them.
#[repr(C)]
pub struct RtcArguments {
    pub flags: u32,
    pub feature_mask: u32,
    pub context: *mut RtcRayQueryContext,
    pub filter: Option<RtcFilterFunction>,
    pub intersect: *mut c_void,
    pub min_width_distance_factor: f32,
}

pub type RtcMemoryMonitor = unsafe extern "C" fn(user: *mut c_void, bytes: isize, post: bool) -> bool;

/// The Embree functions the CPU engine calls, from the loaded library.
pub struct EmbreeApi {
    pub new_device: unsafe extern "C" fn(config: *const c_char) -> RtcDevice,
    pub release_device: unsafe extern "C" fn(RtcDevice),
    pub get_device_error: unsafe extern "C" fn(RtcDevice) -> u32,
    pub get_device_property: unsafe extern "C" fn(RtcDevice, i32) -> isize,
    pub set_memory_monitor: unsafe extern "C" fn(RtcDevice, Option<RtcMemoryMonitor>, *mut c_void),
    pub new_scene: unsafe extern "C" fn(RtcDevice) -> RtcScene,
    pub release_scene: unsafe extern "C" fn(RtcScene),
    pub set_scene_flags: unsafe extern "C" fn(RtcScene, u32),
    pub set_scene_build_quality: unsafe extern "C" fn(RtcScene, u32),
    pub attach_geometry_by_id: unsafe extern "C" fn(RtcScene, RtcGeometry, u32),
    pub commit_scene: unsafe extern "C" fn(RtcScene),
    pub new_geometry: unsafe extern "C" fn(RtcDevice, u32) -> RtcGeometry,
    pub release_geometry: unsafe extern "C" fn(RtcGeometry),
    pub commit_geometry: unsafe extern "C" fn(RtcGeometry),
    pub set_geometry_mask: unsafe extern "C" fn(RtcGeometry, u32),
    pub set_geometry_build_quality: unsafe extern "C" fn(RtcGeometry, u32),
    pub set_new_geometry_buffer: unsafe extern "C" fn(RtcGeometry, u32, u32, u32, usize, usize) -> *mut c_void,
    pub set_shared_geometry_buffer:
        unsafe extern "C" fn(RtcGeometry, u32, u32, u32, *const c_void, usize, usize, usize),
    pub update_geometry_buffer: unsafe extern "C" fn(RtcGeometry, u32, u32),
    pub enable_filter_from_arguments: unsafe extern "C" fn(RtcGeometry, bool),
    pub set_instanced_scene: unsafe extern "C" fn(RtcGeometry, RtcScene),
    pub set_geometry_transform: unsafe extern "C" fn(RtcGeometry, u32, u32, *const c_void),
    pub intersect1: unsafe extern "C" fn(RtcScene, *mut RtcRayHit, *mut RtcArguments),
    pub occluded1: unsafe extern "C" fn(RtcScene, *mut RtcRay, *mut RtcArguments),
    /// Packets of 8 and 16 (the ray half of a packet is the leading part of its record).
    pub intersect8: unsafe extern "C" fn(*const i32, RtcScene, *mut c_void, *mut RtcArguments),
    pub occluded8: unsafe extern "C" fn(*const i32, RtcScene, *mut c_void, *mut RtcArguments),
    pub intersect16: unsafe extern "C" fn(*const i32, RtcScene, *mut c_void, *mut RtcArguments),
    pub occluded16: unsafe extern "C" fn(*const i32, RtcScene, *mut c_void, *mut RtcArguments),
    /// Keeps the library loaded: never unloaded, as TBB's worker threads (which Embree starts)
    /// outlive any device, and unmapping their code under them crashes the process at exit.
    _library: std::mem::ManuallyDrop<Library>,
}

/// The file names Embree 4 goes by, the wheel's copy (renamed by its build) first.
const LIBRARY_NAMES: [&str; 2] = ["libembree4.so.4", "libembree4.so"];

impl EmbreeApi {
    /// Loads Embree from the first of `places` (folders) that has it, else by name from the
    /// system's library path.
    pub fn load(places: &[PathBuf]) -> Result<EmbreeApi> {
        let mut tried = Vec::new();
        for place in places {
            if let Some(path) = library_in(place) {
                match Self::load_from(&path) {
                    Ok(api) => return Ok(api),
                    Err(e) => tried.push(format!("{}: {e}", path.display())),
                }
            }
        }
        for name in LIBRARY_NAMES {
            match Self::load_from(Path::new(name)) {
                Ok(api) => return Ok(api),
                Err(e) => tried.push(format!("{name}: {e}")),
            }
        }
        Err(Error::NoDevice(format!(
            "the CPU engine needs Embree 4, which vkray's wheel carries; it could not be loaded ({})",
            tried.join("; ")
        )))
    }

    fn load_from(path: &Path) -> std::result::Result<EmbreeApi, libloading::Error> {
        // SAFETY: loading Embree runs its (and TBB's) initializers, which have no preconditions;
        // each symbol below is taken with the signature of `embree4/rtcore_*.h`.
        unsafe {
            let library = Library::new(path)?;
            macro_rules! symbol {
                ($name:literal) => {
                    *library.get(concat!($name, "\0").as_bytes())?
                };
            }
            Ok(EmbreeApi {
                new_device: symbol!("rtcNewDevice"),
                release_device: symbol!("rtcReleaseDevice"),
                get_device_error: symbol!("rtcGetDeviceError"),
                get_device_property: symbol!("rtcGetDeviceProperty"),
                set_memory_monitor: symbol!("rtcSetDeviceMemoryMonitorFunction"),
                new_scene: symbol!("rtcNewScene"),
                release_scene: symbol!("rtcReleaseScene"),
                set_scene_flags: symbol!("rtcSetSceneFlags"),
                set_scene_build_quality: symbol!("rtcSetSceneBuildQuality"),
                attach_geometry_by_id: symbol!("rtcAttachGeometryByID"),
                commit_scene: symbol!("rtcCommitScene"),
                new_geometry: symbol!("rtcNewGeometry"),
                release_geometry: symbol!("rtcReleaseGeometry"),
                commit_geometry: symbol!("rtcCommitGeometry"),
                set_geometry_mask: symbol!("rtcSetGeometryMask"),
                set_geometry_build_quality: symbol!("rtcSetGeometryBuildQuality"),
                set_new_geometry_buffer: symbol!("rtcSetNewGeometryBuffer"),
                set_shared_geometry_buffer: symbol!("rtcSetSharedGeometryBuffer"),
                update_geometry_buffer: symbol!("rtcUpdateGeometryBuffer"),
                enable_filter_from_arguments: symbol!("rtcSetGeometryEnableFilterFunctionFromArguments"),
                set_instanced_scene: symbol!("rtcSetGeometryInstancedScene"),
                set_geometry_transform: symbol!("rtcSetGeometryTransform"),
                intersect1: symbol!("rtcIntersect1"),
                occluded1: symbol!("rtcOccluded1"),
                intersect8: symbol!("rtcIntersect8"),
                occluded8: symbol!("rtcOccluded8"),
                intersect16: symbol!("rtcIntersect16"),
                occluded16: symbol!("rtcOccluded16"),
                _library: std::mem::ManuallyDrop::new(library),
            })
        }
    }
}

/// The Embree library file in `folder`, if any (the wheel's copy carries a hash in its name).
fn library_in(folder: &Path) -> Option<PathBuf> {
    let entries = std::fs::read_dir(folder).ok()?;
    let mut found: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("libembree4") && n.contains(".so"))
        })
        .collect();
    found.sort();
    found.into_iter().next()
}

/// What Embree's error code says.
pub fn error_name(code: u32) -> &'static str {
    match code {
        0 => "no error",
        2 => "invalid argument",
        3 => "invalid operation",
        4 => "out of memory",
        5 => "unsupported CPU",
        6 => "cancelled",
        _ => "unknown error",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{offset_of, size_of};

    #[test]
    fn records_match_embree4_headers() {
        assert_eq!(size_of::<RtcRay>(), 48);
        assert_eq!(offset_of!(RtcRay, tfar), 32);
        assert_eq!(offset_of!(RtcRay, mask), 36);
        assert_eq!(offset_of!(RtcHit, uv), 12);
        assert_eq!(offset_of!(RtcHit, prim_id), 20);
        assert_eq!(offset_of!(RtcHit, geom_id), 24);
        assert_eq!(offset_of!(RtcHit, inst_id), 28);
        assert_eq!(offset_of!(RtcRayHit, hit), 48);
        assert_eq!(offset_of!(RtcFilterArguments, n), 40);
        assert_eq!(offset_of!(RtcArguments, context), 8);
        assert_eq!(offset_of!(RtcArguments, filter), 16);
        assert_eq!(offset_of!(RtcArguments, intersect), 24);
        // RTCRayHit16: the ray's 12 fields of 16 lanes, then the hit's.
        assert_eq!(offset_of!(RtcRayHitPacket<16>, tfar), 8 * 64);
        assert_eq!(offset_of!(RtcRayHitPacket<16>, ng_x), 12 * 64);
        assert_eq!(offset_of!(RtcRayHitPacket<16>, inst_id), 19 * 64);
        assert_eq!(offset_of!(RtcRayHitPacket<8>, prim_id), 17 * 32);
    }
}

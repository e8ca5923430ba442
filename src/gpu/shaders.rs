//! SPIR-V modules compiled from shaders/ by build.rs.

macro_rules! spirv {
    ($name:literal) => {
        include_bytes!(concat!(env!("OUT_DIR"), "/", $name, ".spv"))
    };
}

pub const TRACE_RAY_QUERY: &[u8] = spirv!("trace_ray_query.comp");
pub const RAYGEN: &[u8] = spirv!("raygen.rgen");
pub const CLOSEST_HIT: &[u8] = spirv!("closest_hit.rchit");
pub const MISS: &[u8] = spirv!("miss.rmiss");
pub const TRACE_EXACT_RAY_QUERY: &[u8] = spirv!("trace_exact_ray_query.comp");
pub const RAYGEN_EXACT: &[u8] = spirv!("raygen_exact.rgen");
pub const INTERSECTION_EXACT: &[u8] = spirv!("intersection_exact.rint");
pub const SPHERE_INTERSECTION: &[u8] = spirv!("sphere.rint");
pub const ANY_HIT_ALL: &[u8] = spirv!("any_hit_all.rahit");
pub const ANY_HIT_OPACITY: &[u8] = spirv!("any_hit_opacity.rahit");
pub const CLOSEST_POINT: &[u8] = spirv!("closest_point.comp");
pub const WINDING: &[u8] = spirv!("winding.comp");
pub const PACK_RAYS: &[u8] = spirv!("pack_rays.comp");
pub const POINT_ORDER: &[u8] = spirv!("point_order.comp");
pub const SIGN_POINTS: &[u8] = spirv!("sign_points.comp");
pub const CAP_WINDING: &[u8] = spirv!("cap_winding.comp");
pub const LIST_OFFSETS: &[u8] = spirv!("list_offsets.comp");
pub const HIT_COLUMNS: &[u8] = spirv!("hit_columns.comp");

/// Every embedded module with its source name (for `spirv-val` in the tests).
pub const ALL: &[(&str, &[u8])] = &[
    ("trace_ray_query.comp", TRACE_RAY_QUERY),
    ("raygen.rgen", RAYGEN),
    ("closest_hit.rchit", CLOSEST_HIT),
    ("miss.rmiss", MISS),
    ("trace_exact_ray_query.comp", TRACE_EXACT_RAY_QUERY),
    ("raygen_exact.rgen", RAYGEN_EXACT),
    ("intersection_exact.rint", INTERSECTION_EXACT),
    ("sphere.rint", SPHERE_INTERSECTION),
    ("any_hit_all.rahit", ANY_HIT_ALL),
    ("any_hit_opacity.rahit", ANY_HIT_OPACITY),
    ("closest_point.comp", CLOSEST_POINT),
    ("winding.comp", WINDING),
    ("pack_rays.comp", PACK_RAYS),
    ("point_order.comp", POINT_ORDER),
    ("sign_points.comp", SIGN_POINTS),
    ("cap_winding.comp", CAP_WINDING),
    ("list_offsets.comp", LIST_OFFSETS),
    ("hit_columns.comp", HIT_COLUMNS),
];

/// A module's words, copied to u32 alignment (`include_bytes!` guarantees none).
pub fn words(bytes: &[u8]) -> Vec<u32> {
    ash::util::read_spv(&mut std::io::Cursor::new(bytes)).expect("embedded SPIR-V is whole words")
}

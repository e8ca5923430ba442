// Shared by every tracer backend: the ray record, the hit record and the outputs; the records the
// host writes (push constants, geometry sources) are declared in records.glsl. Everything is
// reached through buffer device addresses in push constants, so the ray-query and
// ray-tracing-pipeline backends bind nothing else and share this file. Include after enabling
// GL_EXT_ray_query or GL_EXT_ray_tracing (for the gl_RayFlags*EXT constants).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require

// Bits of OUTPUTS: which hit fields the caller asked for. Unasked fields are never written.
const uint OUT_T = 1u;
const uint OUT_PRIM = 2u;
const uint OUT_INSTANCE = 4u;
const uint OUT_CUSTOM = 8u;
const uint OUT_UV = 16u;
const uint OUT_NORMAL = 32u;
const uint OUT_GEOMETRY = 64u;

// Specialization constants: resolved when the pipeline variant is created, so a query only pays
// for what its scene holds and what its caller asked.
layout(constant_id = 0) const uint OUTPUTS = 0x7Fu;
layout(constant_id = 1) const uint RAY_FLAGS = 0u;
// What each ray asks: the closest hit (or any, with TerminateOnFirstHit), or all of them (ALL:
// every hit counted, none committed, the nearest kept in the ray's HitList; see hit_lists.glsl),
// or (PARITY, exact tier, for contains) the signed sum of its crossings and whether the ray's
// origin lies on a surface, into one int (trace::request::Crossings): CROSSING where the ray
// meets a triangle's back in the mesh's frame (it leaves an outward mesh), -CROSSING its front,
// plus ON_SURFACE; or (WINDING, exact tier, one instance) PARITY's sum, less the crossings of the
// cap that closes the mesh's holes, and the cap's winding number about the origin in out_t.
layout(constant_id = 3) const uint QUERY = 0u;
const uint QUERY_CLOSEST = 0u;
const uint QUERY_ALL = 1u;
const uint QUERY_PARITY = 2u;
// The product of (1 - opacity) over every crossing in [tmin, tmax], written to out_t.
const uint QUERY_TRANSMIT = 3u;
const uint QUERY_WINDING = 4u;
// The exact tier's edges (trace::Request::contacts): 0, crossings (an edge or vertex that several
// triangles share belongs to exactly one of them: the tie-break); 1, contacts (closed triangles:
// each triangle has its edges and vertices, so a ray that only touches a boundary hits it).
layout(constant_id = 4) const uint CLOSED_EDGES = 0u;
const int ON_SURFACE = 1;
const int CROSSING = 2;
// Where rays come from: the rays buffer, or a Sensor record the shaders generate them from, or
// (exact tier) a PointRays record: one ray from each point of the closest-point search's buffer.
layout(constant_id = 5) const uint RAY_SOURCE = 0u;
const uint RAYS_FROM_BUFFER = 0u;
const uint RAYS_FROM_SENSOR = 1u;
const uint RAYS_FROM_POINTS = 2u;
// Triangles whose opacity is below this let rays through in every query but transmittance (which
// multiplies 1 - opacity over them all); cut-outs (0) always do. Only scenes with opacity read it.
layout(constant_id = 6) const float OPACITY_THRESHOLD = 0.5;

// One ray: origin and tmin, direction and tmax (32 bytes, one aligned pair of vec4).
layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer RayBuffer { vec4 v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer FloatOut { float v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer IntOut { int v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Floats { float v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Words { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Ints { int v[]; };

// The records the host writes: Params (the push constants), GeometrySource, the exact tier's.
#include "records.glsl"

// The GeometrySource records of one BLAS (one per geometry). Indexed by instance (TLAS order),
// `geometries` points at that BLAS's GeometrySource array.
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer GeometrySources { GeometrySource g[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer InstanceGeometries { uint64_t geometries[]; };

struct Ray {
  vec3 origin;
  float tmin;
  vec3 direction;
  float tmax;
};

uint ray_cull_mask(uint i) {
  if (RAY_SOURCE == RAYS_FROM_SENSOR) return params.ray_mask;
  return params.masks == 0ul ? params.ray_mask : Words(params.masks).v[i];
}

layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer SensorRecord { Sensor s; };

// Ray i of the chunk a Sensor record describes; see records.glsl for the order of operations
// (`precise`: no fused multiply-adds, so that Sensor.rays() on the host is the same bit for bit).
Ray sensor_ray(uint i) {
  Sensor s = SensorRecord(params.rays).s;
  uint index = uint(params.masks) + i;
  uint column = index % s.columns;
  uint row = index / s.columns;
  precise float px = float(column) + s.pixel_offset;
  precise float py = float(row) + s.pixel_offset;
  if (s.kind == SENSOR_PINHOLE) {
    precise vec3 d = s.axes[0].xyz * px + (s.axes[1].xyz * py + s.axes[2].xyz);
    return Ray(s.origin.xyz, s.origin.w, d, s.axes[0].w);
  }
  if (s.kind == SENSOR_ORTHOGRAPHIC) {
    precise vec3 o = (s.origin.xyz + s.axes[0].xyz * px) + s.axes[1].xyz * py;
    return Ray(o, s.origin.w, s.axes[2].xyz, s.axes[0].w);
  }
  Floats table = Floats(s.table);
  uint channel = 2u * (s.columns + row);
  precise float lx = table.v[channel] * table.v[2u * column];
  precise float ly = table.v[channel] * table.v[2u * column + 1u];
  float lz = table.v[channel + 1u];
  vec3 c0 = vec3(s.axes[0].x, s.axes[1].x, s.axes[2].x);
  vec3 c1 = vec3(s.axes[0].y, s.axes[1].y, s.axes[2].y);
  vec3 c2 = vec3(s.axes[0].z, s.axes[1].z, s.axes[2].z);
  precise vec3 d = (c0 * lx + c1 * ly) + c2 * lz;
  return Ray(s.origin.xyz, s.origin.w, d, s.axes[0].w);
}

Ray load_ray(uint i) {
  if (RAY_SOURCE == RAYS_FROM_SENSOR) return sensor_ray(i);
  RayBuffer rays = RayBuffer(params.rays);
  vec4 a = rays.v[2u * i];
  vec4 b = rays.v[2u * i + 1u];
  return Ray(a.xyz, a.w, b.xyz, b.w);
}

// What traversal found: prim < 0 means a miss.
struct Hit {
  float t;  // prim is the caller's triangle index, -1 on a miss
  int prim;
  int instance;
  int custom;
  int geometry;
  vec2 uv;
  vec3 normal;
};

Hit miss_hit() {
  float nan = uintBitsToFloat(0x7fc00000u);
  return Hit(uintBitsToFloat(0x7f800000u), -1, -1, -1, -1, vec2(nan), vec3(nan));
}

// Corner indices of triangle `prim` in an index buffer of uint32, or of uint16 packed in words.
uvec3 triangle_indices_at(uint64_t indices, uint index_is_u16, uint prim) {
  Words words = Words(indices);
  if (index_is_u16 != 0u) {
    uint first = 3u * prim;
    uvec3 idx;
    for (uint k = 0u; k < 3u; ++k) {
      uint word = words.v[(first + k) >> 1u];
      idx[k] = ((first + k) & 1u) == 0u ? (word & 0xFFFFu) : (word >> 16u);
    }
    return idx;
  }
  return uvec3(words.v[3u * prim], words.v[3u * prim + 1u], words.v[3u * prim + 2u]);
}

uvec3 triangle_indices(GeometrySource src, uint prim) {
  return triangle_indices_at(src.indices, src.index_is_u16, prim);
}

// A vertex in the mesh's device frame, decoded as the acceleration structure reads it.
vec3 vertex_at(GeometrySource src, uint index) {
  if (src.vertex_format == VERTEX_F32) {
    Floats f = Floats(src.vertices);
    return vec3(f.v[3u * index], f.v[3u * index + 1u], f.v[3u * index + 2u]);
  }
  Words w = Words(src.vertices);
  uvec2 packed = uvec2(w.v[2u * index], w.v[2u * index + 1u]);
  if (src.vertex_format == VERTEX_F16) {
    return vec3(unpackHalf2x16(packed.x), unpackHalf2x16(packed.y).x);
  }
  return vec3(unpackSnorm2x16(packed.x), unpackSnorm2x16(packed.y).x);
}

GeometrySource geometry_source(int instance, int geometry) {
  uint64_t sources = InstanceGeometries(params.instances).geometries[instance];
  return GeometrySources(sources).g[geometry];
}

// The caller's index of a triangle the device may hold in another order (see src/scene/mesh.rs):
// `order` maps device triangles to the caller's, or is 0 where they agree.
int caller_index(uint64_t order, int prim) {
  return order == 0ul ? prim : Ints(order).v[prim];
}

int caller_primitive(GeometrySource src, int prim) {
  return caller_index(src.primitive_order, prim);
}

// Unit geometric normal of the hit triangle in world space, right-handed in the triangle's winding
// (v0, v1, v2). Built from the transformed edges, so mirroring instances flip it as they flip the
// triangle.
vec3 world_normal(GeometrySource src, int prim, mat4x3 object_to_world) {
  uvec3 idx = triangle_indices(src, uint(prim));
  mat3 linear = mat3(object_to_world);
  vec3 e1 = linear * (vertex_at(src, idx.y) - vertex_at(src, idx.x));
  vec3 e2 = linear * (vertex_at(src, idx.z) - vertex_at(src, idx.x));
  return normalize(cross(e1, e2));
}

layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer Spheres { vec4 s[]; };

// The hit kind sphere intersections report (user kinds are 0..127; triangles are 0xFE, 0xFF).
const uint SPHERE_HIT_KIND = 1u;

vec4 sphere_at(int instance, int geometry, int prim) {
  return Spheres(geometry_source(instance, geometry).vertices).s[prim];
}

// Where a ray meets a sphere within [tmin, tmax]: the nearer root inside the interval, or -1.
// Haines et al. (Ray Tracing Gems, ch. 7): the discriminant from the closest point of the line
// to the centre, free of the cancellation of b^2 - 4ac for small or distant spheres, and the
// nearer root from the farther one (q / a and c / q), never as a difference of close numbers.
float sphere_hit(vec3 origin, vec3 direction, vec4 sphere, float tmin, float tmax) {
  vec3 f = origin - sphere.xyz;
  float a = dot(direction, direction);
  float b = -dot(f, direction);
  vec3 closest = f + (b / a) * direction;
  float r2 = sphere.w * sphere.w;
  float discriminant = r2 - dot(closest, closest);
  if (discriminant < 0.0) return -1.0;
  float q = b + (b >= 0.0 ? 1.0 : -1.0) * sqrt(a * discriminant);
  float c = dot(f, f) - r2;
  float t0 = q != 0.0 ? c / q : 0.0;
  float t1 = q / a;
  float near = min(t0, t1);
  float far = max(t0, t1);
  if (near >= tmin && near <= tmax) return near;
  if (far >= tmin && far <= tmax) return far;
  return -1.0;
}

// Unit outward normal of a sphere hit, in world space, from the ray in object space.
vec3 sphere_normal(vec4 sphere, vec3 object_origin, vec3 object_direction, float t, mat4x3 world_to_object) {
  vec3 n = (object_origin + t * object_direction - sphere.xyz) / sphere.w;
  return normalize(transpose(mat3(world_to_object)) * n);
}

// The opacity of device triangle `prim` of a geometry (1 where the geometry has none).
float triangle_opacity(GeometrySource src, int prim) {
  return src.opacity == 0ul ? 1.0 : Floats(src.opacity).v[prim];
}

// Whether a triangle of this opacity stops rays (closest, occluded, all hits and counts).
bool is_solid(float opacity) {
  return opacity >= OPACITY_THRESHOLD;
}

// Fills the fields that need the triangle's source: its caller index and its normal.
void resolve_triangle(inout Hit hit, mat4x3 object_to_world) {
  if ((OUTPUTS & (OUT_PRIM | OUT_NORMAL)) == 0u) return;
  GeometrySource src = geometry_source(hit.instance, hit.geometry);
  if ((OUTPUTS & OUT_NORMAL) != 0u) hit.normal = world_normal(src, hit.prim, object_to_world);
  hit.prim = caller_primitive(src, hit.prim);
}

// The order of all hits (QUERY_ALL) in the fast tier: nearer first, then lower ids.
bool is_before(FastHit a, FastHit b) {
  return a.t < b.t || (a.t == b.t && (a.instance < b.instance || (a.instance == b.instance &&
                                      (a.geometry < b.geometry || (a.geometry == b.geometry && a.prim < b.prim)))));
}

bool is_same(FastHit a, FastHit b) {
  return a.t == b.t && a.instance == b.instance && a.geometry == b.geometry && a.prim == b.prim;
}

void store_hit(uint i, Hit h) {
  if ((OUTPUTS & OUT_T) != 0u) FloatOut(params.out_t).v[i] = h.t;
  if ((OUTPUTS & OUT_PRIM) != 0u) IntOut(params.out_prim).v[i] = h.prim;
  if ((OUTPUTS & OUT_INSTANCE) != 0u) IntOut(params.out_instance).v[i] = h.instance;
  if ((OUTPUTS & OUT_CUSTOM) != 0u) IntOut(params.out_custom).v[i] = h.custom;
  if ((OUTPUTS & OUT_GEOMETRY) != 0u) IntOut(params.out_geometry).v[i] = h.geometry;
  if ((OUTPUTS & OUT_UV) != 0u) {
    FloatOut uv = FloatOut(params.out_uv);
    uv.v[2u * i] = h.uv.x;
    uv.v[2u * i + 1u] = h.uv.y;
  }
  if ((OUTPUTS & OUT_NORMAL) != 0u) {
    FloatOut n = FloatOut(params.out_normal);
    n.v[3u * i] = h.normal.x;
    n.v[3u * i + 1u] = h.normal.y;
    n.v[3u * i + 2u] = h.normal.z;
  }
}

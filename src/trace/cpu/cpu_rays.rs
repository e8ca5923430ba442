//! The CPU engine's fast tier: rays packed in f32 exactly as the GPU's are (far origins advanced
//! in f64 first), traced by Embree on every core chunk by chunk, each chunk's answers written
//! into the caller's fields before the next starts (and the interrupt asked between chunks).

use std::time::Instant;

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use super::hit_filter::{Candidate, QueryContext};
use crate::embree::api::{
    RtcArguments, RtcHit, RtcRay, RtcRayHit, RtcRayHitPacket, RtcValid, FEATURE_FLAGS_ALL, INVALID_ID,
    RAY_QUERY_FLAG_COHERENT, RAY_QUERY_FLAG_INCOHERENT,
};
use crate::error::{invalid_value, Error, Result};
use crate::geometry::parallel::{self, try_vec, try_zeroed};
use crate::geometry::precision::Cull;
use crate::geometry::rays::{Advance, Frame, PlainLanes, PlainPacker, Rays, RAY_FLOATS};
use crate::geometry::reference::ReferenceHit;
use crate::scene::{CpuScene, MeshKind, Scene};
use crate::trace::hit_fields::{Field, HitSink};
use crate::trace::host_tiers::{check_hits_fit, AllHits};
use crate::trace::pacer::{first_on_cpu, in_paced_blocks};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Query, RayBatch};

/// One ray's answer: its nearest hit (`prim` -1 where none), or for counts the number of hits in
/// `prim`, for transmittance the light kept in `t`.
#[derive(Clone, Copy, Debug)]
struct RayAnswer {
    t: f32,
    uv: [f32; 2],
    prim: i32,
    geometry: i32,
    instance: i32,
    normal: [f32; 3],
}

const MISS: RayAnswer =
    RayAnswer { t: f32::INFINITY, uv: [f32::NAN; 2], prim: -1, geometry: -1, instance: -1, normal: [f32::NAN; 3] };

/// What the scene's frame is divided by in Embree (`CpuScene::unit`, a power of two), with its
/// inverse (exact) for the rays' packing.
#[derive(Clone, Copy)]
struct Units {
    unit: f64,
    inverse: f64,
    /// `log2(inverse)`: the packing scales in f32 where every factor is a normal f32.
    inverse_exponent: i32,
}

impl Units {
    fn of(hierarchy: &CpuScene) -> Units {
        Units::new(hierarchy.unit())
    }

    /// The units of `unit`, a power of two (normal in f64).
    fn new(unit: f64) -> Units {
        let inverse = 1.0 / unit;
        Units { unit, inverse, inverse_exponent: ((inverse.to_bits() >> 52) & 0x7ff) as i32 - 1023 }
    }
}

/// 2^k as an f32, where it is a normal one.
#[inline(always)]
fn normal_power_of_two(k: i32) -> Option<f32> {
    (-126..=127).contains(&k).then(|| f32::from_bits(((k + 127) as u32) << 23))
}

/// A packed ray (`RAY_FLOATS`: origin, tmin, direction, tmax) as Embree takes it, and what its
/// `t` is multiplied by to be the caller's. Embree holds the scene's frame divided by `unit`
/// (`CpuScene::unit`), so the origin is too; the direction is scaled to a length near 1 (Embree
/// clamps direction components below 1e-18, which a direction in units of a huge scene would
/// be); both by powers of two (exact: multiplying by their inverses is dividing, bit for bit,
/// without a division a ray), and `t` by their ratio.
#[inline(always)]
fn embree_ray(packed: &[f32], mask: u8, units: Units) -> (RtcRay, f64) {
    let longest = packed[4].abs().max(packed[5].abs()).max(packed[6].abs());
    // The direction is divided by 2^up (exact), so that its longest component lies in (1/2, 1].
    let up = exponent_at_or_above(longest).unwrap_or(0);
    let (down, back_up) = (power_of_two(-up), power_of_two(up));
    // A point at t lies at (o + t d) / unit = o / unit + t' (d / 2^up).
    let (t_unit, inverse_t_unit) = (units.unit * down, units.inverse * back_up);
    let k = units.inverse_exponent;
    let (Some(o), Some(d), Some(t)) = (normal_power_of_two(k), normal_power_of_two(-up), normal_power_of_two(k + up))
    else {
        return (embree_ray_in_f64(packed, mask, (units.inverse, down, inverse_t_unit)), t_unit);
    };
    // Every factor a normal f32: the f32 product is the exact one rounded once, as the f64
    // product (exact) rounded to f32 is, bit for bit, without two conversions a value (a
    // tenth of a closest hit's time).
    let ray = RtcRay {
        org: [packed[0] * o, packed[1] * o, packed[2] * o],
        tnear: (packed[3] * t).min(f32::MAX),
        dir: [packed[4] * d, packed[5] * d, packed[6] * d],
        time: 0.0,
        tfar: (packed[7] * t).min(f32::MAX),
        mask: u32::from(mask),
        id: 0,
        flags: 0,
    };
    (ray, t_unit)
}

/// `embree_ray` scaled in f64 (exact), where a factor (origin, direction, t) is no normal f32
/// while the products may be.
fn embree_ray_in_f64(packed: &[f32], mask: u8, (origin, direction, t): (f64, f64, f64)) -> RtcRay {
    let scaled = |v: f32, by: f64| (f64::from(v) * by) as f32;
    RtcRay {
        org: [0, 1, 2].map(|k| scaled(packed[k], origin)),
        tnear: scaled(packed[3], t).min(f32::MAX),
        dir: [4, 5, 6].map(|k| scaled(packed[k], direction)),
        time: 0.0,
        tfar: scaled(packed[7], t).min(f32::MAX),
        mask: u32::from(mask),
        id: 0,
        flags: 0,
    }
}

/// `ceil(log2 |x|)`, read from the bits (a logarithm a ray cost a tenth of the trace): None for
/// 0, infinities and NaN.
#[inline(always)]
fn exponent_at_or_above(x: f32) -> Option<i32> {
    let bits = x.to_bits() & 0x7fff_ffff;
    let exponent = (bits >> 23) as i32;
    if bits == 0 || exponent == 0xff {
        return None;
    }
    if exponent == 0 {
        // Subnormal: rare enough for the logarithm.
        return Some(f64::from(x.abs()).log2().ceil() as i32);
    }
    Some(exponent - 127 + i32::from(bits & 0x7f_ffff != 0))
}

/// 2^k in f64 (k within f32's exponents, as `exponent_at_or_above` gives), from its bits.
#[inline(always)]
fn power_of_two(k: i32) -> f64 {
    f64::from_bits(((k + 1023) as u64) << 52)
}

/// Plain lanes (`PlainPacker::lanes`) into `packet` as `embree_ray` makes each ray, with each
/// lane's `t_unit`, where every factor is a normal f32 and each direction's longest component a
/// normal one (false otherwise: `embree_ray` then). No branch a lane, so that the lanes are
/// scaled side by side (packed a ray at a time, then copied into packets, vkray's own work on a
/// camera ray's closest hit was 0.62 of Embree's; lane by lane 0.43).
#[inline(always)]
fn embree_lanes<const K: usize>(lanes: &PlainLanes<K>, units: Units, ready: &mut ReadyPacket<K>) -> bool {
    let k = units.inverse_exponent;
    let Some(o) = normal_power_of_two(k) else { return false };
    let ReadyPacket { packet, t_units, .. } = ready;
    let [dx, dy, dz] = &lanes.directions;
    let mut refused = 0u32;
    for lane in 0..K {
        let bits = dx[lane].abs().max(dy[lane].abs()).max(dz[lane].abs()).to_bits();
        // `exponent_at_or_above` of a normal longest component (the lanes' are finite).
        let exponent = (bits >> 23) as i32;
        let up = exponent - 127 + i32::from(bits & 0x7f_ffff != 0);
        let (down_bits, t_bits) = (127 - up, 127 + k + up);
        let normal = |bits: i32| (1..=254).contains(&bits);
        refused |= u32::from((exponent == 0) | !normal(down_bits) | !normal(t_bits));
        let d = f32::from_bits((down_bits.clamp(1, 254) as u32) << 23);
        let t = f32::from_bits((t_bits.clamp(1, 254) as u32) << 23);
        packet.dir_x[lane] = dx[lane] * d;
        packet.dir_y[lane] = dy[lane] * d;
        packet.dir_z[lane] = dz[lane] * d;
        packet.tnear[lane] = (lanes.interval[0] * t).min(f32::MAX);
        packet.tfar[lane] = (lanes.interval[1] * t).min(f32::MAX);
        t_units[lane] = units.unit * f64::from_bits(((1023 - up).clamp(1, 2046) as u64) << 52);
    }
    for lane in 0..K {
        packet.org_x[lane] = lanes.origins[0][lane] * o;
        packet.org_y[lane] = lanes.origins[1][lane] * o;
        packet.org_z[lane] = lanes.origins[2][lane] * o;
    }
    refused == 0
}

/// A packet of Embree's made ready: its rays, the lanes that hold one (`valid`), and what each
/// lane's `t` is multiplied by to be the caller's (`embree_ray`).
struct ReadyPacket<const K: usize> {
    packet: RtcRayHitPacket<K>,
    valid: RtcValid<K>,
    t_units: [f64; K],
}

impl<const K: usize> ReadyPacket<K> {
    fn new() -> ReadyPacket<K> {
        ReadyPacket { packet: RtcRayHitPacket::default(), valid: RtcValid([0i32; K]), t_units: [1.0f64; K] }
    }

    /// Made ready again for new rays (filled in place: a packet is 700 bytes and more, whose
    /// copies cost more than its packing): no lane valid, no hit.
    #[inline(always)]
    fn clear(&mut self) {
        self.valid = RtcValid([0i32; K]);
        self.packet.geom_id = [INVALID_ID; K];
        self.packet.inst_id = [INVALID_ID; K];
    }

    /// The rays of `packed` (at most `K` packed rays), lane k's mask `mask(k)`.
    fn fill_packed(&mut self, packed: &[f32], mask: impl Fn(usize) -> u8, units: Units) {
        self.clear();
        let ReadyPacket { packet, valid, t_units } = self;
        for (lane, ray) in packed.chunks_exact(RAY_FLOATS).enumerate() {
            let (r, t_unit) = embree_ray(ray, mask(lane), units);
            [packet.org_x[lane], packet.org_y[lane], packet.org_z[lane]] = r.org;
            [packet.dir_x[lane], packet.dir_y[lane], packet.dir_z[lane]] = r.dir;
            (packet.tnear[lane], packet.tfar[lane], packet.mask[lane]) = (r.tnear, r.tfar, r.mask);
            (valid.0[lane], t_units[lane]) = (-1, t_unit);
        }
    }
}

/// Fills `ready` (but its masks) with plain rays `first..first + K` (`PlainPacker::lanes`,
/// `embree_lanes`), where they take that way; false otherwise, and the packet is to be filled
/// again. In AVX2's vectors where the CPU has them (the lanes side by side).
#[inline(always)]
fn fill_plain<const K: usize>(packer: &PlainPacker, first: usize, units: Units, ready: &mut ReadyPacket<K>) -> bool {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        return unsafe { fill_plain_avx2(packer, first, units, ready) };
    }
    fill_plain_here(packer, first, units, ready)
}

/// `fill_plain` compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fill_plain_avx2<const K: usize>(
    packer: &PlainPacker,
    first: usize,
    units: Units,
    ready: &mut ReadyPacket<K>,
) -> bool {
    fill_plain_here(packer, first, units, ready)
}

/// `fill_plain` for the instructions the caller is compiled for.
#[inline(always)]
fn fill_plain_here<const K: usize>(
    packer: &PlainPacker,
    first: usize,
    units: Units,
    ready: &mut ReadyPacket<K>,
) -> bool {
    ready.clear();
    let Some(lanes) = packer.lanes::<K>(first) else { return false };
    if !embree_lanes(&lanes, units, ready) {
        return false;
    }
    ready.valid = RtcValid([-1i32; K]);
    true
}

/// A block's rays as its packets take them: lane by lane from the caller's plain rays where every
/// ray of a packet is valid and near the scene (no pass over the block first), else packed
/// (`pack_block`) packet by packet.
struct BlockRays<'a> {
    rays: &'a Rays<'a>,
    packer: Option<&'a PlainPacker<'a>>,
    frame: &'a Frame,
    /// The block's first ray and its number of rays.
    first: usize,
    count: usize,
    units: Units,
}

impl BlockRays<'_> {
    /// Fills `ready` with packet `p` of the block (rays `p * K..` of it, at most `K`), lane k's
    /// mask `mask(k)`, and adds the advances of its far rays (at their places in the block) to
    /// `advances`.
    fn packet<const K: usize>(
        &self,
        p: usize,
        mask: impl Fn(usize) -> u8,
        (scratch, advances): (&mut [f32], &mut Vec<Advance>),
        ready: &mut ReadyPacket<K>,
    ) -> Result<()> {
        let (first, count) = (self.first + p * K, K.min(self.count - p * K));
        if let Some(packer) = self.packer.filter(|_| count == K) {
            if fill_plain(packer, first, self.units, ready) {
                for lane in 0..K {
                    ready.packet.mask[lane] = u32::from(mask(lane));
                }
                return Ok(());
            }
        }
        let packed = &mut scratch[..count * RAY_FLOATS];
        let far = pack_block(self.rays, self.packer, first, packed, self.frame)?;
        advances.extend(far.into_iter().map(|a| Advance { ray: a.ray + p * K, ..a }));
        ready.fill_packed(packed, mask, self.units);
        Ok(())
    }
}

/// Rays one task of the fast tier packs, traces and writes out at once (the chunk's tasks run on
/// every core, with no pass over the whole chunk between them).
const BLOCK_RAYS: usize = 2048;

/// What every block of a fast-tier query shares.
struct Plan<'a> {
    hierarchy: &'a CpuScene,
    scene: &'a Scene,
    query: Query,
    coherent: bool,
    normals: bool,
    /// Rays a packet takes (1: one ray at a time, through the filter where the query needs it).
    packets: usize,
    /// The scene is one mesh of triangles, unturned and unscaled: every hit's instance is 0 and
    /// its normal Embree's (`unpack_plain`).
    plain_mesh: bool,
}

/// Traces the batch's rays in the fast tier (closest hits, occlusion, counts, transmittance),
/// chunks of at most `chunk` rays paced to a fraction of a second (the interrupt asked between
/// chunks), each chunk in blocks that pack,
/// trace and write every field `sink` asks for (and `hit`).
pub fn trace_fast(
    batch: RayBatch,
    hierarchy: &CpuScene,
    sink: &mut HitSink,
    (chunk, packet_width): (usize, usize),
    profile: &mut TraceProfile,
) -> Result<()> {
    let RayBatch { scene, rays, request, interrupt } = batch;
    let query = request.query;
    if !matches!(query, Query::Closest | Query::Occluded | Query::Count | Query::Transmit) {
        return Err(Error::Unsupported(format!("the CPU engine answers {query:?} through its host tiers")));
    }
    let every = matches!(query, Query::Count | Query::Transmit);
    // Transmittance multiplies over every crossing, whatever its opacity.
    let threshold = if query == Query::Transmit { 0.0 } else { request.opacity_threshold };
    // Closest hits and occlusion with nothing for the filter to do trace in Embree's packets; so
    // do counts and transmittance where the filter needs no ray's direction (no culling).
    let plain = matches!(query, Query::Closest | Query::Occluded)
        && !QueryContext::new(scene, request.cull, threshold, false).needs_filter();
    let every_in_packets = every && request.cull == Cull::None;
    let plan = Plan {
        hierarchy,
        scene,
        query,
        coherent: rays.sensor.is_some(),
        normals: sink.field(Field::Normal).is_some(),
        packets: if plain || every_in_packets { packet_width } else { 1 },
        plain_mesh: matches!(scene.placements.as_slice(),
            [p] if p.mesh.kind == MeshKind::Triangles && p.to_local.linear == DMat3::IDENTITY),
    };
    let (n, frame) = (rays.len(), scene.frame());
    let mut hit = sink.hit.take();
    let packer = rays.plain_packer(&frame);
    let began = Instant::now();
    let first = first_on_cpu(parallel::install(rayon::current_num_threads));
    in_paced_blocks(n, (first, chunk), interrupt, |range| {
        let (start, len) = (range.start, range.len());
        let blocks = block_sinks(sink, hit.as_deref_mut(), start, len);
        let traced = parallel::install(|| {
            blocks.into_par_iter().enumerate().try_for_each_init(
                || {
                    let context = QueryContext::new(scene, request.cull, threshold, every);
                    (context, vec![0f32; BLOCK_RAYS * RAY_FLOATS], vec![MISS; BLOCK_RAYS])
                },
                |(context, scratch, answers), (b, out)| -> Result<()> {
                    let first = start + b * BLOCK_RAYS;
                    let count = BLOCK_RAYS.min(start + len - first);
                    let answers = &mut answers[..count];
                    let units = Units::of(hierarchy);
                    let block = BlockRays { rays, packer: packer.as_ref(), frame: &frame, first, count, units };
                    let advances = trace_block(&plan, context, &block, scratch, answers)?;
                    if query == Query::Closest {
                        add_advances(answers, &advances);
                    }
                    out.write(scene, answers);
                    Ok(())
                },
            )
        });
        if traced.is_err() {
            // A block's error names its own first invalid ray: the caller's is the first of all.
            rays.check()?;
        }
        traced?;
        profile.chunks += 1;
        Ok(())
    })?;
    profile.host_f64 = began.elapsed().as_secs_f64();
    Ok(())
}

/// Answers the rays of `block` (`answers`, one a ray) as `plan` asks; returns the advances of
/// its far rays.
fn trace_block(
    plan: &Plan,
    context: &mut QueryContext,
    block: &BlockRays,
    scratch: &mut [f32],
    answers: &mut [RayAnswer],
) -> Result<Vec<Advance>> {
    let (rays, first) = (block.rays, block.first);
    let mask = |k: usize| rays.mask.get(first + k);
    let every = matches!(plan.query, Query::Count | Query::Transmit);
    Ok(match (plan.packets, every) {
        (16, false) => trace_packets::<16>(plan, block, scratch, answers, mask)?,
        (8, false) => trace_packets::<8>(plan, block, scratch, answers, mask)?,
        (16, true) => trace_every_packets::<16>(plan, context, block, scratch, answers, mask)?,
        (8, true) => trace_every_packets::<8>(plan, context, block, scratch, answers, mask)?,
        _ => {
            let packed = &mut scratch[..block.count * RAY_FLOATS];
            let advances = pack_block(rays, block.packer, first, packed, block.frame)?;
            trace_rays(plan, context, packed, answers, mask);
            advances
        }
    })
}

/// Packs the block of rays from `first` into `packed` as `Rays::pack` does: by `packer` where
/// the rays are plain and every one of the block is valid and near the scene (no pass of
/// `pack`'s own, which a block of a query already on every core need not pay), else by `pack`.
fn pack_block(
    rays: &Rays,
    packer: Option<&PlainPacker>,
    first: usize,
    packed: &mut [f32],
    frame: &Frame,
) -> Result<Vec<Advance>> {
    if let Some(packer) = packer {
        let direct = packed.chunks_exact_mut(RAY_FLOATS).enumerate().all(|(k, out)| match packer.ray(first + k) {
            Some(ray) => {
                out.copy_from_slice(&ray);
                true
            }
            None => false,
        });
        if direct {
            return Ok(Vec::new());
        }
    }
    rays.pack(first, packed, frame)
}

/// Rays one at a time (through the query's filter where it needs one).
fn trace_rays(
    plan: &Plan,
    context: &mut QueryContext,
    packed: &[f32],
    answers: &mut [RayAnswer],
    mask: impl Fn(usize) -> u8,
) {
    let units = Units::of(plan.hierarchy);
    for (k, (answer, ray)) in answers.iter_mut().zip(packed.chunks_exact(RAY_FLOATS)).enumerate() {
        let (ray, t_unit) = embree_ray(ray, mask(k), units);
        *answer = trace_one(plan.hierarchy, context, ray, plan.query, plan.coherent, plan.normals, units.unit);
        if plan.query == Query::Closest && answer.prim >= 0 {
            answer.t = (f64::from(answer.t) * t_unit) as f32;
        }
    }
}

/// Closest hits (or occlusion) of a block's rays in Embree's packets of `K` rays, with no
/// filter: `mask(k)` is ray k's mask; `answers` one per ray. Returns the advances of the block's
/// far rays.
fn trace_packets<const K: usize>(
    plan: &Plan,
    block: &BlockRays,
    scratch: &mut [f32],
    answers: &mut [RayAnswer],
    mask: impl Fn(usize) -> u8,
) -> Result<Vec<Advance>> {
    let units = block.units;
    let order = if plan.coherent { RAY_QUERY_FLAG_COHERENT } else { RAY_QUERY_FLAG_INCOHERENT };
    let mut advances = Vec::new();
    let mut ready = ReadyPacket::<K>::new();
    for (p, answers) in answers.chunks_mut(K).enumerate() {
        block.packet::<K>(p, |lane| mask(p * K + lane), (scratch, &mut advances), &mut ready)?;
        let ReadyPacket { packet, valid, t_units } = &mut ready;
        let mut args = RtcArguments {
            flags: order,
            feature_mask: FEATURE_FLAGS_ALL,
            context: std::ptr::null_mut(),
            filter: None,
            intersect: std::ptr::null_mut(),
            min_width_distance_factor: 0.0,
        };
        let scene = plan.hierarchy.scene();
        if plan.query == Query::Occluded {
            // SAFETY: the scene is committed and held; no context or filter is passed.
            unsafe { scene.trace_packet(valid, packet, &mut args, true) };
            for (lane, answer) in answers.iter_mut().enumerate() {
                *answer = if packet.tfar[lane] == f32::NEG_INFINITY { RayAnswer { prim: 0, ..MISS } } else { MISS };
            }
            continue;
        }
        // SAFETY: as above.
        unsafe { scene.trace_packet(valid, packet, &mut args, false) };
        if plan.plain_mesh {
            unpack_plain(packet, t_units, plan.normals, answers);
            continue;
        }
        for (lane, answer) in answers.iter_mut().enumerate() {
            *answer = if packet.geom_id[lane] == INVALID_ID {
                MISS
            } else {
                let found = nearest(plan.scene, &lane_hit(packet, lane), plan.normals, units.unit);
                RayAnswer { t: (f64::from(found.t) * t_units[lane]) as f32, ..found }
            };
        }
    }
    Ok(advances)
}

/// The answers of a traced packet's lanes (`nearest`'s, bit for bit), one a lane of `answers`,
/// where the scene is one mesh of triangles held as placed (`Plan::plain_mesh`): no placement
/// looked up a hit, and the normals side by side, in AVX2's vectors where the CPU has them.
#[inline(always)]
fn unpack_plain<const K: usize>(
    packet: &RtcRayHitPacket<K>,
    t_units: &[f64; K],
    normals: bool,
    answers: &mut [RayAnswer],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        return unsafe { unpack_plain_avx2(packet, t_units, normals, answers) };
    }
    unpack_plain_here(packet, t_units, normals, answers)
}

/// `unpack_plain` compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unpack_plain_avx2<const K: usize>(
    packet: &RtcRayHitPacket<K>,
    t_units: &[f64; K],
    normals: bool,
    answers: &mut [RayAnswer],
) {
    unpack_plain_here(packet, t_units, normals, answers)
}

/// `unpack_plain` for the instructions the caller is compiled for.
#[inline(always)]
fn unpack_plain_here<const K: usize>(
    packet: &RtcRayHitPacket<K>,
    t_units: &[f64; K],
    normals: bool,
    answers: &mut [RayAnswer],
) {
    let mut normal = [MISS.normal; K];
    if normals {
        for (lane, normal) in normal.iter_mut().enumerate() {
            // `nearest`'s normal of an unturned placement: Embree's, normalized in f64 as
            // `DVec3::normalize` does.
            let [x, y, z] = [packet.ng_x[lane], packet.ng_y[lane], packet.ng_z[lane]].map(f64::from);
            let recip = 1.0 / (x * x + y * y + z * z).sqrt();
            *normal = [(x * recip) as f32, (y * recip) as f32, (z * recip) as f32];
        }
    }
    for (lane, answer) in answers.iter_mut().enumerate() {
        *answer = if packet.geom_id[lane] == INVALID_ID {
            MISS
        } else {
            RayAnswer {
                t: (f64::from(packet.tfar[lane]) * t_units[lane]) as f32,
                uv: [packet.u[lane], packet.v[lane]],
                prim: packet.prim_id[lane] as i32,
                geometry: packet.geom_id[lane] as i32,
                instance: 0,
                normal: normal[lane],
            }
        };
    }
}

/// Counts or transmittance (`plan.query`) of a block's packed rays in Embree's packets of `K`
/// rays, each hit met through the query's filter (which needs no ray's direction: no culling).
fn trace_every_packets<const K: usize>(
    plan: &Plan,
    context: &mut QueryContext,
    block: &BlockRays,
    scratch: &mut [f32],
    answers: &mut [RayAnswer],
    mask: impl Fn(usize) -> u8,
) -> Result<Vec<Advance>> {
    // Counts and transmittance need no advance: nothing lies before an advanced origin.
    let mut advances = Vec::new();
    let mut ready = ReadyPacket::<K>::new();
    for (p, answers) in answers.chunks_mut(K).enumerate() {
        block.packet::<K>(p, |lane| mask(p * K + lane), (scratch, &mut advances), &mut ready)?;
        every_hit_of_packet::<K>(plan.hierarchy, context, &mut ready, plan.coherent);
        let scene = context.scene();
        let mut found = context.sorted_found();
        for (lane, answer) in answers.iter_mut().enumerate() {
            let (mine, rest) = found.split_at(hits_of_lane(found, lane));
            *answer = match plan.query {
                Query::Count => RayAnswer { prim: mine.len() as i32, ..MISS },
                _ => RayAnswer { t: light_through(scene, mine), ..MISS },
            };
            found = rest;
        }
    }
    Ok(Vec::new())
}

/// Traces `ready` as one packet of Embree's through `context`'s filter, which keeps every hit in
/// `context.found` under its lane (`Candidate::ray`); returns each lane's `t_unit` (`embree_ray`).
fn every_hit_of_packet<const K: usize>(
    hierarchy: &CpuScene,
    context: &mut QueryContext,
    ready: &mut ReadyPacket<K>,
    coherent: bool,
) -> [f64; K] {
    let ReadyPacket { packet, valid, t_units } = ready;
    // The filter files each hit under its ray's id.
    packet.id = std::array::from_fn(|lane| lane as u32);
    context.found.clear();
    let mut args = context.arguments(coherent);
    // SAFETY: the scene is committed and held; `args` points into `context`, alive here.
    unsafe { hierarchy.scene().trace_packet(valid, packet, &mut args, false) };
    *t_units
}

/// How many of `found` (sorted by lane, the lanes before `lane` taken off) are lane `lane`'s.
fn hits_of_lane(found: &[Candidate], lane: usize) -> usize {
    found.iter().position(|c| c.ray != lane as u32).unwrap_or(found.len())
}

/// Lane `lane` of a packet, as one ray and its hit.
#[inline(always)]
fn lane_hit<const K: usize>(packet: &RtcRayHitPacket<K>, lane: usize) -> RtcRayHit {
    RtcRayHit {
        ray: RtcRay {
            org: [packet.org_x[lane], packet.org_y[lane], packet.org_z[lane]],
            tnear: packet.tnear[lane],
            dir: [packet.dir_x[lane], packet.dir_y[lane], packet.dir_z[lane]],
            time: 0.0,
            tfar: packet.tfar[lane],
            mask: packet.mask[lane],
            id: 0,
            flags: 0,
        },
        hit: RtcHit {
            ng: [packet.ng_x[lane], packet.ng_y[lane], packet.ng_z[lane]],
            uv: [packet.u[lane], packet.v[lane]],
            prim_id: packet.prim_id[lane],
            geom_id: packet.geom_id[lane],
            inst_id: [packet.inst_id[lane]],
            inst_prim_id: [packet.inst_prim_id[lane]],
        },
    }
}

/// Moves the hits of rays advanced before packing back to their distances from the real origin.
fn add_advances(answers: &mut [RayAnswer], advances: &[Advance]) {
    for advance in advances {
        let answer = &mut answers[advance.ray];
        if answer.prim >= 0 {
            answer.t = (f64::from(answer.t) + advance.t) as f32;
        }
    }
}

/// One ray's answer to `query`.
fn trace_one(
    hierarchy: &CpuScene,
    context: &mut QueryContext,
    ray: RtcRay,
    query: Query,
    coherent: bool,
    normals: bool,
    unit: f64,
) -> RayAnswer {
    context.direction = DVec3::new(f64::from(ray.dir[0]), f64::from(ray.dir[1]), f64::from(ray.dir[2]));
    context.found.clear();
    let mut args = context.arguments(coherent);
    if query == Query::Occluded {
        let mut ray = ray;
        // SAFETY: the scene is committed and held; `args` points into `context`, alive here.
        unsafe { hierarchy.scene().occluded(&mut ray, &mut args) };
        return if ray.tfar == f32::NEG_INFINITY { RayAnswer { prim: 0, ..MISS } } else { MISS };
    }
    let mut rayhit =
        RtcRayHit { ray, hit: RtcHit { geom_id: INVALID_ID, inst_id: [INVALID_ID], ..Default::default() } };
    // SAFETY: as above.
    unsafe { hierarchy.scene().intersect(&mut rayhit, &mut args) };
    match query {
        Query::Count => RayAnswer { prim: context.sorted_found().len() as i32, ..MISS },
        Query::Transmit => RayAnswer { t: light_through(context.scene(), context.sorted_found()), ..MISS },
        _ if rayhit.hit.geom_id == INVALID_ID => MISS,
        _ => nearest(context.scene(), &rayhit, normals, unit),
    }
}

/// The light a ray keeps: the product of (1 - opacity) over the triangles it crossed (`found`,
/// sorted, without repeats).
fn light_through(scene: &Scene, found: &[Candidate]) -> f32 {
    let kept = found.iter().fold(1.0f64, |left, c| {
        let placement = &scene.placements[c.instance as usize];
        let opacity = match (&placement.mesh.opacity, placement.flags.force_opaque) {
            (Some(o), false) => f64::from(o[placement.triangles.global(c.geometry as usize, c.prim as usize)]),
            _ => 1.0,
        };
        left * (1.0 - opacity)
    });
    kept as f32
}

/// The answer of a closest hit: its ids, barycentrics (NaN on spheres) and, where asked, the
/// world normal (from the f64 triangle, or the sphere at the hit; the ray in `unit`s).
#[inline(always)]
fn nearest(scene: &Scene, rayhit: &RtcRayHit, normals: bool, unit: f64) -> RayAnswer {
    let (hit, ray) = (&rayhit.hit, &rayhit.ray);
    // No instance id: a one-instance scene traced without its instance level.
    let instance = if hit.inst_id[0] == INVALID_ID { 0 } else { hit.inst_id[0] };
    let placement = &scene.placements[instance as usize];
    let spheres = placement.mesh.kind == MeshKind::Spheres;
    let normal = if !normals {
        [f32::NAN; 3]
    } else if spheres {
        let (center, radius) = placement.mesh.spheres[hit.prim_id as usize];
        let along = |k: usize| unit * (f64::from(ray.org[k]) + f64::from(ray.tfar) * f64::from(ray.dir[k]));
        let local = placement.to_local.point(DVec3::new(along(0), along(1), along(2)));
        (placement.to_local.linear.transpose() * ((local - center) / radius)).normalize().as_vec3().to_array()
    } else {
        // Embree's geometric normal, cross(v1 - v0, v2 - v0) in the mesh's frame (f32, as the
        // GPU's), into the world as `world_normal` takes a triangle's.
        let ng = DVec3::new(f64::from(hit.ng[0]), f64::from(hit.ng[1]), f64::from(hit.ng[2]));
        let linear = &placement.to_local.linear;
        // An unturned, unscaled placement (the usual one) maps normals to themselves: the same
        // answer, bit for bit, without a determinant and a product a hit.
        let world =
            if *linear == DMat3::IDENTITY { ng } else { linear.determinant().signum() * (linear.transpose() * ng) };
        world.normalize().as_vec3().to_array()
    };
    RayAnswer {
        t: ray.tfar,
        uv: if spheres { [f32::NAN; 2] } else { hit.uv },
        prim: hit.prim_id as i32,
        geometry: hit.geom_id as i32,
        instance: instance as i32,
        normal,
    }
}

/// One block's share of the caller's fields (and `hit`).
#[derive(Default)]
struct BlockSink<'a> {
    fields: Vec<(Field, &'a mut [u8])>,
    hit: Option<&'a mut [u8]>,
}

/// The fields of rays `start..start + len` cut into blocks of `BLOCK_RAYS` rays.
fn block_sinks<'a>(sink: &'a mut HitSink, hit: Option<&'a mut [u8]>, start: usize, len: usize) -> Vec<BlockSink<'a>> {
    let mut blocks: Vec<BlockSink> = (0..len.div_ceil(BLOCK_RAYS)).map(|_| BlockSink::default()).collect();
    if let Some(hit) = hit {
        for (block, piece) in blocks.iter_mut().zip(hit[start..start + len].chunks_mut(BLOCK_RAYS)) {
            block.hit = Some(piece);
        }
    }
    for (field, out) in sink.iter_mut() {
        let width = field.bytes_per_ray(false);
        let pieces = out[start * width..(start + len) * width].chunks_mut(BLOCK_RAYS * width);
        for (block, piece) in blocks.iter_mut().zip(pieces) {
            block.fields.push((field, piece));
        }
    }
    blocks
}

impl BlockSink<'_> {
    /// Writes the block's answers into its fields: a loop a field, each element typed (a match
    /// on the field an element had cost a fifth of a closest-hit query's time).
    fn write(self, scene: &Scene, answers: &[RayAnswer]) {
        let custom = |a: &RayAnswer| match a.instance {
            -1 => -1,
            k => scene.placements[k as usize].custom_index as i32,
        };
        for (field, out) in self.fields {
            match field {
                Field::T => fill(out, answers, |a| a.t),
                Field::Prim => fill(out, answers, |a| a.prim),
                Field::Instance => fill(out, answers, |a| a.instance),
                Field::Custom => fill(out, answers, custom),
                Field::Geometry => fill(out, answers, |a| a.geometry),
                Field::Uv => fill(out, answers, |a| a.uv),
                Field::Normal => fill(out, answers, |a| a.normal),
            }
        }
        if let Some(hit) = self.hit {
            for (h, a) in hit.iter_mut().zip(answers) {
                *h = u8::from(a.prim >= 0);
            }
        }
    }
}

/// Each answer's `value` into `out`, a field's bytes: as typed elements where they are aligned
/// (numpy's arrays are), else byte by byte.
fn fill<T: bytemuck::Pod>(out: &mut [u8], answers: &[RayAnswer], value: impl Fn(&RayAnswer) -> T) {
    match bytemuck::try_cast_slice_mut::<u8, T>(out) {
        Ok(typed) => typed.iter_mut().zip(answers).for_each(|(dst, a)| *dst = value(a)),
        Err(_) => out
            .chunks_exact_mut(std::mem::size_of::<T>())
            .zip(answers)
            .for_each(|(dst, a)| dst.copy_from_slice(bytemuck::bytes_of(&value(a)))),
    }
}

/// Every hit of every ray in the fast tier (the nearest `max_hits` of each, f32 values), chunk
/// by chunk; refused (MemoryError) before it grows past what the host can hold with
/// `host_bytes_per_hit` more a hit for the caller.
pub fn all_hits_fast(
    batch: RayBatch,
    hierarchy: &CpuScene,
    (max_hits, host_bytes_per_hit): (usize, usize),
    (chunk, packet_width): (usize, usize),
    mut hits: Vec<ReferenceHit>,
) -> Result<AllHits> {
    let RayBatch { scene, rays, request, interrupt } = batch;
    if request.cull != crate::geometry::precision::Cull::None && max_hits == 0 {
        return Err(invalid_value("max_hits must be at least 1"));
    }
    let (n, frame) = (rays.len(), scene.frame());
    let mut packed = try_vec(chunk.min(n) * RAY_FLOATS, 0f32, "the CPU engine's rays")?;
    // Packets where the filter needs no ray's direction (no culling).
    let packets = if request.cull == Cull::None { packet_width } else { 1 };
    let coherent = rays.sensor.is_some();
    let mut offsets: Vec<i64> = try_zeroed(n + 1, "the offsets of all hits")?;
    hits.clear();
    let first = first_on_cpu(parallel::install(rayon::current_num_threads));
    in_paced_blocks(n, (first, chunk), interrupt, |range| {
        let (start, len) = (range.start, range.len());
        let advances = rays.pack(start, &mut packed[..len * RAY_FLOATS], &frame)?;
        // Each block's hits in one list and its rays' counts (no list a ray).
        let blocks: Vec<(Vec<u32>, Vec<ReferenceHit>)> = parallel::install(|| {
            packed[..len * RAY_FLOATS]
                .par_chunks(BLOCK_RAYS * RAY_FLOATS)
                .enumerate()
                .map_init(
                    || QueryContext::new(scene, request.cull, request.opacity_threshold, true),
                    |context, (b, block)| {
                        let mask = |k: usize| rays.mask.get(start + b * BLOCK_RAYS + k);
                        let mut kept =
                            KeptHits { scene, max_hits, counts: Vec::with_capacity(BLOCK_RAYS), found: Vec::new() };
                        match packets {
                            16 => kept.trace_packets::<16>(hierarchy, context, block, mask, coherent),
                            8 => kept.trace_packets::<8>(hierarchy, context, block, mask, coherent),
                            _ => kept.trace_rays(hierarchy, context, block, mask),
                        }
                        (kept.counts, kept.found)
                    },
                )
                .collect()
        });
        let added: usize = blocks.iter().map(|(_, found)| found.len()).sum();
        check_hits_fit(hits.len() + added, std::mem::size_of::<ReferenceHit>() + host_bytes_per_hit)?;
        hits.try_reserve(added)
            .map_err(|_| Error::OutOfMemory(format!("{} hits do not fit in host memory", hits.len() + added)))?;
        place_blocks(&blocks, &mut offsets[start..start + len + 1], &mut hits);
        for advance in &advances {
            let r = start + advance.ray;
            for hit in &mut hits[offsets[r] as usize..offsets[r + 1] as usize] {
                hit.t = f64::from((hit.t + advance.t) as f32);
            }
        }
        Ok(())
    })?;
    Ok(AllHits { offsets, hits, wide: false })
}

/// A block's hits as all hits keep them: the nearest `max_hits` of each ray, with its count.
struct KeptHits<'a> {
    scene: &'a Scene,
    max_hits: usize,
    counts: Vec<u32>,
    found: Vec<ReferenceHit>,
}

impl KeptHits<'_> {
    /// Keeps the hits of the sorted `found` (one ray's) at `t_unit` (`embree_ray`).
    fn keep(&mut self, found: &[Candidate], t_unit: f64) {
        let kept = &found[..found.len().min(self.max_hits)];
        self.found.extend(kept.iter().map(|c| reference_hit(self.scene, c, t_unit)));
        self.counts.push(kept.len() as u32);
    }

    /// The block's packed rays one at a time (culling asks each ray's direction).
    fn trace_rays(
        &mut self,
        hierarchy: &CpuScene,
        context: &mut QueryContext,
        block: &[f32],
        mask: impl Fn(usize) -> u8,
    ) {
        let units = Units::of(hierarchy);
        for (k, ray) in block.chunks_exact(RAY_FLOATS).enumerate() {
            let (ray, t_unit) = embree_ray(ray, mask(k), units);
            trace_one(hierarchy, context, ray, Query::Count, false, false, units.unit);
            self.keep(context.sorted_found(), t_unit);
        }
    }

    /// The block's packed rays in Embree's packets of `K`.
    fn trace_packets<const K: usize>(
        &mut self,
        hierarchy: &CpuScene,
        context: &mut QueryContext,
        block: &[f32],
        mask: impl Fn(usize) -> u8,
        coherent: bool,
    ) {
        let units = Units::of(hierarchy);
        let mut ready = ReadyPacket::<K>::new();
        for (p, rays) in block.chunks(K * RAY_FLOATS).enumerate() {
            ready.fill_packed(rays, |lane| mask(p * K + lane), units);
            let t_units = every_hit_of_packet::<K>(hierarchy, context, &mut ready, coherent);
            let mut found = context.sorted_found();
            for (lane, &t_unit) in t_units.iter().enumerate().take(rays.len() / RAY_FLOATS) {
                let (mine, rest) = found.split_at(hits_of_lane(found, lane));
                self.keep(mine, t_unit);
                found = rest;
            }
        }
    }
}

/// Appends each block's hits to `hits` (room reserved) and writes its rays' offsets after
/// `offsets[0]` (the first ray's, written already), the blocks side by side on all cores.
fn place_blocks(blocks: &[(Vec<u32>, Vec<ReferenceHit>)], offsets: &mut [i64], hits: &mut Vec<ReferenceHit>) {
    let base = hits.len();
    let mut parts = Vec::with_capacity(blocks.len());
    let mut at = offsets[0];
    let (mut rest, mut rays) = (&mut hits.spare_capacity_mut()[..], &mut offsets[1..]);
    for (counts, found) in blocks {
        let (part, tail) = std::mem::take(&mut rest).split_at_mut(found.len());
        let (ends, more) = std::mem::take(&mut rays).split_at_mut(counts.len());
        parts.push((at, part, ends, counts, found));
        (rest, rays, at) = (tail, more, at + found.len() as i64);
    }
    parallel::install(|| {
        parts.into_par_iter().for_each(|(at, part, ends, counts, found)| {
            for (slot, hit) in part.iter_mut().zip(found) {
                slot.write(*hit);
            }
            let mut end = at;
            for (out, &count) in ends.iter_mut().zip(counts.iter()) {
                end += i64::from(count);
                *out = end;
            }
        })
    });
    let added: usize = blocks.iter().map(|(_, found)| found.len()).sum();
    // SAFETY: the parts cover the `added` entries after the first `base`, each written above.
    unsafe { hits.set_len(base + added) };
}

/// A fast-tier hit as every-hit answers hold it: f32 values, the triangle among all parts (`t`
/// times `t_unit`: see `embree_ray`).
fn reference_hit(scene: &Scene, c: &Candidate, t_unit: f64) -> ReferenceHit {
    let placement = &scene.placements[c.instance as usize];
    ReferenceHit {
        t: f64::from((f64::from(c.t) * t_unit) as f32),
        u: f64::from(c.u),
        v: f64::from(c.v),
        instance: c.instance,
        prim: placement.triangles.global(c.geometry as usize, c.prim as usize) as u32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exponent read from the bits is the logarithm's, powers of two and subnormals too.
    #[test]
    fn exponents_from_bits_are_the_ceiling_of_the_logarithm() {
        for x in [1.0f32, 0.75, 2.0, 3.0, 1e-20, 3e38, -5.5, 1e-40, f32::MIN_POSITIVE, 1.0 + f32::EPSILON] {
            let expected = f64::from(x.abs()).log2().ceil() as i32;
            assert_eq!(exponent_at_or_above(x), Some(expected), "{x}");
            assert_eq!(power_of_two(expected), 2f64.powi(expected));
        }
        for x in [0.0f32, -0.0, f32::INFINITY, f32::NAN] {
            assert_eq!(exponent_at_or_above(x), None);
        }
    }

    /// The f32 scaling gives the f64 one's rays bit for bit, subnormal products, infinite
    /// intervals and the largest scales too.
    #[test]
    fn rays_scaled_in_f32_equal_those_scaled_in_f64() {
        let values = [0.0f32, -0.0, 1.0, -0.7, 0.3, 1e-30, -1e-38, 1e-44, 3e38, -2.5e37, 123.456, f32::INFINITY];
        let (mut checked, mut in_f32) = (0, 0);
        for unit_exponent in [-120, -20, -2, 0, 3, 60, 126] {
            let unit = 2f64.powi(unit_exponent);
            let units = Units::new(unit);
            assert_eq!(units.inverse_exponent, -unit_exponent);
            for (i, &a) in values.iter().enumerate() {
                for (j, &b) in values.iter().enumerate() {
                    let direction = [a, b, values[(i + j) % values.len()]];
                    if !direction.iter().all(|c| c.is_finite()) || direction == [0.0; 3] {
                        continue;
                    }
                    let origin =
                        [b, a, values[(i * 3 + j) % values.len()]].map(|c| if c.is_finite() { c } else { 1.0 });
                    let packed =
                        [origin[0], origin[1], origin[2], a.abs(), direction[0], direction[1], direction[2], b.abs()];
                    let (ray, t_unit) = embree_ray(&packed, 3, units);
                    let longest = direction.iter().fold(0f32, |m, c| m.max(c.abs()));
                    let up = exponent_at_or_above(longest).unwrap();
                    let k = units.inverse_exponent;
                    in_f32 += [k, -up, k + up].iter().all(|&e| normal_power_of_two(e).is_some()) as usize;
                    let wide = embree_ray_in_f64(
                        &packed,
                        3,
                        (units.inverse, power_of_two(-up), units.inverse * power_of_two(up)),
                    );
                    let bits = |r: &RtcRay| [r.org, [r.tnear; 3], r.dir, [r.tfar; 3]].map(|v| v.map(f32::to_bits));
                    assert_eq!(bits(&ray), bits(&wide), "{packed:?} in units of {unit}");
                    assert_eq!(t_unit, unit * power_of_two(-up));
                    checked += 1;
                }
            }
        }
        assert!(checked > 500 && in_f32 > 300, "{checked} rays, {in_f32} scaled in f32");
    }

    /// The lanes' answers (`unpack_plain`) are `nearest`'s normals (`DVec3::normalize`), bit for
    /// bit, with their `t` in the caller's units.
    #[test]
    fn answers_of_plain_lanes_are_those_of_nearest() {
        let values = [1.0f32, -0.7, 0.3, 1e-30, -1e-38, 3e38, 123.456, 0.0, 1e-7, -2.5e-3, 7.0e5];
        let mut packet = RtcRayHitPacket::<8>::default();
        let mut answers = [MISS; 8];
        let mut checked = 0;
        for (i, &a) in values.iter().enumerate() {
            for (j, &b) in values.iter().enumerate() {
                for lane in 0..8 {
                    let c = values[(i + j + lane) % values.len()];
                    [packet.ng_x[lane], packet.ng_y[lane], packet.ng_z[lane]] = [a, b * (lane as f32 + 1.0), c];
                    (packet.geom_id[lane], packet.prim_id[lane], packet.tfar[lane]) = (0, lane as u32, 2.5);
                }
                packet.geom_id[7] = INVALID_ID;
                unpack_plain(&packet, &[0.5; 8], true, &mut answers[..7]);
                for (lane, answer) in answers.iter().enumerate().take(7) {
                    let ng = DVec3::new(packet.ng_x[lane].into(), packet.ng_y[lane].into(), packet.ng_z[lane].into());
                    let expected = ng.normalize().as_vec3().to_array().map(f32::to_bits);
                    assert_eq!(answer.normal.map(f32::to_bits), expected, "{ng:?}");
                    assert_eq!((answer.t, answer.prim, answer.instance, answer.geometry), (1.25, lane as i32, 0, 0));
                    checked += 1;
                }
                unpack_plain(&packet, &[0.5; 8], false, &mut answers);
                assert_eq!((answers[7].prim, answers[0].normal[0].is_nan()), (-1, true));
            }
        }
        assert!(checked > 800);
    }

    /// Packets filled lane by lane from plain rays (`fill_plain`) equal those of the rays packed
    /// one at a time (`pack_block`, `embree_ray`) bit for bit, and are refused exactly where a
    /// ray is invalid or far (or a factor no normal f32).
    #[test]
    fn packets_of_plain_lanes_equal_packets_of_packed_rays() {
        use crate::geometry::arrays::Vec3s;
        use crate::geometry::rays::{Masks, PerRay};
        const K: usize = 8;
        let values = [1.0f32, -0.7, 0.3, 1e-30, -1e-38, 1e-44, 3e38, 123.456, 0.0, -0.0, 1e7, f32::NAN];
        let (mut origins, mut directions) = (Vec::new(), Vec::new());
        for i in 0..values.len() * values.len() * 12 {
            let pick = |k: usize| values[(i / values.len().pow(k as u32 % 2 + 1) + k * i) % values.len()];
            // Mostly ordinary rays, so that most packets are whole; a few of every kind.
            let odd = i % 19 == 0;
            let o = if odd { [pick(0), pick(1), pick(2)] } else { [0.1 * (i % 7) as f32, -0.2, 0.05 * (i % 3) as f32] };
            let d = if odd {
                [pick(3), pick(4), pick(5)]
            } else {
                [0.3, -0.2 * (i % 11) as f32, 1.0 / (1 + i % 13) as f32]
            };
            origins.extend(o);
            directions.extend(d);
        }
        let rays = Rays {
            origins: Vec3s::F32(&origins),
            directions: Vec3s::F32(&directions),
            tmin: PerRay::All(0.0),
            tmax: PerRay::All(f64::INFINITY),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        let n = rays.len();
        let (mut whole, mut refused) = (0, 0);
        for unit_exponent in [-120, -3, 0, 5, 126] {
            let units = Units::new(2f64.powi(unit_exponent));
            for frame in [
                Frame::new(DVec3::ZERO, DVec3::ZERO, 1.0),
                Frame::new(DVec3::new(0.1, -0.2, 0.3), DVec3::new(0.01, 0.0, 0.0), 2.0),
                Frame::new(DVec3::new(1e7, 0.0, -1e7), DVec3::ZERO, 1e8),
            ] {
                let packer = rays.plain_packer(&frame).expect("plain rays");
                let mut scratch = vec![0f32; K * RAY_FLOATS];
                for first in (0..n - K).step_by(K) {
                    let (mut lanes, mut packed) = (ReadyPacket::<K>::new(), ReadyPacket::<K>::new());
                    let by_lanes = fill_plain(&packer, first, units, &mut lanes);
                    let each = (first..first + K).all(|i| packer.ray(i).is_some());
                    if !each {
                        assert!(!by_lanes, "rays {first}.. has an invalid or far ray");
                        continue;
                    }
                    pack_block(&rays, Some(&packer), first, &mut scratch, &frame).expect("valid rays");
                    packed.fill_packed(&scratch, |_| 0, units);
                    let scaled_in_f32 = (0..K).all(|lane| {
                        let longest = scratch[lane * RAY_FLOATS + 4..lane * RAY_FLOATS + 7]
                            .iter()
                            .fold(0f32, |m, c| m.max(c.abs()));
                        let up = exponent_at_or_above(longest).unwrap();
                        let k = units.inverse_exponent;
                        longest.is_normal() && [k, -up, k + up].iter().all(|&e| normal_power_of_two(e).is_some())
                    });
                    assert_eq!(by_lanes, scaled_in_f32, "rays {first}.., units 2^{unit_exponent}");
                    if !by_lanes {
                        refused += 1;
                        continue;
                    }
                    let (a, b) = (&lanes.packet, &packed.packet);
                    let bits = |p: &RtcRayHitPacket<K>| {
                        [p.org_x, p.org_y, p.org_z, p.tnear, p.dir_x, p.dir_y, p.dir_z, p.tfar]
                            .map(|v| v.map(f32::to_bits))
                    };
                    assert_eq!(bits(a), bits(b), "rays {first}.., units 2^{unit_exponent}");
                    assert_eq!(lanes.t_units, packed.t_units);
                    assert_eq!(lanes.valid.0, packed.valid.0);
                    whole += 1;
                }
            }
        }
        assert!(whole > 200 && refused > 10, "{whole} packets filled by lanes, {refused} refused");
    }
}

//! Batches of rays as the caller gave them: checks, and packing into the GPU's ray records.
//! Bad rays become an error naming the argument and the first offending row.

use glam::DVec3;
use rayon::prelude::*;

use super::arrays::{fmt_row, Vec3s};
use super::parallel;
use super::precision::{Aabb, Ray64};
use super::sensor::SensorRays;
use crate::error::{invalid_value, Result};

/// A per-ray interval bound: one value for every ray, or one per ray.
#[derive(Clone, Copy, Debug)]
pub enum PerRay<'a> {
    All(f64),
    Each(&'a [f64]),
}

impl PerRay<'_> {
    #[inline(always)]
    pub fn get(&self, i: usize) -> f64 {
        match self {
            PerRay::All(v) => *v,
            PerRay::Each(v) => v[i],
        }
    }
}

/// Per-ray 8-bit visibility masks: a ray sees an instance when `instance mask & ray mask != 0`.
#[derive(Clone, Copy, Debug)]
pub enum Masks<'a> {
    All(u8),
    Each(&'a [u8]),
}

impl Masks<'_> {
    #[inline]
    pub fn get(&self, i: usize) -> u8 {
        match self {
            Masks::All(m) => *m,
            Masks::Each(m) => m[i],
        }
    }
}

/// A batch of rays as the caller gave it. `origins` or `directions` may hold a single row shared
/// by every ray (a camera's eye), so that broadcasting never copies it; per-ray bounds then give
/// the batch its size.
#[derive(Clone, Copy, Debug)]
pub struct Rays<'a> {
    pub origins: Vec3s<'a>,
    pub directions: Vec3s<'a>,
    pub tmin: PerRay<'a>,
    pub tmax: PerRay<'a>,
    pub mask: Masks<'a>,
    /// Rays a sensor generates instead of `origins` and `directions` (which are then empty).
    pub sensor: Option<&'a SensorRays>,
}

/// Floats one packed ray takes: origin, tmin, direction, tmax.
pub const RAY_FLOATS: usize = 8;

/// How a chunk's f32 rays lie in staging for the shaders (their RAY_SOURCE).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayLayout {
    /// `RAY_FLOATS` a ray: origin, tmin, direction, tmax.
    Full,
    /// A header of `RAY_HEADER_FLOATS` (the shared interval: tmin at 3, tmax at 7), then 6 f32 a
    /// ray: origin, direction (rays of one interval: 24 bytes a ray written instead of 32).
    Compact,
    /// A header of `RAY_HEADER_FLOATS` (the shared origin at 0..3, tmin at 3, tmax at 7), then 3
    /// f32 a ray: its direction (rays from one origin, a camera's: 12 bytes a ray).
    Directions,
}

/// Floats of the header of the `Compact` and `Directions` layouts (two aligned vec4).
pub const RAY_HEADER_FLOATS: usize = 8;

/// Floats of the header of the exact tier's `Compact` and `Directions` layouts (shaders/exact.glsl
/// `ExactRayHeader`): the shift into the scene's frame, tmin and tmax in f64, then the shared
/// origin in f32.
pub const EXACT_HEADER_FLOATS: usize = 16;

impl RayLayout {
    pub fn floats_per_ray(self) -> usize {
        match self {
            RayLayout::Full => RAY_FLOATS,
            RayLayout::Compact => 6,
            RayLayout::Directions => 3,
        }
    }

    /// Bytes `n` rays take in this layout, with its header.
    pub fn bytes(self, n: usize) -> usize {
        let header = if self == RayLayout::Full { 0 } else { RAY_HEADER_FLOATS };
        4 * (header + n * self.floats_per_ray())
    }

    /// Bytes `n` rays of the exact tier take in this layout, with its header (f64 rays in the full
    /// one).
    pub fn exact_bytes(self, n: usize) -> usize {
        match self {
            RayLayout::Full => 8 * RAY_FLOATS * n,
            _ => 4 * (EXACT_HEADER_FLOATS + n * self.floats_per_ray()),
        }
    }
}

/// Rays one thread checks and packs at a time at most: large enough to amortize scheduling.
const PACK_PIECE: usize = 1 << 14;
/// Rays one thread checks and packs at a time at least (`pack_piece_rays`).
const SMALLEST_PACK_PIECE: usize = 1 << 10;

/// Rays a piece of a pack of `rays` rays takes: `PACK_PIECE`, or fewer where that would leave
/// cores idle (about four pieces a thread of the pool the pack runs on). The rays a GPU chunk
/// packs travel over the bus as they are written, at a few GB/s a thread: on an H200's host, the
/// 32k points a `contains` grid left undecided packed in 0.39 ms on the two threads of two whole
/// pieces, in 0.11 ms in pieces for 16 threads (50k rays: 0.19 -> 0.09 ms).
fn pack_piece_rays(rays: usize) -> usize {
    let threads = parallel::install(rayon::current_num_threads).max(1);
    rays.div_ceil(4 * threads).clamp(SMALLEST_PACK_PIECE, PACK_PIECE)
}

impl<'a> Rays<'a> {
    /// These rays with their origins as one row shared by every ray where each ray's origin is
    /// the first's, bit for bit (a camera's rays with their origin repeated, as trimesh's
    /// `camera_rays` gives them): the GPU then packs and uploads only the directions (12 bytes a
    /// ray, not 24) and the CPU engine reads one origin. A pass over the origins on all cores,
    /// after the first rows show them equal (other rays differ at once); `Tracer`'s ray queries
    /// take it (with the GIL released, on the device's host threads).
    pub fn sharing_origin(&self) -> Rays<'a> {
        let n = self.len();
        // The directions keep the batch's length (one row of each would make it one ray).
        if self.sensor.is_some() || n < 2 || self.origins.rows() != n || self.directions.rows() != n {
            return *self;
        }
        let origins = match self.origins {
            Vec3s::F32(o) if same_rows(o) => Vec3s::F32(&o[..3]),
            Vec3s::F64(o) if same_rows(o) => Vec3s::F64(&o[..3]),
            _ => return *self,
        };
        Rays { origins, ..*self }
    }
}

/// Whether every row of the 3-column `values` is the first, bit for bit.
fn same_rows<T: bytemuck::Pod + Sync>(values: &[T]) -> bool {
    // As rows of 32-bit words (an f32 row is 3 of them, an f64 row 6), compared without a call:
    // a byte slice's `==` calls memcmp, a row of 12 bytes each (3% of a CPU engine's camera
    // query; on an H200's 16 cores 0.35 ms of a count of 1M camera rays, 0.13 now).
    let rows = match std::mem::size_of::<T>() {
        4 => bytemuck::try_cast_slice::<T, [u32; 3]>(values).ok().map(rows_equal),
        8 => bytemuck::try_cast_slice::<T, [u32; 6]>(values).ok().map(rows_equal),
        _ => None,
    };
    rows.unwrap_or_else(|| {
        let bytes: &[u8] = bytemuck::cast_slice(values);
        let row = 3 * std::mem::size_of::<T>();
        bytes.chunks_exact(row).all(|r| r == &bytes[..row])
    })
}

/// Whether every one of `rows` is the first.
fn rows_equal<const N: usize>(rows: &[[u32; N]]) -> bool {
    let Some((first, rest)) = rows.split_first() else { return true };
    // Differences OR-ed over a block of rows (no branch a row: vectorized), the block's verdict
    // then.
    let differ = |block: &[[u32; N]]| block.iter().fold(0u32, |acc, r| (0..N).fold(acc, |a, k| a | (r[k] ^ first[k])));
    // A few rows first: rays from different origins differ at once, without waking the cores.
    let (head, tail) = rest.split_at(rest.len().min(64));
    if differ(head) != 0 {
        return false;
    }
    parallel::install(|| tail.par_chunks(1 << 14).all(|block| differ(block) == 0))
}

impl Rays<'_> {
    /// The batch size: the longest of the four arrays (the others have one row or value).
    pub fn len(&self) -> usize {
        if let Some(sensor) = self.sensor {
            return sensor.len();
        }
        let bound_len = |b: PerRay| match b {
            PerRay::All(_) => 0,
            PerRay::Each(v) => v.len(),
        };
        let mask_len = match self.mask {
            Masks::All(_) => 0,
            Masks::Each(m) => m.len(),
        };
        self.origins
            .rows()
            .max(self.directions.rows())
            .max(bound_len(self.tmin))
            .max(bound_len(self.tmax))
            .max(mask_len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    #[inline(always)]
    fn origin(&self, i: usize) -> [f32; 3] {
        if let Some(sensor) = self.sensor {
            return sensor.ray(i).0;
        }
        self.origins.row_f32(if self.origins.rows() == 1 { 0 } else { i })
    }

    #[inline(always)]
    fn direction(&self, i: usize) -> [f32; 3] {
        if let Some(sensor) = self.sensor {
            return sensor.ray(i).1;
        }
        self.directions.row_f32(if self.directions.rows() == 1 { 0 } else { i })
    }

    /// Ray `i` in f64, its origin shifted by `-shift` (into a scene's frame).
    #[inline(always)]
    pub fn ray64(&self, i: usize, shift: DVec3) -> Ray64 {
        Ray64 {
            origin: self.origin64(i, shift),
            direction: self.direction64(i),
            tmin: self.tmin.get(i),
            tmax: self.tmax.get(i),
        }
    }

    /// Ray `i`'s origin in f64, shifted by `-shift`.
    #[inline(always)]
    fn origin64(&self, i: usize, shift: DVec3) -> DVec3 {
        if self.sensor.is_some() {
            return DVec3::from_array(self.origin(i).map(f64::from)) - shift;
        }
        DVec3::from_array(self.origins.row_f64(if self.origins.rows() == 1 { 0 } else { i })) - shift
    }

    #[inline(always)]
    fn direction64(&self, i: usize) -> DVec3 {
        if self.sensor.is_some() {
            return DVec3::from_array(self.direction(i).map(f64::from));
        }
        DVec3::from_array(self.directions.row_f64(if self.directions.rows() == 1 { 0 } else { i }))
    }

    /// The sensor whose rays the GPU may generate itself: these rays' sensor, if none of its rays
    /// is far enough from the scene for the host to advance it (the shaders do not advance rays).
    pub fn generated_on_gpu(&self, frame: &Frame) -> Option<&SensorRays> {
        let sensor = self.sensor?;
        let near =
            sensor.extreme_origins().iter().all(|o| !frame.is_far(DVec3::from_array(o.map(f64::from)) - frame.shift));
        near.then_some(sensor)
    }

    /// Array lengths must agree (one shared origin or direction row is allowed).
    pub fn check_shapes(&self) -> Result<()> {
        if let Some(sensor) = self.sensor {
            // A sensor's rays share its interval and one mask.
            sensor.check()?;
            return match (self.mask, self.tmin, self.tmax) {
                (Masks::All(_), PerRay::All(_), PerRay::All(_)) => Ok(()),
                _ => Err(invalid_value("a sensor's rays share one mask and the sensor's range")),
            };
        }
        let n = self.len();
        for (name, rows) in [("origins", self.origins.rows()), ("directions", self.directions.rows())] {
            if rows != n && rows != 1 {
                return Err(invalid_value(format!("{name} has {rows} rows for {n} rays")));
            }
        }
        for (name, bound) in [("tmin", self.tmin), ("tmax", self.tmax)] {
            if let PerRay::Each(values) = bound {
                if values.len() != n {
                    return Err(invalid_value(format!("{name} has {} values for {n} rays", values.len())));
                }
            }
        }
        if let Masks::Each(masks) = self.mask {
            if masks.len() != n {
                return Err(invalid_value(format!("mask has {} values for {n} rays", masks.len())));
            }
        }
        Ok(())
    }

    /// Whether ray `i` is valid for Vulkan once in f32: finite origin, finite non-zero direction,
    /// 0 <= tmin <= tmax, no NaN (tmax may be +inf).
    #[inline(always)]
    fn is_valid(&self, i: usize) -> bool {
        let (o, d) = (self.origin(i), self.direction(i));
        let (tmin, tmax) = (self.tmin.get(i), self.tmax.get(i));
        o.iter().all(|c| c.is_finite())
            && d.iter().all(|c| c.is_finite())
            && d.iter().any(|c| *c != 0.0)
            && tmin >= 0.0
            && (tmin as f32).is_finite()
            && tmax >= tmin
    }

    /// Why ray `i` is invalid, naming the array and the row.
    pub fn invalid_ray(&self, i: usize) -> crate::error::Error {
        let (origin, direction) = match self.sensor {
            Some(_) => (self.origin(i).map(f64::from), self.direction(i).map(f64::from)),
            None => {
                let row = |v: &Vec3s| v.row_f64(if v.rows() == 1 { 0 } else { i });
                (row(&self.origins), row(&self.directions))
            }
        };
        describe_invalid_ray(i, &origin, &direction, self.tmin.get(i), self.tmax.get(i))
    }

    /// Checks every ray, on all cores; the error names the first invalid one.
    pub fn check(&self) -> Result<()> {
        self.check_shapes()?;
        let first_bad = parallel::install(|| {
            (0..self.len().div_ceil(PACK_PIECE))
                .into_par_iter()
                .filter_map(|piece| {
                    let range = piece * PACK_PIECE..((piece + 1) * PACK_PIECE).min(self.len());
                    range.into_iter().find(|&i| !self.is_valid(i))
                })
                .min()
        });
        first_bad.map_or(Ok(()), |i| Err(self.invalid_ray(i)))
    }

    /// Checks rays `start..` and packs them for the GPU in `frame` (origins moved by
    /// `-frame.shift`): 8 f32 a ray (origin, tmin, direction, tmax), as many rays as `out` holds.
    /// One pass over the caller's arrays on all cores; the error names the first invalid ray.
    ///
    /// The interval is widened outward by one f32 ulp at each end, so that traversal, which
    /// compares in f32, reports hits exactly at `tmin` or `tmax` (it is closed, not open).
    ///
    /// A ray starting far outside the scene (`FAR_RADII` of its bounding radius) would lose its
    /// precision in f32 before reaching it: its origin is advanced in f64 to just outside the
    /// scene's bounding sphere, and the distance advanced is returned with the ray's position in
    /// `out`, for `t` to be corrected after the trace. A far ray that cannot reach the scene
    /// within its interval is packed as one that misses.
    pub fn pack(&self, start: usize, out: &mut [f32], frame: &Frame) -> Result<Vec<Advance>> {
        if let Some(plain) = PlainRays::of(self) {
            return self.pack_plain(plain, start, out, frame);
        }
        // One interval for every ray (the common case) is widened once.
        let shared = match (self.tmin, self.tmax) {
            (PerRay::All(lo), PerRay::All(hi)) => Some(widened(lo, hi)),
            _ => None,
        };
        self.pack_with(start, out, |i, ray| {
            let d = self.direction(i);
            let near = self.origin64(i, frame.shift);
            let (o, [tmin, tmax], advance) = if frame.is_far(near) {
                let (origin, tmin, tmax, advance) = self.advanced(i, frame);
                (origin, widened(tmin, tmax), advance)
            } else {
                (near, shared.unwrap_or_else(|| widened(self.tmin.get(i), self.tmax.get(i))), None)
            };
            let o = o.as_vec3();
            ray.copy_from_slice(&[o.x, o.y, o.z, tmin, d[0], d[1], d[2], tmax]);
            advance
        })
    }

    /// A packer of these rays one at a time (`PlainPacker`), where they are plain.
    pub fn plain_packer(&self, frame: &Frame) -> Option<PlainPacker<'_>> {
        PlainRays::of(self).map(|plain| PlainPacker { plain, frame: *frame })
    }

    /// `pack` for `PlainRays`: the same rays, bit for bit, in a loop with no per-ray dispatch on
    /// the arrays' types and shapes (about twice as fast: the host's packing pass is what bounds
    /// numpy in, numpy out on a GPU; docs/benchmarks.md, issue 14).
    fn pack_plain(&self, plain: PlainRays, start: usize, out: &mut [f32], frame: &Frame) -> Result<Vec<Advance>> {
        let PlainRays { origins, shared_origin, directions, interval } = plain;
        self.pack_pieces(start, out, |i, ray| {
            let at = if shared_origin { 0 } else { 3 * i };
            let o: [f32; 3] = origins[at..at + 3].try_into().expect("three floats");
            let d: [f32; 3] = directions[3 * i..3 * i + 3].try_into().expect("three floats");
            if !o.iter().chain(&d).all(|c| c.is_finite()) || d == [0.0; 3] {
                return Err(Invalid);
            }
            let near = DVec3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2])) - frame.shift;
            if !frame.is_far(near) {
                let o = near.as_vec3();
                ray.copy_from_slice(&[o.x, o.y, o.z, interval[0], d[0], d[1], d[2], interval[1]]);
                return Ok(None);
            }
            let (origin, tmin, tmax, advance) = self.advanced(i, frame);
            let [tmin, tmax] = widened(tmin, tmax);
            let o = origin.as_vec3();
            ray.copy_from_slice(&[o.x, o.y, o.z, tmin, d[0], d[1], d[2], tmax]);
            Ok(advance)
        })
    }

    /// The leaner layout rays of the common shape (`PlainRays`) pack in (`pack_compact`):
    /// `Directions` for rays from one origin that is not far from the scene, else `Compact`
    /// (which a chunk holding a far ray gives up for `Full`); `None` for other rays.
    pub fn compact_layout(&self, frame: &Frame) -> Option<RayLayout> {
        let plain = PlainRays::of(self)?;
        if !plain.shared_origin {
            return Some(RayLayout::Compact);
        }
        let o = &plain.origins[..3];
        let near = DVec3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2])) - frame.shift;
        (o.iter().all(|c| c.is_finite()) && !frame.is_far(near)).then_some(RayLayout::Directions)
    }

    /// Packs rays `start..` in `layout` (from `compact_layout`) into `out`, header first, as many
    /// as fit after it; each ray's values are those `pack` writes, bit for bit. `None` where a ray
    /// lies far from the scene (its origin is advanced, with an interval of its own): the chunk
    /// is then packed by `pack` instead. The error names the first invalid ray.
    pub fn pack_compact(&self, layout: RayLayout, start: usize, out: &mut [f32], frame: &Frame) -> Result<Option<()>> {
        let plain = PlainRays::of(self).expect("compact layouts are for plain rays");
        let PlainRays { origins, directions, interval, .. } = plain;
        let (header, out) = out.split_at_mut(RAY_HEADER_FLOATS);
        let o = match layout {
            RayLayout::Directions => {
                let near =
                    DVec3::new(f64::from(origins[0]), f64::from(origins[1]), f64::from(origins[2])) - frame.shift;
                near.as_vec3()
            }
            _ => glam::Vec3::ZERO,
        };
        header.copy_from_slice(&[o.x, o.y, o.z, interval[0], 0.0, 0.0, 0.0, interval[1]]);
        let valid = |o: &[f32], d: &[f32; 3]| o.iter().chain(d).all(|c| c.is_finite()) && *d != [0.0; 3];
        let packed = match layout {
            RayLayout::Directions => self.pack_strided(start, out, 3, |i, ray| {
                let d: [f32; 3] = directions[3 * i..3 * i + 3].try_into().expect("three floats");
                if !valid(&origins[..3], &d) {
                    return Err(Refused::Invalid);
                }
                ray.copy_from_slice(&d);
                Ok(None)
            }),
            RayLayout::Compact => self.pack_strided(start, out, 6, |i, ray| {
                let o: [f32; 3] = origins[3 * i..3 * i + 3].try_into().expect("three floats");
                let d: [f32; 3] = directions[3 * i..3 * i + 3].try_into().expect("three floats");
                if !valid(&o, &d) {
                    return Err(Refused::Invalid);
                }
                let near = DVec3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2])) - frame.shift;
                if frame.is_far(near) {
                    return Err(Refused::Far);
                }
                let o = near.as_vec3();
                ray.copy_from_slice(&[o.x, o.y, o.z, d[0], d[1], d[2]]);
                Ok(None)
            }),
            RayLayout::Full => unreachable!("the full layout packs by `pack`"),
        }?;
        Ok(packed.map(|_| ()))
    }

    /// The leaner layout the exact tier packs these rays in, if any (`pack_exact_compact`):
    /// plain rays (f32, one interval), from one origin or each from its own.
    pub fn exact_layout(&self) -> Option<RayLayout> {
        let plain = PlainRays::of(self)?;
        if !plain.shared_origin {
            return Some(RayLayout::Compact);
        }
        plain.origins[..3].iter().all(|c| c.is_finite()).then_some(RayLayout::Directions)
    }

    /// Packs rays `start..` for the exact tier in `layout` (from `exact_layout`) into `out`,
    /// header first, as many as fit after it: each ray's f32 origin (unless shared) and direction
    /// as given, which the shaders move into the scene's frame by `shift` in f64, as `pack_f64`
    /// does (`ray64`). The error names the first invalid ray.
    pub fn pack_exact_compact(&self, layout: RayLayout, start: usize, out: &mut [f32], shift: DVec3) -> Result<()> {
        let plain = PlainRays::of(self).expect("compact layouts are for plain rays");
        let (PerRay::All(tmin), PerRay::All(tmax)) = (self.tmin, self.tmax) else {
            unreachable!("plain rays share one interval")
        };
        let PlainRays { origins, directions, .. } = plain;
        let (header, out) = out.split_at_mut(EXACT_HEADER_FLOATS);
        let (wide, narrow) = header.split_at_mut(12);
        bytemuck::cast_slice_mut::<f32, f64>(wide).copy_from_slice(&[shift.x, shift.y, shift.z, tmin, tmax, 0.0]);
        let shared = if layout == RayLayout::Directions { [origins[0], origins[1], origins[2]] } else { [0.0; 3] };
        narrow.copy_from_slice(&[shared[0], shared[1], shared[2], 0.0]);
        let valid = |o: &[f32], d: &[f32]| o.iter().chain(d).all(|c| c.is_finite()) && d != [0.0; 3];
        let packed = match layout {
            RayLayout::Directions => self.pack_strided(start, out, 3, |i, ray| {
                let d = &directions[3 * i..3 * i + 3];
                if !valid(&shared, d) {
                    return Err(Refused::Invalid);
                }
                ray.copy_from_slice(d);
                Ok(None)
            }),
            RayLayout::Compact => self.pack_strided(start, out, 6, |i, ray| {
                let (o, d) = (&origins[3 * i..3 * i + 3], &directions[3 * i..3 * i + 3]);
                if !valid(o, d) {
                    return Err(Refused::Invalid);
                }
                ray[..3].copy_from_slice(o);
                ray[3..].copy_from_slice(d);
                Ok(None)
            }),
            RayLayout::Full => unreachable!("the full layout packs by `pack_f64`"),
        }?;
        packed.map(|_| ()).ok_or_else(|| crate::error::Error::Internal("an exact ray refused as far".into()))
    }

    /// A far ray's origin and interval after `Frame::advance`, and how far it moved.
    #[cold]
    fn advanced(&self, i: usize, frame: &Frame) -> (DVec3, f64, f64, Option<f64>) {
        let r = self.ray64(i, frame.shift);
        match frame.advance(&r) {
            Approach::Near => (r.origin, r.tmin, r.tmax, None),
            Approach::Advanced { origin, t } => (origin, (r.tmin - t).max(0.0), r.tmax - t, Some(t)),
            Approach::Never { origin } => (origin, 0.0, 0.0, None),
        }
    }

    /// As `pack`, in f64 for the exact tier (tmax stays +inf where it is; the exact shaders start
    /// f32 traversal where a ray enters the scene's bounds themselves).
    pub fn pack_f64(&self, start: usize, out: &mut [f64], shift: DVec3) -> Result<()> {
        self.pack_with(start, out, |i, ray| {
            let r = self.ray64(i, shift);
            let (o, d) = (r.origin, r.direction);
            ray.copy_from_slice(&[o.x, o.y, o.z, r.tmin, d.x, d.y, d.z, r.tmax]);
            None
        })
        .map(|_| ())
    }

    #[inline]
    fn pack_with<T: Send>(
        &self,
        start: usize,
        out: &mut [T],
        write: impl Fn(usize, &mut [T]) -> Option<f64> + Sync,
    ) -> Result<Vec<Advance>> {
        self.pack_pieces(start, out, |i, ray| if self.is_valid(i) { Ok(write(i, ray)) } else { Err(Invalid) })
    }

    /// Packs rays `start..` into `out` (`RAY_FLOATS` a ray) on all cores, in pieces, each ray by
    /// `write` (how far it was advanced, if it was; `Invalid` for an invalid ray); the error
    /// names the first invalid ray.
    #[inline]
    fn pack_pieces<T: Send>(
        &self,
        start: usize,
        out: &mut [T],
        write: impl Fn(usize, &mut [T]) -> std::result::Result<Option<f64>, Invalid> + Sync,
    ) -> Result<Vec<Advance>> {
        let packed =
            self.pack_strided(start, out, RAY_FLOATS, |i, ray| write(i, ray).map_err(|Invalid| Refused::Invalid));
        Ok(packed?.expect("the full layout takes every ray"))
    }

    /// `pack_pieces` for rays of `floats` values each; `None` where `write` refused a ray as
    /// far (the layout cannot hold it), which wins over an invalid ray (the full layout's pass
    /// names that one).
    fn pack_strided<T: Send>(
        &self,
        start: usize,
        out: &mut [T],
        floats: usize,
        write: impl Fn(usize, &mut [T]) -> std::result::Result<Option<f64>, Refused> + Sync,
    ) -> Result<Option<Vec<Advance>>> {
        // A pack of one piece runs where it is called (a block of a caller already on every
        // core): only a larger one asks its pool's size.
        let one_piece = out.len() <= PACK_PIECE * floats;
        let piece_rays = if one_piece { PACK_PIECE } else { pack_piece_rays(out.len() / floats) };
        let pack_piece = |(piece, out): (usize, &mut [T])| {
            let first = piece * piece_rays;
            let mut advances = Vec::new();
            for (k, ray) in out.chunks_exact_mut(floats).enumerate() {
                match write(start + first + k, ray) {
                    Err(refused) => return Err((refused, start + first + k)),
                    Ok(Some(t)) => advances.push(Advance { ray: first + k, t }),
                    Ok(None) => {}
                }
            }
            Ok(advances)
        };
        let pieces: Vec<std::result::Result<Vec<Advance>, (Refused, usize)>> = if one_piece {
            vec![pack_piece((0, out))]
        } else {
            parallel::install(|| out.par_chunks_mut(piece_rays * floats).enumerate().map(pack_piece).collect())
        };
        let refused = |kind| pieces.iter().filter_map(|p| p.as_ref().err()).filter(move |(r, _)| *r == kind);
        if refused(Refused::Far).next().is_some() {
            return Ok(None);
        }
        if let Some((_, i)) = refused(Refused::Invalid).min_by_key(|(_, i)| *i) {
            return Err(self.invalid_ray(*i));
        }
        Ok(Some(pieces.into_iter().flat_map(|p| p.unwrap_or_default()).collect()))
    }
}

/// A ray `pack_pieces` found invalid.
struct Invalid;

/// Why `pack_strided` could not pack a ray.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Refused {
    Invalid,
    /// Far from the scene: the layout has no room for its own interval.
    Far,
}

/// Rays in the common shape, which `Rays::pack_plain` packs without asking per ray: f32 origins
/// (one a ray, or one shared) and directions (one a ray), one valid interval for all, no sensor.
#[derive(Clone, Copy)]
struct PlainRays<'a> {
    origins: &'a [f32],
    shared_origin: bool,
    directions: &'a [f32],
    /// The shared interval, widened (`widened`).
    interval: [f32; 2],
}

impl<'a> PlainRays<'a> {
    fn of(rays: &Rays<'a>) -> Option<PlainRays<'a>> {
        let (Vec3s::F32(origins), Vec3s::F32(directions)) = (rays.origins, rays.directions) else { return None };
        let (PerRay::All(tmin), PerRay::All(tmax)) = (rays.tmin, rays.tmax) else { return None };
        // An invalid interval makes every ray invalid: the general path names the first.
        let interval_valid = tmin >= 0.0 && (tmin as f32).is_finite() && tmax >= tmin;
        let n = rays.len();
        let shapes = rays.directions.rows() == n && (rays.origins.rows() == n || rays.origins.rows() == 1);
        (rays.sensor.is_none() && interval_valid && shapes).then(|| PlainRays {
            origins,
            shared_origin: rays.origins.rows() == 1,
            directions,
            interval: widened(tmin, tmax),
        })
    }
}

/// Packs plain rays (`PlainRays`) one at a time where the caller asks, for a caller that packs
/// into its own records (the CPU engine's packets): each ray exactly as `Rays::pack` packs it,
/// or None where `pack` is needed (an invalid ray, whose error it names, or a far one).
#[derive(Clone, Copy)]
pub struct PlainPacker<'a> {
    plain: PlainRays<'a>,
    frame: Frame,
}

impl PlainPacker<'_> {
    /// Ray `i` packed (`RAY_FLOATS`), where it is valid and near the scene.
    #[inline(always)]
    pub fn ray(&self, i: usize) -> Option<[f32; RAY_FLOATS]> {
        let PlainRays { origins, shared_origin, directions, interval } = self.plain;
        let at = if shared_origin { 0 } else { 3 * i };
        let o: [f32; 3] = origins[at..at + 3].try_into().expect("three floats");
        let d: [f32; 3] = directions[3 * i..3 * i + 3].try_into().expect("three floats");
        if !o.iter().chain(&d).all(|c| c.is_finite()) || d == [0.0; 3] {
            return None;
        }
        // As `pack_plain`: the origin into the frame in f64, then to f32.
        let near = DVec3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2])) - self.frame.shift;
        if self.frame.is_far(near) {
            return None;
        }
        let o = near.as_vec3();
        Some([o.x, o.y, o.z, interval[0], d[0], d[1], d[2], interval[1]])
    }
}

/// `K` rays packed as `PlainPacker::ray` packs each, as lanes side by side (one array an axis):
/// origins in the frame, directions, and the interval every ray shares.
pub struct PlainLanes<const K: usize> {
    pub origins: [[f32; K]; 3],
    pub directions: [[f32; K]; 3],
    pub interval: [f32; 2],
}

impl PlainPacker<'_> {
    /// Rays `first..first + K` packed as lanes (as `ray` packs each), where all K exist and every
    /// one is valid and near the scene; else None (`ray` or `pack` then). Loops over lanes with no
    /// branch, so that the lanes are computed side by side in vectors.
    #[inline(always)]
    pub fn lanes<const K: usize>(&self, first: usize) -> Option<PlainLanes<K>> {
        let PlainRays { origins, shared_origin, directions, interval } = self.plain;
        // The rays a few packets on, asked of memory now: a packet's trace evicts them from the
        // caches, and waiting for them was most of a packet's packing with rays of their own
        // origins.
        prefetch(directions, 3 * (first + 4 * K), 3 * K);
        if !shared_origin {
            prefetch(origins, 3 * (first + 4 * K), 3 * K);
        }
        let directions = &directions.get(3 * first..3 * (first + K))?[..3 * K];
        let mut lanes = PlainLanes { origins: [[0.0; K]; 3], directions: [[0.0; K]; 3], interval };
        let mut given = [[0.0f32; K]; 3];
        if shared_origin {
            let shared = origins.get(..3)?;
            for axis in 0..3 {
                given[axis] = [shared[axis]; K];
            }
        } else {
            let origins = &origins.get(3 * first..3 * (first + K))?[..3 * K];
            for lane in 0..K {
                for axis in 0..3 {
                    given[axis][lane] = origins[3 * lane + axis];
                }
            }
        }
        for lane in 0..K {
            for axis in 0..3 {
                lanes.directions[axis][lane] = directions[3 * lane + axis];
            }
        }
        // As `ray`: each origin into the frame in f64, its distance from the bounds' centre
        // summed in `length_squared`'s order.
        let (shift, center) = (self.frame.shift.to_array(), self.frame.bounds_center.to_array());
        let mut far = [0.0f64; K];
        for axis in 0..3 {
            for lane in 0..K {
                let near = f64::from(given[axis][lane]) - shift[axis];
                let off = near - center[axis];
                far[lane] += off * off;
                lanes.origins[axis][lane] = near as f32;
            }
        }
        let mut refused = 0u32;
        for lane in 0..K {
            let [ox, oy, oz] = [given[0][lane], given[1][lane], given[2][lane]];
            let [dx, dy, dz] = [0, 1, 2].map(|axis| lanes.directions[axis][lane]);
            // NaN where any is infinite or NaN (a sum of comparisons packs poorly in vectors).
            let finite = (ox * 0.0 + oy * 0.0 + oz * 0.0 + dx * 0.0 + dy * 0.0 + dz * 0.0) == 0.0;
            let zero = dx.abs().max(dy.abs()).max(dz.abs()) == 0.0;
            refused |= u32::from(!finite | zero | (far[lane] > self.frame.far_squared));
        }
        (refused == 0).then_some(lanes)
    }
}

/// Asks the caches for `values[at..at + len]` (what of it exists), without waiting.
#[inline(always)]
fn prefetch(values: &[f32], at: usize, len: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        let end = values.len().min(at + len);
        // One line of 64 bytes in 16 floats.
        for k in (at..end).step_by(16) {
            // SAFETY: a prefetch reads nothing and cannot fault; the address is inside `values`.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    values.as_ptr().add(k) as *const i8
                )
            };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (values, at, len);
}

/// How far a far ray's origin was advanced before packing: `t` (in units of its direction) for
/// the ray at position `ray` of the packed chunk.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Advance {
    pub ray: usize,
    pub t: f64,
}

/// Rays whose origin lies farther than this many bounding radii from a scene are advanced towards
/// it in f64 before they become f32 (16: f32 then keeps all but 4 bits of the scene's precision).
pub const FAR_RADII: f64 = 16.0;

/// A scene's frame for packing rays: the shift from world coordinates into it (the scene's
/// centre), and the sphere bounding its geometry in it.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub shift: DVec3,
    pub bounds_center: DVec3,
    pub radius: f64,
    /// The squared distance from `bounds_center` beyond which rays are advanced.
    far_squared: f64,
}

enum Approach {
    /// Close enough to trace as given.
    Near,
    /// Advanced by `t` to `origin`; nothing lies before it.
    Advanced { origin: DVec3, t: f64 },
    /// Far, and the scene is out of reach within the interval: packed as an empty interval at
    /// `origin`, a point outside the scene.
    Never { origin: DVec3 },
}

/// Steps of the advance: each one lands within about 1e-16 of the distance it started from, so
/// even an origin at the end of f64's range converges in a handful.
const ADVANCE_STEPS: usize = 24;

impl Frame {
    pub fn new(shift: DVec3, bounds_center: DVec3, radius: f64) -> Frame {
        let far = FAR_RADII * radius.max(f64::MIN_POSITIVE);
        Frame { shift, bounds_center, radius, far_squared: far * far }
    }

    /// The squared distance from `bounds_center` beyond which rays are advanced.
    pub fn far_squared(&self) -> f64 {
        self.far_squared
    }

    /// A frame whose rays are never advanced.
    pub fn at(shift: DVec3) -> Frame {
        Frame::new(shift, DVec3::ZERO, f64::INFINITY)
    }

    /// Whether a ray from `origin` (in the frame) starts far enough out to be advanced.
    #[inline]
    fn is_far(&self, origin: DVec3) -> bool {
        (origin - self.bounds_center).length_squared() > self.far_squared
    }

    fn advance(&self, ray: &Ray64) -> Approach {
        if !self.is_far(ray.origin) {
            return Approach::Near;
        }
        // Every point within `radius` of the centre lies at t >= tca - radius / |d|; aim twice
        // that short, so that the new origin is outside the sphere. One step from far away lands
        // only within f64 rounding of its own length, so step again from there until the step
        // is small: the along-ray error then shrinks by 1e-16 a step.
        let (d, d2) = (ray.direction, ray.direction.length_squared());
        let back_off = 2.0 * self.radius / d2.sqrt();
        let (mut origin, mut advanced) = (ray.origin, 0.0);
        for step in 0..ADVANCE_STEPS {
            let t = -(origin - self.bounds_center).dot(d) / d2 - back_off;
            if step == 0 && t <= 0.0 {
                // Moving away, or passing its closest point within 2 radii of a start that is 16
                // radii out: it never comes within one radius of the centre.
                return Approach::Never { origin };
            }
            origin += t * d;
            advanced += t;
            if t.abs() <= 1e-3 * back_off {
                break;
            }
        }
        if ray.tmax < advanced {
            return Approach::Never { origin };
        }
        Approach::Advanced { origin, t: advanced }
    }
}

/// Points as a query that casts rays from them can take them: each point beyond f32's range and
/// outside the scene's `bounds` (its frame: the world less `center`) replaced by one point just outside the bounds, which
/// every such query answers alike (outside, unhit: a ray from outside the bounds in any direction
/// meets the scene as often as from any other point outside, an even number of times for a
/// closed mesh). None where no point needs it (the common case: no copy).
pub fn far_points_moved_in(points: Vec3s, bounds: Aabb, center: DVec3) -> Result<Option<Vec<f64>>> {
    let bounds = Aabb { min: bounds.min + center, max: bounds.max + center };
    let far = |p: [f64; 3]| p.iter().any(|c| !(*c as f32).is_finite()) && !bounds.contains(DVec3::from_array(p));
    // On all cores: a pass over every point of every `contains` (serial, 1M points took ~1 ms).
    let any_far = crate::geometry::parallel::install(|| {
        use rayon::prelude::*;
        (0..points.rows()).into_par_iter().with_min_len(1 << 14).any(|i| far(points.row_f64(i)))
    });
    if !any_far {
        return Ok(None);
    }
    let stand_in = if bounds.min.cmple(bounds.max).all() {
        bounds.max + (bounds.max - bounds.min).max(DVec3::ONE)
    } else {
        DVec3::ZERO
    };
    let mut moved = crate::geometry::parallel::try_vec(3 * points.rows(), 0.0, "the points moved in from far away")?;
    for (i, row) in moved.chunks_exact_mut(3).enumerate() {
        let p = points.row_f64(i);
        row.copy_from_slice(&if far(p) { stand_in.to_array() } else { p });
    }
    Ok(Some(moved))
}

/// Why ray `i` (with these values) is invalid, naming the array and the row (see
/// `Rays::is_valid`).
pub fn describe_invalid_ray(i: usize, origin: &[f64], direction: &[f64], tmin: f64, tmax: f64) -> crate::error::Error {
    let as_f32 = |v: &[f64]| v.iter().map(|c| *c as f32).collect::<Vec<f32>>();
    let (o, d) = (as_f32(origin), as_f32(direction));
    let row = |v: &[f64]| fmt_row([v[0], v[1], v[2]]);
    let tmin_ok = tmin >= 0.0 && (tmin as f32).is_finite();
    let message = if !o.iter().all(|c| c.is_finite()) {
        format!("origins row {i} is not finite in float32: {}", row(origin))
    } else if !d.iter().all(|c| c.is_finite()) {
        format!("directions row {i} is not finite in float32: {}", row(direction))
    } else if d.iter().all(|c| *c == 0.0) {
        format!("directions row {i} has zero length in float32: {}", row(direction))
    } else if !tmin_ok {
        format!("tmin of ray {i} must be finite and >= 0, got {tmin}")
    } else {
        format!("ray {i} has tmax ({tmax}) below tmin ({tmin}) or NaN")
    };
    invalid_value(message)
}

/// `[tmin, tmax]` in f32, widened outward by one ulp at each end (an empty interval stays empty
/// at 0); Vulkan wants finite bounds, and the largest float is as far as +inf for any f32 scene.
#[inline]
pub fn widened(tmin: f64, tmax: f64) -> [f32; 2] {
    let lo = round_down_f32(tmin).next_down().max(0.0);
    let hi = if tmax == 0.0 { 0.0 } else { round_up_f32(tmax).next_up().min(f32::MAX) };
    [lo, hi]
}

/// The largest f32 not above `x` (x >= 0).
fn round_down_f32(x: f64) -> f32 {
    let f = x as f32;
    if f as f64 > x {
        f.next_down()
    } else {
        f
    }
}

/// The smallest f32 not below `x` (x >= 0; +inf stays).
fn round_up_f32(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) < x {
        f.next_up()
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::tests::invalid_message as message;

    fn rays<'a>(o: &'a [f32], d: &'a [f32], tmin: PerRay<'a>, tmax: PerRay<'a>) -> Rays<'a> {
        Rays { origins: Vec3s::F32(o), directions: Vec3s::F32(d), tmin, tmax, mask: Masks::All(0xFF), sensor: None }
    }

    #[test]
    fn origins_equal_bit_for_bit_are_shared() {
        let n = 70_000;
        let o: Vec<f32> = (0..n).flat_map(|_| [0.5f32, -0.0, 2.0]).collect();
        let d: Vec<f32> = (0..n).flat_map(|i| [0.0f32, i as f32, 1.0]).collect();
        let shared = |o: &[f32], d: &[f32]| {
            let r = rays(o, d, PerRay::All(0.0), PerRay::All(1.0)).sharing_origin();
            (r.origins.rows(), r.len())
        };
        assert_eq!(shared(&o, &d), (1, n));
        // One direction for all: the origins keep the batch's length.
        assert_eq!(shared(&o, &d[..3]), (n, n));
        // A row that differs, among the first rows or in a later block, even by a zero's sign.
        for (row, column, value) in [(1, 0, 0.25f32), (n - 1, 2, 2.0000002), (40_000, 1, 0.0)] {
            let mut moved = o.clone();
            moved[3 * row + column] = value;
            assert_eq!(shared(&moved, &d), (n, n), "row {row}");
        }
        let wide: Vec<f64> = o.iter().map(|&c| f64::from(c)).collect();
        let r = Rays { origins: Vec3s::F64(&wide), ..rays(&o, &d, PerRay::All(0.0), PerRay::All(1.0)) };
        assert_eq!(r.sharing_origin().origins.rows(), 1);
        // float64 rows compared as six words: a low word that differs in the last row.
        let mut wide = wide;
        wide[3 * (n - 1) + 1] = f64::from_bits(1);
        let r = Rays { origins: Vec3s::F64(&wide), ..rays(&o, &d, PerRay::All(0.0), PerRay::All(1.0)) };
        assert_eq!(r.sharing_origin().origins.rows(), n);
    }

    #[test]
    fn rays_are_checked_row_by_row() {
        let o = [0.0f32; 6];
        let d = [0.0f32, 0.0, 1.0, 0.0, 0.0, 0.0];
        assert!(message(rays(&o, &d, PerRay::All(0.0), PerRay::All(f64::INFINITY)).check())
            .contains("directions row 1 has zero length"));
        let d = [0.0f32, 0.0, 1.0, 0.0, 1.0, 0.0];
        assert!(rays(&o, &d, PerRay::All(0.0), PerRay::All(f64::INFINITY)).check().is_ok());
        let tmax = [1.0, 0.5];
        assert!(message(rays(&o, &d, PerRay::All(0.75), PerRay::Each(&tmax)).check()).contains("ray 1"));
        assert!(message(rays(&o, &d, PerRay::All(-1.0), PerRay::All(1.0)).check()).contains("tmin"));
        assert!(message(rays(&o, &d, PerRay::All(0.0), PerRay::All(f64::NAN)).check()).contains("ray 0"));
        let o_nan = [0.0f32, f32::NAN, 0.0, 0.0, 0.0, 0.0];
        assert!(message(rays(&o_nan, &d, PerRay::All(0.0), PerRay::All(1.0)).check()).contains("origins row 0"));
    }

    #[test]
    fn packing_names_the_first_bad_ray_of_many_pieces() {
        let n = 3 * PACK_PIECE + 5;
        let o = [0.5f32, 0.0, 0.0]; // one origin shared by every ray
        let mut d = vec![0.0f32; 3 * n];
        d.iter_mut().skip(2).step_by(3).for_each(|z| *z = 1.0);
        let (late, early) = (2 * PACK_PIECE + 3, PACK_PIECE + 1);
        d[3 * late + 2] = f32::NAN;
        d[3 * early + 2] = 0.0;
        let r = rays(&o, &d, PerRay::All(0.0), PerRay::All(1.0));
        let mut out = vec![0f32; n * RAY_FLOATS];
        let text = message(r.pack(0, &mut out, &Frame::at(DVec3::ZERO)).map(|_| ()));
        assert!(text.contains(&format!("directions row {early} has zero length")), "{text}");
        assert!(message(r.check()).contains(&format!("row {early}")));
        // Packing from an offset reports caller row numbers.
        let tail = &mut out[..(n - late) * RAY_FLOATS];
        assert!(message(r.pack(late, tail, &Frame::at(DVec3::ZERO)).map(|_| ()))
            .contains(&format!("directions row {late} is not finite")));
        let mut first = [0f32; RAY_FLOATS];
        r.pack(0, &mut first, &Frame::at(DVec3::ZERO)).unwrap();
        assert_eq!(first, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0f32.next_up()]);
    }

    #[test]
    fn rays_pack_with_finite_bounds() {
        let o = [1.0f64, 2.0, 3.0];
        let d = [0.0f64, 0.0, -1.0];
        let r = Rays {
            origins: Vec3s::F64(&o),
            directions: Vec3s::F64(&d),
            tmin: PerRay::All(0.5),
            tmax: PerRay::All(f64::INFINITY),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        let mut out = [0f32; RAY_FLOATS];
        r.pack(0, &mut out, &Frame::at(DVec3::ZERO)).unwrap();
        assert_eq!(out, [1.0, 2.0, 3.0, 0.5f32.next_down(), 0.0, 0.0, -1.0, f32::MAX]);
    }

    #[test]
    fn far_rays_are_advanced_towards_the_scene_in_f64() {
        // A scene of radius 1 around (20, 0, 0) in its frame; a ray from 1e9 away along -x.
        let frame = Frame::new(DVec3::new(-10.0, 0.0, 0.0), DVec3::new(20.0, 0.0, 0.0), 1.0);
        let o = [1e9f64, 0.0, 0.0, 20.0, 0.0, 0.0, 1e9, 0.0, 0.0];
        let d = [-1.0f64, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0];
        let tmax = [f64::INFINITY, f64::INFINITY, f64::INFINITY];
        let r = Rays {
            origins: Vec3s::F64(&o),
            directions: Vec3s::F64(&d),
            tmin: PerRay::All(0.0),
            tmax: PerRay::Each(&tmax),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        let mut out = [0f32; 3 * RAY_FLOATS];
        let advances = r.pack(0, &mut out, &frame).unwrap();
        // Ray 0 stops 2 radii short of the sphere: at x = 22 in the frame (32 in the world).
        assert_eq!(advances.len(), 1);
        assert_eq!(advances[0].ray, 0);
        assert_eq!(advances[0].t, 1e9 + 10.0 - 22.0);
        assert_eq!(out[0], 22.0);
        // Ray 1 starts near (10 radii out): as given (20 + 10 = 30 in the frame).
        assert_eq!(out[RAY_FLOATS], 30.0);
        // Ray 2 moves away: an empty interval.
        assert_eq!((out[2 * RAY_FLOATS + 3], out[2 * RAY_FLOATS + 7]), (0.0, 0.0));
    }

    /// The plain rays' loop packs what the general one does, bit for bit: per-ray and shared
    /// origins, near and far rays, an offset start. (Per-ray intervals of equal values send the
    /// same rays down the general path.)
    #[test]
    fn plain_rays_pack_as_the_general_path_does() {
        let frame = Frame::new(DVec3::new(0.3, -0.2, 0.1), DVec3::new(0.5, 0.0, 0.0), 1.0);
        let n = 2 * PACK_PIECE + 7;
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        };
        let mut o: Vec<f32> = (0..3 * n).map(|_| 3.0 * next()).collect();
        let mut d: Vec<f32> = (0..3 * n).map(|_| next()).collect();
        for far in (0..n).step_by(97) {
            // Some far rays, towards the scene: advanced in f64.
            o[3 * far] = 1e7 * next();
            d[3 * far] = -o[3 * far].signum();
        }
        let (tmin, tmax) = (0.25, f64::INFINITY);
        let (tmins, tmaxs) = (vec![tmin; n], vec![tmax; n]);
        for origins in [&o[..], &o[..3]] {
            let plain = rays(origins, &d, PerRay::All(tmin), PerRay::All(tmax));
            let general = rays(origins, &d, PerRay::Each(&tmins), PerRay::Each(&tmaxs));
            assert!(PlainRays::of(&plain).is_some() && PlainRays::of(&general).is_none());
            for start in [0, PACK_PIECE + 3] {
                let (mut a, mut b) = (vec![0f32; (n - start) * RAY_FLOATS], vec![0f32; (n - start) * RAY_FLOATS]);
                let advances_a = plain.pack(start, &mut a, &frame).unwrap();
                let advances_b = general.pack(start, &mut b, &frame).unwrap();
                assert_eq!(advances_a, advances_b);
                assert!(origins.len() == 3 || !advances_a.is_empty(), "no far ray was tested");
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&a), bits(&b));
            }
        }
    }

    /// The compact layouts hold each ray's values as the full layout does, bit for bit (the
    /// shared interval and origin in the header); a chunk with a far ray is refused, one with an
    /// invalid ray names it.
    #[test]
    fn compact_layouts_pack_what_the_full_layout_packs() {
        let frame = Frame::new(DVec3::new(0.3, -0.2, 0.1), DVec3::new(0.5, 0.0, 0.0), 1.0);
        let n = 2 * PACK_PIECE + 7;
        let value = |k: usize| ((k * 7919 % 1000) as f32 / 500.0 - 1.0) * if k % 3 == 0 { 3.0 } else { 1.0 };
        let mut o: Vec<f32> = (0..3 * n).map(value).collect();
        let d: Vec<f32> = (0..3 * n).map(|k| value(k + 11) + 0.01).collect();
        for origins in [&o[..], &o[..3]] {
            let plain = rays(origins, &d, PerRay::All(0.25), PerRay::All(7.5));
            let layout = plain.compact_layout(&frame).unwrap();
            assert_eq!(layout, if origins.len() == 3 { RayLayout::Directions } else { RayLayout::Compact });
            let start = PACK_PIECE + 3;
            let mut full = vec![0f32; (n - start) * RAY_FLOATS];
            assert!(plain.pack(start, &mut full, &frame).unwrap().is_empty());
            let mut compact = vec![0f32; layout.bytes(n - start) / 4];
            plain.pack_compact(layout, start, &mut compact, &frame).unwrap().unwrap();
            let (header, packed) = compact.split_at(RAY_HEADER_FLOATS);
            let k = layout.floats_per_ray();
            for (i, ray) in full.chunks_exact(RAY_FLOATS).enumerate() {
                let p = &packed[k * i..k * i + k];
                let origin = if k == 3 { &header[..3] } else { &p[..3] };
                let expected = [origin, &header[3..4], &p[k - 3..], &header[7..8]].concat();
                assert_eq!(
                    ray.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                    expected.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                    "ray {i}"
                );
            }
        }
        // A far origin: per-ray origins give the chunk up; a shared one never takes a compact layout.
        o[3 * (n - 5)] = 1e7;
        let far = rays(&o, &d, PerRay::All(0.0), PerRay::All(f32::INFINITY as f64));
        let mut out = vec![0f32; RayLayout::Compact.bytes(n) / 4];
        assert!(far.pack_compact(RayLayout::Compact, 0, &mut out, &frame).unwrap().is_none());
        assert!(rays(&o[3 * (n - 5)..3 * (n - 4)], &d, PerRay::All(0.0), PerRay::All(1.0))
            .compact_layout(&frame)
            .is_none());
        // An invalid ray (zero direction) is named, as the full layout names it.
        let mut zero = d.clone();
        zero[3 * 40..3 * 41].fill(0.0);
        let invalid = rays(&o[..3], &zero, PerRay::All(0.0), PerRay::All(1.0));
        let mut out = vec![0f32; RayLayout::Directions.bytes(n) / 4];
        let error = invalid.pack_compact(RayLayout::Directions, 0, &mut out, &frame).unwrap_err().to_string();
        assert!(error.contains("40"), "{error}");
    }

    #[test]
    fn rays_from_the_end_of_float_range_land_just_outside_the_scene() {
        let frame = Frame::new(DVec3::ZERO, DVec3::ZERO, 1.0);
        for far in [1e20, 1e38, 1e300] {
            let ray =
                Ray64 { origin: DVec3::new(0.25, 0.5, far), direction: DVec3::NEG_Z, tmin: 0.0, tmax: f64::INFINITY };
            let Approach::Advanced { origin, t } = frame.advance(&ray) else { panic!("{far}: not advanced") };
            assert_eq!((origin.x, origin.y), (0.25, 0.5), "{far}: the line is kept");
            assert!((origin.z - 2.0).abs() < 1e-9, "{far}: lands 2 radii out, got {}", origin.z);
            assert!((t - far).abs() <= 1e-15 * far, "{far}: advanced {t}");
        }
    }
}

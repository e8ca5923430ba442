//! Host-side checks and packing of user input: vertices, faces, instance transforms and rays.
//! Everything here runs before anything reaches the GPU, so bad input becomes an error naming the
//! argument and the first offending row, never undefined behaviour on the device.

use glam::DVec3;
use rayon::prelude::*;

use crate::error::{invalid_value, Result};
use crate::precision::Ray64;

/// Rows of three coordinates, as the caller's dtype.
#[derive(Clone, Copy, Debug)]
pub enum Vec3s<'a> {
    F32(&'a [f32]),
    F64(&'a [f64]),
}

impl Vec3s<'_> {
    pub fn rows(&self) -> usize {
        match self {
            Vec3s::F32(v) => v.len() / 3,
            Vec3s::F64(v) => v.len() / 3,
        }
    }

    /// Row `i` as the f32 values the GPU will see.
    #[inline]
    pub fn row_f32(&self, i: usize) -> [f32; 3] {
        match self {
            Vec3s::F32(v) => [v[3 * i], v[3 * i + 1], v[3 * i + 2]],
            Vec3s::F64(v) => [v[3 * i] as f32, v[3 * i + 1] as f32, v[3 * i + 2] as f32],
        }
    }

    pub fn row_f64(&self, i: usize) -> [f64; 3] {
        match self {
            Vec3s::F32(v) => [v[3 * i] as f64, v[3 * i + 1] as f64, v[3 * i + 2] as f64],
            Vec3s::F64(v) => [v[3 * i], v[3 * i + 1], v[3 * i + 2]],
        }
    }
}

/// Triangle corner indices, as the caller's dtype.
#[derive(Clone, Copy, Debug)]
pub enum Indices<'a> {
    U16(&'a [u16]),
    U32(&'a [u32]),
    I32(&'a [i32]),
    I64(&'a [i64]),
}

impl Indices<'_> {
    pub fn triangles(&self) -> usize {
        self.len() / 3
    }

    fn len(&self) -> usize {
        match self {
            Indices::U16(v) => v.len(),
            Indices::U32(v) => v.len(),
            Indices::I32(v) => v.len(),
            Indices::I64(v) => v.len(),
        }
    }

    #[inline]
    fn get(&self, i: usize) -> i64 {
        match self {
            Indices::U16(v) => v[i] as i64,
            Indices::U32(v) => v[i] as i64,
            Indices::I32(v) => v[i] as i64,
            Indices::I64(v) => v[i],
        }
    }

    /// uint16 indices stay 16-bit on the device; every other type becomes uint32.
    pub fn is_u16(&self) -> bool {
        matches!(self, Indices::U16(_))
    }

    /// Bytes the device copy takes (16-bit indices padded to whole 32-bit words for shader reads).
    pub fn device_bytes(&self) -> u64 {
        if self.is_u16() {
            crate::memory::align_up(2 * self.len() as u64, 4)
        } else {
            4 * self.len() as u64
        }
    }

    /// Writes the device copy, triangles in `order` (new position -> caller's triangle) where
    /// given; indices must have passed `check_faces`.
    pub fn write_device(&self, out: &mut [u8], order: Option<&[u32]>) {
        let source = |k: usize| match order {
            Some(order) => 3 * order[k / 3] as usize + k % 3,
            None => k,
        };
        match (self, order) {
            (Indices::U32(v), None) => out[..4 * v.len()].copy_from_slice(as_bytes(v)),
            (Indices::U16(_), _) => {
                for (k, dst) in out.chunks_exact_mut(2).take(self.len()).enumerate() {
                    dst.copy_from_slice(&(self.get(source(k)) as u16).to_ne_bytes());
                }
            }
            _ => {
                for (k, dst) in out.chunks_exact_mut(4).take(self.len()).enumerate() {
                    dst.copy_from_slice(&(self.get(source(k)) as u32).to_ne_bytes());
                }
            }
        }
    }

    pub fn corner(&self, triangle: usize, k: usize) -> usize {
        self.get(3 * triangle + k) as usize
    }
}

/// Spreads the low 21 bits of `x` to every third bit.
fn spread_bits(x: u64) -> u64 {
    let mut x = x & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    (x | x << 2) & 0x1249_2492_4924_9249
}

/// Triangles sorted along a Morton (Z-order) curve through their centroids: new position ->
/// caller's triangle. Neighbours in this order are neighbours in space, which is what a BVH
/// builder that splits primitives in input order (lavapipe's) needs to build a good tree.
pub fn morton_order(vertices: Vec3s, faces: Indices) -> Vec<u32> {
    let n = faces.triangles();
    let centroid = |t: usize| {
        let mut c = [0.0f64; 3];
        for k in 0..3 {
            let v = vertices.row_f64(faces.corner(t, k));
            for a in 0..3 {
                c[a] += v[a] / 3.0;
            }
        }
        c
    };
    let centroids: Vec<[f64; 3]> = (0..n).map(centroid).collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for c in &centroids {
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let scale: Vec<f64> = (0..3).map(|a| if hi[a] > lo[a] { 2097151.0 / (hi[a] - lo[a]) } else { 0.0 }).collect();
    let mut keyed: Vec<(u64, u32)> = centroids
        .iter()
        .enumerate()
        .map(|(t, c)| {
            let q = |a: usize| ((c[a] - lo[a]) * scale[a]) as u64;
            (spread_bits(q(0)) | spread_bits(q(1)) << 1 | spread_bits(q(2)) << 2, t as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, t)| t).collect()
}

fn as_bytes<T: Copy>(values: &[T]) -> &[u8] {
    // SAFETY: plain numeric data reinterpreted as bytes of the same extent.
    unsafe { std::slice::from_raw_parts(values.as_ptr() as *const u8, std::mem::size_of_val(values)) }
}

fn fmt_row(row: [f64; 3]) -> String {
    format!("[{}, {}, {}]", row[0], row[1], row[2])
}

/// Vertices must be non-empty and finite once converted to f32.
pub fn check_vertices(name: &str, vertices: Vec3s) -> Result<()> {
    if vertices.rows() == 0 {
        return Err(invalid_value(format!("{name} is empty: a mesh needs at least one triangle")));
    }
    for i in 0..vertices.rows() {
        if !vertices.row_f32(i).iter().all(|c| c.is_finite()) {
            return Err(invalid_value(format!(
                "{name} row {i} is not finite in float32: {}",
                fmt_row(vertices.row_f64(i))
            )));
        }
    }
    Ok(())
}

/// Faces must be non-empty and index existing vertices.
pub fn check_faces(name: &str, faces: Indices, vertex_count: usize) -> Result<()> {
    if faces.triangles() == 0 {
        return Err(invalid_value(format!("{name} is empty: a mesh needs at least one triangle")));
    }
    for i in 0..faces.len() {
        let index = faces.get(i);
        if index < 0 || index >= vertex_count as i64 {
            let row = i / 3;
            let corners = [faces.get(3 * row), faces.get(3 * row + 1), faces.get(3 * row + 2)];
            return Err(invalid_value(format!(
                "{name} row {row} = {corners:?} indexes outside the {vertex_count} vertices (valid: 0..{})",
                vertex_count.saturating_sub(1)
            )));
        }
    }
    Ok(())
}

/// How a mesh's vertices are stored on the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum VertexFormat {
    #[default]
    F32,
    /// IEEE half floats (x, y, z, 0): 8 bytes a vertex.
    F16,
    /// Signed normalized 16-bit integers (x, y, z, 0) of the coordinates over their largest
    /// magnitude: 8 bytes a vertex.
    Snorm16,
}

impl VertexFormat {
    pub fn parse(name: &str) -> Result<VertexFormat> {
        match name {
            "float32" => Ok(VertexFormat::F32),
            "float16" => Ok(VertexFormat::F16),
            "snorm16" => Ok(VertexFormat::Snorm16),
            other => {
                Err(invalid_value(format!("vertex_format must be 'float32', 'float16' or 'snorm16', got {other:?}")))
            }
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            VertexFormat::F32 => "float32",
            VertexFormat::F16 => "float16",
            VertexFormat::Snorm16 => "snorm16",
        }
    }

    /// Bytes of one vertex on the device (the 16-bit formats are padded to four components:
    /// those are the ones Vulkan requires acceleration structures to accept).
    pub fn stride(self) -> usize {
        match self {
            VertexFormat::F32 => 12,
            _ => 8,
        }
    }

    /// The value the f64 tiers trace for coordinate `x` (|x| <= 1 for the 16-bit formats): the
    /// one the device holds for the 16-bit formats, whose loss the caller chose; the caller's own
    /// value for float32, whose rounding is the f32 tiers' alone.
    pub fn quantize(self, x: f64) -> f64 {
        match self {
            VertexFormat::F32 => x,
            VertexFormat::F16 => half::f16::from_f64(x).to_f64(),
            VertexFormat::Snorm16 => (x.clamp(-1.0, 1.0) * 32767.0).round() / 32767.0,
        }
    }

    /// Writes vertices (already quantized by `quantize`) in this format.
    pub fn write(self, vertices: &[f64], out: &mut [u8]) {
        match self {
            VertexFormat::F32 => write_vertices_f32(Vec3s::F64(vertices), out),
            VertexFormat::F16 | VertexFormat::Snorm16 => {
                for (dst, v) in out.chunks_exact_mut(8).zip(vertices.chunks_exact(3)) {
                    for (k, d) in dst.chunks_exact_mut(2).enumerate() {
                        let c = if k < 3 { v[k] } else { 0.0 };
                        let bits = match self {
                            VertexFormat::F16 => half::f16::from_f64(c).to_bits(),
                            _ => ((c.clamp(-1.0, 1.0) * 32767.0).round() as i16) as u16,
                        };
                        d.copy_from_slice(&bits.to_ne_bytes());
                    }
                }
            }
        }
    }
}

/// Writes vertices as tightly packed float32 xyz.
pub fn write_vertices_f32(vertices: Vec3s, out: &mut [u8]) {
    match vertices {
        Vec3s::F32(v) => out[..4 * v.len()].copy_from_slice(as_bytes(v)),
        Vec3s::F64(v) => {
            for (dst, &src) in out.chunks_exact_mut(4).zip(v.iter()) {
                dst.copy_from_slice(&(src as f32).to_ne_bytes());
            }
        }
    }
}

/// A row-major 3×4 or 4×4 matrix acting on column vectors (numpy's `M @ p`), as its 3×4 rows in
/// f64 (scenes subtract their centre before the f32 of `VkTransformMatrixKHR`). A 4×4 must be
/// affine (last row 0 0 0 1).
pub fn instance_transform(values: &[f64], rows: usize) -> Result<[f64; 12]> {
    if !(rows == 3 || rows == 4) || values.len() != rows * 4 {
        return Err(crate::error::Error::InvalidType(format!(
            "transform must be a 3x4 or 4x4 matrix, got {} values in {rows} rows",
            values.len()
        )));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite() || !(*v as f32).is_finite()) {
        return Err(invalid_value(format!("transform[{}, {}] is not finite in float32: {}", i / 4, i % 4, values[i])));
    }
    if rows == 4 && values[12..16] != [0.0, 0.0, 0.0, 1.0] {
        return Err(invalid_value(format!(
            "transform's last row must be [0, 0, 0, 1] (an affine transform), got {:?}",
            &values[12..16]
        )));
    }
    let mut out = [0f64; 12];
    out.copy_from_slice(&values[..12]);
    Ok(out)
}

/// A per-ray interval bound: one value for every ray, or one per ray.
#[derive(Clone, Copy, Debug)]
pub enum PerRay<'a> {
    All(f64),
    Each(&'a [f64]),
}

impl PerRay<'_> {
    #[inline]
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
}

/// Floats one packed ray takes: origin, tmin, direction, tmax.
pub const RAY_FLOATS: usize = 8;

/// Rays one thread checks and packs at a time: large enough to amortize scheduling, small enough
/// to spread a chunk over every core.
const PACK_PIECE: usize = 1 << 14;

impl Rays<'_> {
    /// The batch size: the longest of the four arrays (the others have one row or value).
    pub fn len(&self) -> usize {
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

    #[inline]
    fn origin(&self, i: usize) -> [f32; 3] {
        self.origins.row_f32(if self.origins.rows() == 1 { 0 } else { i })
    }

    #[inline]
    fn direction(&self, i: usize) -> [f32; 3] {
        self.directions.row_f32(if self.directions.rows() == 1 { 0 } else { i })
    }

    /// Ray `i` in f64, its origin shifted by `-shift` (into a scene's frame).
    pub fn ray64(&self, i: usize, shift: DVec3) -> Ray64 {
        let row = |v: &Vec3s| DVec3::from_array(v.row_f64(if v.rows() == 1 { 0 } else { i }));
        Ray64 {
            origin: row(&self.origins) - shift,
            direction: row(&self.directions),
            tmin: self.tmin.get(i),
            tmax: self.tmax.get(i),
        }
    }

    /// Array lengths must agree (one shared origin or direction row is allowed).
    pub fn check_shapes(&self) -> Result<()> {
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
    #[inline]
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
    fn invalid_ray(&self, i: usize) -> crate::error::Error {
        let row = |v: &Vec3s| v.row_f64(if v.rows() == 1 { 0 } else { i });
        let (tmin, tmax) = (self.tmin.get(i), self.tmax.get(i));
        let tmin_ok = tmin >= 0.0 && (tmin as f32).is_finite();
        let message = if !self.origin(i).iter().all(|c| c.is_finite()) {
            format!("origins row {i} is not finite in float32: {}", fmt_row(row(&self.origins)))
        } else if !self.direction(i).iter().all(|c| c.is_finite()) {
            format!("directions row {i} is not finite in float32: {}", fmt_row(row(&self.directions)))
        } else if self.direction(i).iter().all(|c| *c == 0.0) {
            format!("directions row {i} has zero length in float32: {}", fmt_row(row(&self.directions)))
        } else if !tmin_ok {
            format!("tmin of ray {i} must be finite and >= 0, got {tmin}")
        } else {
            format!("ray {i} has tmax ({tmax}) below tmin ({tmin}) or NaN")
        };
        invalid_value(message)
    }

    /// Checks every ray, on all cores; the error names the first invalid one.
    pub fn check(&self) -> Result<()> {
        self.check_shapes()?;
        let first_bad = (0..self.len().div_ceil(PACK_PIECE))
            .into_par_iter()
            .filter_map(|piece| {
                let range = piece * PACK_PIECE..((piece + 1) * PACK_PIECE).min(self.len());
                range.into_iter().find(|&i| !self.is_valid(i))
            })
            .min();
        first_bad.map_or(Ok(()), |i| Err(self.invalid_ray(i)))
    }

    /// Checks rays `start..` and packs them for the GPU with their origins moved by `-shift`
    /// (into a scene's frame): 8 f32 a ray (origin, tmin, direction, tmax), as many rays as `out`
    /// holds. One pass over the caller's arrays on all cores; the error names the first invalid ray.
    pub fn pack(&self, start: usize, out: &mut [f32], shift: DVec3) -> Result<()> {
        self.pack_with(start, out, |i, ray| {
            let (mut o, d) = (self.origin(i), self.direction(i));
            if shift != DVec3::ZERO {
                o = self.ray64(i, shift).origin.as_vec3().to_array();
            }
            // Vulkan wants finite bounds; the largest float is as far as +inf for any f32 scene.
            let tmax = (self.tmax.get(i) as f32).min(f32::MAX);
            ray.copy_from_slice(&[o[0], o[1], o[2], self.tmin.get(i) as f32, d[0], d[1], d[2], tmax]);
        })
    }

    /// As `pack`, in f64 for the exact tier (tmax stays +inf where it is).
    pub fn pack_f64(&self, start: usize, out: &mut [f64], shift: DVec3) -> Result<()> {
        self.pack_with(start, out, |i, ray| {
            let r = self.ray64(i, shift);
            let (o, d) = (r.origin, r.direction);
            ray.copy_from_slice(&[o.x, o.y, o.z, r.tmin, d.x, d.y, d.z, r.tmax]);
        })
    }

    fn pack_with<T: Send>(&self, start: usize, out: &mut [T], write: impl Fn(usize, &mut [T]) + Sync) -> Result<()> {
        let first_bad = out
            .par_chunks_mut(PACK_PIECE * RAY_FLOATS)
            .enumerate()
            .filter_map(|(piece, out)| {
                let first = start + piece * PACK_PIECE;
                for (k, ray) in out.chunks_exact_mut(RAY_FLOATS).enumerate() {
                    let i = first + k;
                    if !self.is_valid(i) {
                        return Some(i);
                    }
                    write(i, ray);
                }
                None
            })
            .min();
        first_bad.map_or(Ok(()), |i| Err(self.invalid_ray(i)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Error;

    fn message(r: Result<()>) -> String {
        match r {
            Err(Error::InvalidValue(m)) => m,
            other => panic!("expected InvalidValue, got {other:?}"),
        }
    }

    #[test]
    fn vertices_name_first_bad_row() {
        let v = [0.0f64, 0.0, 0.0, 1.0, f64::NAN, 0.0, f64::INFINITY, 0.0, 0.0];
        assert!(message(check_vertices("vertices", Vec3s::F64(&v))).contains("row 1"));
        // Finite in f64 but not in f32.
        let big = [0.0f64, 0.0, 1e39];
        assert!(message(check_vertices("vertices", Vec3s::F64(&big))).contains("row 0"));
        assert!(message(check_vertices("vertices", Vec3s::F32(&[]))).contains("empty"));
    }

    #[test]
    fn faces_must_index_vertices() {
        let ok = [0i64, 1, 2];
        assert!(check_faces("faces", Indices::I64(&ok), 3).is_ok());
        let negative = [0i32, 1, 2, 2, -1, 0];
        assert!(message(check_faces("faces", Indices::I32(&negative), 3)).contains("row 1"));
        let too_big = [0u16, 1, 3];
        assert!(message(check_faces("faces", Indices::U16(&too_big), 3)).contains("row 0"));
        assert!(message(check_faces("faces", Indices::U32(&[]), 3)).contains("empty"));
    }

    #[test]
    fn indices_pack_to_device_widths() {
        let faces = [1i64, 2, 3];
        let mut out = vec![0u8; Indices::I64(&faces).device_bytes() as usize];
        Indices::I64(&faces).write_device(&mut out, None);
        assert_eq!(out, [1u32, 2, 3].iter().flat_map(|v| v.to_ne_bytes()).collect::<Vec<_>>());
        let short = [7u16, 8, 9];
        assert_eq!(Indices::U16(&short).device_bytes(), 8);
        let mut out = vec![0u8; 8];
        Indices::U16(&short).write_device(&mut out, None);
        assert_eq!(&out[..6], [7u16, 8, 9].iter().flat_map(|v| v.to_ne_bytes()).collect::<Vec<_>>().as_slice());
    }

    #[test]
    fn reordered_indices_follow_the_order() {
        let faces = [0u16, 1, 2, 3, 4, 5];
        let mut out = vec![0u8; 12];
        Indices::U16(&faces).write_device(&mut out, Some(&[1, 0]));
        assert_eq!(out, [3u16, 4, 5, 0, 1, 2].iter().flat_map(|v| v.to_ne_bytes()).collect::<Vec<_>>());
    }

    #[test]
    fn quantized_formats_round_as_the_device_reads_them() {
        let v = [0.1, -1.0, 0.999_99];
        for format in [VertexFormat::F32, VertexFormat::F16, VertexFormat::Snorm16] {
            let mut out = vec![0u8; format.stride()];
            format.write(&v, &mut out);
            let read: Vec<f64> = match format {
                VertexFormat::F32 => {
                    out.chunks_exact(4).map(|b| f32::from_ne_bytes(b.try_into().unwrap()) as f64).collect()
                }
                VertexFormat::F16 => out
                    .chunks_exact(2)
                    .map(|b| half::f16::from_bits(u16::from_ne_bytes(b.try_into().unwrap())).to_f64())
                    .collect(),
                VertexFormat::Snorm16 => {
                    out.chunks_exact(2).map(|b| i16::from_ne_bytes(b.try_into().unwrap()) as f64 / 32767.0).collect()
                }
            };
            for k in 0..3 {
                let device = if format == VertexFormat::F32 { v[k] as f32 as f64 } else { format.quantize(v[k]) };
                assert_eq!(read[k], device, "{format:?}");
            }
            assert!((format.quantize(0.1) - 0.1).abs() < 1e-3);
        }
        assert_eq!(VertexFormat::parse("snorm16").unwrap().name(), "snorm16");
        assert!(VertexFormat::parse("unorm8").is_err());
    }

    #[test]
    fn morton_order_groups_neighbours() {
        // Four triangles along x, given far-near-far-near: the order visits them left to right.
        let mut v = Vec::new();
        for x in [3.0, 0.0, 2.0, 1.0] {
            v.extend_from_slice(&[x, 0.0, 0.0, x + 0.1, 0.0, 0.0, x, 0.1, 0.0]);
        }
        let f: Vec<u32> = (0..12).collect();
        assert_eq!(morton_order(Vec3s::F64(&v), Indices::U32(&f)), vec![1, 3, 2, 0]);
        // A permutation of every triangle.
        let mut sorted = morton_order(Vec3s::F64(&v), Indices::U32(&f));
        sorted.sort();
        assert_eq!(sorted, vec![0, 1, 2, 3]);
    }

    #[test]
    fn transforms_become_vulkan_rows() {
        let m = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 0.0, 0.0, 0.0, 1.0];
        assert_eq!(instance_transform(&m, 4).unwrap(), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0]);
        assert_eq!(instance_transform(&m[..12], 3).unwrap()[3], 4.0);
        let mut projective = m;
        projective[14] = 1.0;
        assert!(instance_transform(&projective, 4).is_err());
        let mut nan = m;
        nan[5] = f64::NAN;
        assert!(message(instance_transform(&nan, 4).map(|_| ())).contains("transform[1, 1]"));
    }

    fn rays<'a>(o: &'a [f32], d: &'a [f32], tmin: PerRay<'a>, tmax: PerRay<'a>) -> Rays<'a> {
        Rays { origins: Vec3s::F32(o), directions: Vec3s::F32(d), tmin, tmax, mask: Masks::All(0xFF) }
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
        let text = message(r.pack(0, &mut out, DVec3::ZERO));
        assert!(text.contains(&format!("directions row {early} has zero length")), "{text}");
        assert!(message(r.check()).contains(&format!("row {early}")));
        // Packing from an offset reports caller row numbers.
        let tail = &mut out[..(n - late) * RAY_FLOATS];
        assert!(message(r.pack(late, tail, DVec3::ZERO)).contains(&format!("directions row {late} is not finite")));
        let mut first = [0f32; RAY_FLOATS];
        r.pack(0, &mut first, DVec3::ZERO).unwrap();
        assert_eq!(first, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]);
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
        };
        let mut out = [0f32; RAY_FLOATS];
        r.pack(0, &mut out, DVec3::ZERO).unwrap();
        assert_eq!(out, [1.0, 2.0, 3.0, 0.5, 0.0, 0.0, -1.0, f32::MAX]);
    }
}

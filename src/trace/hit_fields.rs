//! The hit fields a query can write, and where the caller wants each one.

/// A field of the hit record. The discriminant is the field's position among the shaders' output
/// addresses and its bit in their OUTPUTS constant is `1 << discriminant`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Field {
    T = 0,
    Prim = 1,
    Instance = 2,
    Custom = 3,
    Uv = 4,
    Normal = 5,
    Geometry = 6,
}

pub const FIELD_COUNT: usize = 7;
pub const FIELDS: [Field; FIELD_COUNT] =
    [Field::T, Field::Prim, Field::Instance, Field::Custom, Field::Uv, Field::Normal, Field::Geometry];

impl Field {
    /// Bytes of one ray's value; `wide`: `t` and `uv` in f64 (the f64 precision tiers).
    pub fn bytes_per_ray(self, wide: bool) -> usize {
        match (self, wide) {
            (Field::T, true) => 8,
            (Field::Uv, false) => 8,
            (Field::Uv, true) => 16,
            (Field::Normal, _) => 12,
            _ => 4,
        }
    }

    /// Scalars per ray (2 for `uv`, 3 for `normal`).
    pub fn components(self) -> usize {
        match self {
            Field::Uv => 2,
            Field::Normal => 3,
            _ => 1,
        }
    }

    pub fn bit(self) -> u32 {
        1 << self as u32
    }

    /// The field's name in the Python API.
    pub fn name(self) -> &'static str {
        match self {
            Field::T => "t",
            Field::Prim => "prim_id",
            Field::Instance => "instance_id",
            Field::Custom => "custom_index",
            Field::Uv => "uv",
            Field::Normal => "normal",
            Field::Geometry => "geometry_id",
        }
    }
}

/// Writes whether each ray hit (1) or not (0) from its `prim_id` (native-endian i32, -1 where
/// none), on all cores.
pub fn hits_from_prims(prims: &[u8], hit: &mut [u8]) {
    use rayon::prelude::*;
    const PIECE: usize = 1 << 16;
    assert_eq!(prims.len(), 4 * hit.len(), "one prim_id a ray");
    crate::geometry::parallel::install(|| {
        hit.par_chunks_mut(PIECE).zip(prims.par_chunks(4 * PIECE)).for_each(|(hit, prims)| {
            for (h, p) in hit.iter_mut().zip(prims.chunks_exact(4)) {
                *h = u8::from(i32::from_ne_bytes([p[0], p[1], p[2], p[3]]) >= 0);
            }
        })
    });
}

/// Bytes of one ray's `position` (3 f32, or 3 f64 in the f64 tiers).
pub fn position_bytes_per_ray(wide: bool) -> usize {
    if wide {
        24
    } else {
        12
    }
}

/// Where the caller wants each requested field written, as raw bytes of its output array.
/// `position` (the world-space hit point: 3 f32, or 3 f64 in the f64 tiers) is computed on the
/// host from the hit triangle and its barycentrics, never by a shader.
#[derive(Default)]
pub struct HitSink<'a> {
    fields: [Option<&'a mut [u8]>; FIELD_COUNT],
    pub position: Option<&'a mut [u8]>,
    /// Whether each ray hit anything (a bool, one byte a ray): made from `prim_id` as the hits
    /// are copied out, without an array of prim_id (`occluded`'s answer).
    pub hit: Option<&'a mut [u8]>,
}

impl<'a> HitSink<'a> {
    pub fn set(&mut self, field: Field, out: &'a mut [u8]) {
        self.fields[field as usize] = Some(out);
    }

    pub fn field(&self, field: Field) -> Option<&[u8]> {
        self.fields[field as usize].as_deref()
    }

    /// The outputs of rows `start..start + len` of the `total` this sink holds (each output's
    /// rows are `total` equal slices of it).
    pub fn rows(&mut self, start: usize, len: usize, total: usize) -> HitSink<'_> {
        fn part<'s>(out: &'s mut Option<&mut [u8]>, start: usize, len: usize, total: usize) -> Option<&'s mut [u8]> {
            out.as_deref_mut().map(|out| {
                let width = out.len() / total.max(1);
                &mut out[start * width..(start + len) * width]
            })
        }
        let mut fields: [Option<&mut [u8]>; FIELD_COUNT] = Default::default();
        for (to, from) in fields.iter_mut().zip(self.fields.iter_mut()) {
            *to = part(from, start, len, total);
        }
        HitSink {
            fields,
            position: part(&mut self.position, start, len, total),
            hit: part(&mut self.hit, start, len, total),
        }
    }

    pub fn field_mut(&mut self, field: Field) -> Option<&mut [u8]> {
        self.fields[field as usize].as_deref_mut()
    }

    pub fn take(&mut self, field: Field) -> Option<&'a mut [u8]> {
        self.fields[field as usize].take()
    }

    /// The OUTPUTS bits of the fields asked for (`prim_id`'s where `hit` is).
    pub fn outputs(&self) -> u32 {
        let hit = if self.hit.is_some() { Field::Prim.bit() } else { 0 };
        FIELDS.iter().filter(|f| self.fields[**f as usize].is_some()).map(|f| f.bit()).fold(hit, |a, b| a | b)
    }

    /// The fields asked for, with their arrays.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = (Field, &mut [u8])> + use<'_, 'a> {
        FIELDS.iter().zip(self.fields.iter_mut()).filter_map(|(f, out)| out.as_deref_mut().map(|out| (*f, out)))
    }
}

//! Every hit of every ray as the answer's columns (`intersect_all`): each ray's hits are entries
//! `offsets[i]..offsets[i + 1]` of each column, with the ray of each hit. An engine may write the
//! columns itself (the Vulkan engine's GPU does, chunk by chunk); otherwise they are written from
//! the CPU tracer's records (`HitColumns::from_records`).

use rayon::prelude::*;

use super::hit_fields::{position_bytes_per_ray, Field, HitSink};
use super::host_tiers::{write_all_hits_and_rays, AllHits};
use crate::error::Result;
use crate::geometry::parallel::{self, try_zeroed};
use crate::geometry::rays::Rays;
use crate::geometry::reference::ReferenceHit;
use crate::scene::Scene;

/// One asked column: a hit field, or None for `position`.
pub type AskedColumn = Option<Field>;

/// One column of all hits, typed, so that it becomes an array of its caller's without a copy:
/// its numbers and how many a hit has.
pub enum HitColumn {
    F64(Vec<f64>, usize),
    F32(Vec<f32>, usize),
    I32(Vec<i32>),
}

impl HitColumn {
    /// A column of `hits` zeroed entries for `column`: `t`, `uv` and `position` in f64 where
    /// `wide` (the f64 tiers), else f32.
    pub fn zeroed(column: AskedColumn, hits: usize, wide: bool) -> Result<HitColumn> {
        let floats = |k: usize, what: &str| -> Result<HitColumn> {
            Ok(if wide {
                HitColumn::F64(try_zeroed(k * hits, what)?, k)
            } else {
                HitColumn::F32(try_zeroed(k * hits, what)?, k)
            })
        };
        Ok(match column {
            None => floats(3, "the hits' positions")?,
            Some(Field::T) => floats(1, "the hits' t")?,
            Some(Field::Uv) => floats(2, "the hits' uv")?,
            Some(Field::Normal) => HitColumn::F32(try_zeroed(3 * hits, "the hits' normals")?, 3),
            Some(_) => HitColumn::I32(try_zeroed(hits, "the hits' ids")?),
        })
    }

    /// An empty column for `column`, with room for `hits` entries where the host has it.
    pub fn with_room(column: AskedColumn, hits: usize, wide: bool) -> HitColumn {
        let mut empty = HitColumn::zeroed(column, 0, wide).expect("an empty column needs no memory");
        empty.reserve(hits);
        empty
    }

    /// Bytes a hit takes in `column`.
    pub fn bytes_per_hit(column: AskedColumn, wide: bool) -> usize {
        column.map_or(position_bytes_per_ray(wide), |f| f.bytes_per_ray(wide))
    }

    /// Room for `hits` more entries (amortized growth), or an error where the host has none.
    pub fn try_reserve(&mut self, hits: usize) -> std::result::Result<(), std::collections::TryReserveError> {
        match self {
            HitColumn::F64(v, k) => v.try_reserve(hits * *k),
            HitColumn::F32(v, k) => v.try_reserve(hits * *k),
            HitColumn::I32(v) => v.try_reserve(hits),
        }
    }

    /// Entries (hits) it holds.
    pub fn hits(&self) -> usize {
        match self {
            HitColumn::F64(v, k) => v.len() / k,
            HitColumn::F32(v, k) => v.len() / k,
            HitColumn::I32(v) => v.len(),
        }
    }

    pub fn bytes_mut(&mut self) -> &mut [u8] {
        match self {
            HitColumn::F64(v, _) => bytemuck::cast_slice_mut(v),
            HitColumn::F32(v, _) => bytemuck::cast_slice_mut(v),
            HitColumn::I32(v) => bytemuck::cast_slice_mut(v),
        }
    }

    /// Room for `hits` more entries, where the host has it (else the vector grows as appended).
    fn reserve(&mut self, hits: usize) {
        let reserved = match self {
            HitColumn::F64(v, k) => v.try_reserve_exact(hits * *k).is_ok(),
            HitColumn::F32(v, k) => v.try_reserve_exact(hits * *k).is_ok(),
            HitColumn::I32(v) => v.try_reserve_exact(hits).is_ok(),
        };
        if reserved {
            match self {
                HitColumn::F64(v, _) => parallel::advise_huge_pages(v),
                HitColumn::F32(v, _) => parallel::advise_huge_pages(v),
                HitColumn::I32(v) => parallel::advise_huge_pages(v),
            }
        }
    }

    /// Appends the entries in `bytes` (this column's type, tightly packed, 4-byte aligned; 8 for
    /// f64), on all cores: the pages' first touch is spread too.
    pub fn append_bytes(&mut self, bytes: &[u8]) {
        fn extend<T: bytemuck::Pod + Send + Sync>(v: &mut Vec<T>, bytes: &[u8]) {
            let src: &[T] = bytemuck::cast_slice(bytes);
            parallel::install(|| v.par_extend(src.par_iter().with_min_len(1 << 14).copied()));
        }
        match self {
            HitColumn::F64(v, _) => extend(v, bytes),
            HitColumn::F32(v, _) => extend(v, bytes),
            HitColumn::I32(v) => extend(v, bytes),
        }
    }

    /// Appends another column of the same type's entries.
    pub fn append(&mut self, other: &mut HitColumn) {
        let bytes = other.bytes_mut();
        self.append_bytes(bytes);
    }
}

/// Every hit of every ray, as columns: ray i's hits are entries `offsets[i]..offsets[i + 1]` of
/// `ray_index` (each hit's ray) and of each asked column, in the order asked.
pub struct HitColumns {
    pub offsets: Vec<i64>,
    pub ray_index: Vec<i64>,
    pub columns: Vec<HitColumn>,
}

impl HitColumns {
    /// What the answer takes per hit: its asked columns and its ray index.
    pub fn bytes_per_hit(asked: &[AskedColumn], wide: bool) -> usize {
        8 + asked.iter().map(|&c| HitColumn::bytes_per_hit(c, wide)).sum::<usize>()
    }

    /// The columns of `all`'s hits (of `rays` on `scene`), written on all cores; and the records,
    /// for their engine to reuse.
    pub fn from_records(
        scene: &Scene,
        rays: &Rays,
        all: AllHits,
        asked: &[AskedColumn],
    ) -> Result<(HitColumns, Vec<ReferenceHit>)> {
        let h = all.hits.len();
        let mut columns = asked.iter().map(|&c| HitColumn::zeroed(c, h, all.wide)).collect::<Result<Vec<_>>>()?;
        let mut sink = HitSink::default();
        for (&asked, column) in asked.iter().zip(columns.iter_mut()) {
            match asked {
                Some(field) => sink.set(field, column.bytes_mut()),
                None => sink.position = Some(column.bytes_mut()),
            }
        }
        let mut ray_index = try_zeroed(h, "the hits' ray indices")?;
        write_all_hits_and_rays(scene, rays, &all, &mut sink, &mut ray_index)?;
        Ok((HitColumns { offsets: all.offsets, ray_index, columns }, all.hits))
    }
}

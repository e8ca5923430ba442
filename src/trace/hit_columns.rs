//! Every hit of every ray as the answer's columns (`intersect_all`): each ray's hits are entries
//! `offsets[i]..offsets[i + 1]` of each column, with the ray of each hit. An engine may write the
//! columns itself (the Vulkan engine's GPU does, chunk by chunk); otherwise they are written from
//! the CPU tracer's records (`HitColumns::from_records`).

use rayon::prelude::*;

use super::hit_fields::{position_bytes_per_ray, Field, HitSink};
use super::host_tiers::{write_all_hit_columns, AllHits};
use crate::error::{Error, Result};
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

    /// Bytes a hit takes in `column`.
    pub fn bytes_per_hit(column: AskedColumn, wide: bool) -> usize {
        column.map_or(position_bytes_per_ray(wide), |f| f.bytes_per_ray(wide))
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

    pub fn bytes(&self) -> &[u8] {
        match self {
            HitColumn::F64(v, _) => bytemuck::cast_slice(v),
            HitColumn::F32(v, _) => bytemuck::cast_slice(v),
            HitColumn::I32(v) => bytemuck::cast_slice(v),
        }
    }

    /// An empty column for `column` with room for `hits` entries (untouched: the host's
    /// allocator gives recycled memory without zeroing it again), or `OutOfMemory`.
    pub fn with_room(column: AskedColumn, hits: usize, wide: bool) -> Result<HitColumn> {
        fn room<T>(hits: usize) -> Result<Vec<T>> {
            let mut v = Vec::new();
            v.try_reserve_exact(hits).map_err(|_| {
                Error::OutOfMemory(format!("the hits' columns need room for {hits} more values, which the host lacks"))
            })?;
            parallel::advise_huge_pages(&mut v);
            Ok(v)
        }
        Ok(match HitColumn::zeroed(column, 0, wide)? {
            HitColumn::F64(_, k) => HitColumn::F64(room(hits * k)?, k),
            HitColumn::F32(_, k) => HitColumn::F32(room(hits * k)?, k),
            HitColumn::I32(_) => HitColumn::I32(room(hits)?),
        })
    }

    /// Appends the entries in `bytes` (this column's type, tightly packed and aligned), on all
    /// cores: where the column has room, each core writes its part in place.
    pub fn extend_from_bytes(&mut self, bytes: &[u8]) {
        match self {
            HitColumn::F64(v, _) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::F32(v, _) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::I32(v) => extend(v, bytemuck::cast_slice(bytes)),
        }
    }

    /// `parts` (columns for `column`) one after another, copied on all cores.
    pub fn joined(column: AskedColumn, parts: Vec<HitColumn>, wide: bool) -> Result<HitColumn> {
        let mut out = HitColumn::with_room(column, parts.iter().map(HitColumn::hits).sum(), wide)?;
        for part in &parts {
            out.extend_from_bytes(part.bytes());
        }
        Ok(out)
    }
}

/// Appends `values` to `v` on all cores (in place where `v` has room).
pub fn extend<T: bytemuck::Pod + Send + Sync>(v: &mut Vec<T>, values: &[T]) {
    parallel::install(|| v.par_extend(values.par_iter().with_min_len(1 << 14).copied()));
}

/// Every hit of every ray, as columns: ray i's hits are entries `offsets[i]..offsets[i + 1]` of
/// each asked column, in the order asked. Each hit's ray follows from the offsets
/// (`host_tiers::ray_indices`), made where a caller asks for it.
pub struct HitColumns {
    pub offsets: Vec<i64>,
    pub columns: Vec<HitColumn>,
}

impl HitColumns {
    /// What the answer takes per hit: its asked columns.
    pub fn bytes_per_hit(asked: &[AskedColumn], wide: bool) -> usize {
        asked.iter().map(|&c| HitColumn::bytes_per_hit(c, wide)).sum::<usize>()
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
        write_all_hit_columns(scene, rays, &all, &mut sink)?;
        Ok((HitColumns { offsets: all.offsets, columns }, all.hits))
    }
}

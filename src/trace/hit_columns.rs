//! Every hit of every ray as the answer's columns (`intersect_all`): each ray's hits are entries
//! `offsets[i]..offsets[i + 1]` of each column, with the ray of each hit. An engine may write the
//! columns itself (the Vulkan engine's GPU does, chunk by chunk); otherwise they are written from
//! the CPU tracer's records (`HitColumns::from_records`).

use std::sync::Arc;

use rayon::prelude::*;

use super::hit_fields::{position_bytes_per_ray, Field, HitSink};
use super::host_tiers::{write_all_hits_and_rays, AllHits};
use crate::error::{Error, Result};
use crate::geometry::parallel::{self, try_zeroed};
use crate::geometry::rays::Rays;
use crate::geometry::reference::ReferenceHit;
use crate::scene::Scene;

/// One asked column: a hit field, or None for `position`.
pub type AskedColumn = Option<Field>;

/// Memory an engine lends an answer's columns in, kept as long as the arrays made of it: the
/// Vulkan engine's host-visible buffer that the GPU wrote a query's columns to, which becomes the
/// answer's without a copy.
pub trait LentMemory: Send + Sync {
    fn bytes(&self) -> &[u8];
}

/// The numbers of a column in lent memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LentNumbers {
    F64,
    F32,
    I32,
    I64,
}

impl LentNumbers {
    pub fn size(self) -> usize {
        match self {
            LentNumbers::F64 | LentNumbers::I64 => 8,
            LentNumbers::F32 | LentNumbers::I32 => 4,
        }
    }
}

/// A column in lent memory: `len` bytes from `at`, of `per_hit` numbers a hit.
#[derive(Clone)]
pub struct LentColumn {
    pub memory: Arc<dyn LentMemory>,
    pub at: usize,
    pub len: usize,
    pub numbers: LentNumbers,
    pub per_hit: usize,
}

impl LentColumn {
    pub fn bytes(&self) -> &[u8] {
        &self.memory.bytes()[self.at..self.at + self.len]
    }
}

/// One column of all hits, typed, so that it becomes an array of its caller's without a copy:
/// its numbers and how many a hit has (or lent by the engine that wrote it).
pub enum HitColumn {
    F64(Vec<f64>, usize),
    F32(Vec<f32>, usize),
    I32(Vec<i32>),
    I64(Vec<i64>),
    Lent(LentColumn),
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

    /// The same column's type in `memory`, `hits` entries from `at` (lent by its engine).
    pub fn lent(&self, memory: &Arc<dyn LentMemory>, at: usize, hits: usize) -> HitColumn {
        let (numbers, per_hit) = match self {
            HitColumn::F64(_, k) => (LentNumbers::F64, *k),
            HitColumn::F32(_, k) => (LentNumbers::F32, *k),
            HitColumn::I32(_) => (LentNumbers::I32, 1),
            HitColumn::I64(_) => (LentNumbers::I64, 1),
            HitColumn::Lent(c) => (c.numbers, c.per_hit),
        };
        let len = hits * per_hit * numbers.size();
        HitColumn::Lent(LentColumn { memory: memory.clone(), at, len, numbers, per_hit })
    }

    /// Entries (hits) it holds.
    pub fn hits(&self) -> usize {
        match self {
            HitColumn::F64(v, k) => v.len() / k,
            HitColumn::F32(v, k) => v.len() / k,
            HitColumn::I32(v) => v.len(),
            HitColumn::I64(v) => v.len(),
            HitColumn::Lent(c) => c.len / (c.numbers.size() * c.per_hit),
        }
    }

    /// Its numbers to write, where it owns them (a lent column is its engine's, written).
    pub fn bytes_mut(&mut self) -> Option<&mut [u8]> {
        match self {
            HitColumn::F64(v, _) => Some(bytemuck::cast_slice_mut(v)),
            HitColumn::F32(v, _) => Some(bytemuck::cast_slice_mut(v)),
            HitColumn::I32(v) => Some(bytemuck::cast_slice_mut(v)),
            HitColumn::I64(v) => Some(bytemuck::cast_slice_mut(v)),
            HitColumn::Lent(_) => None,
        }
    }

    pub fn bytes(&self) -> &[u8] {
        match self {
            HitColumn::F64(v, _) => bytemuck::cast_slice(v),
            HitColumn::F32(v, _) => bytemuck::cast_slice(v),
            HitColumn::I32(v) => bytemuck::cast_slice(v),
            HitColumn::I64(v) => bytemuck::cast_slice(v),
            HitColumn::Lent(c) => c.bytes(),
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
            HitColumn::I32(_) | HitColumn::Lent(_) => HitColumn::I32(room(hits)?),
            HitColumn::I64(_) => HitColumn::I64(room(hits)?),
        })
    }

    /// Appends the entries in `bytes` (this column's type, tightly packed and aligned), on all
    /// cores: where the column has room, each core writes its part in place. A lent column
    /// (which is never extended) becomes its own copy first.
    pub fn extend_from_bytes(&mut self, bytes: &[u8]) {
        if let HitColumn::Lent(c) = self {
            *self = owned_copy(c);
        }
        match self {
            HitColumn::F64(v, _) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::F32(v, _) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::I32(v) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::I64(v) => extend(v, bytemuck::cast_slice(bytes)),
            HitColumn::Lent(_) => unreachable!("copied above"),
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

    /// `parts` one after another, copied on all cores.
    pub fn joined_vecs<T: bytemuck::Pod + Send + Sync>(parts: Vec<Vec<T>>) -> Result<Vec<T>> {
        let mut out = Vec::new();
        let total = parts.iter().map(Vec::len).sum();
        out.try_reserve_exact(total)
            .map_err(|_| Error::OutOfMemory(format!("the hits' ray indices need room for {total} values")))?;
        parallel::advise_huge_pages(&mut out);
        for part in &parts {
            extend(&mut out, part);
        }
        Ok(out)
    }
}

/// A lent column's numbers in a column of their own.
fn owned_copy(c: &LentColumn) -> HitColumn {
    let bytes = c.bytes();
    match c.numbers {
        LentNumbers::F64 => HitColumn::F64(bytemuck::pod_collect_to_vec(bytes), c.per_hit),
        LentNumbers::F32 => HitColumn::F32(bytemuck::pod_collect_to_vec(bytes), c.per_hit),
        LentNumbers::I32 => HitColumn::I32(bytemuck::pod_collect_to_vec(bytes)),
        LentNumbers::I64 => HitColumn::I64(bytemuck::pod_collect_to_vec(bytes)),
    }
}

/// Appends `values` to `v` on all cores (in place where `v` has room).
pub fn extend<T: bytemuck::Pod + Send + Sync>(v: &mut Vec<T>, values: &[T]) {
    parallel::install(|| v.par_extend(values.par_iter().with_min_len(1 << 14).copied()));
}

/// Every hit of every ray, as columns: ray i's hits are entries `offsets[i]..offsets[i + 1]` of
/// `ray_index` (each hit's ray, i64) and of each asked column, in the order asked.
pub struct HitColumns {
    pub offsets: Vec<i64>,
    pub ray_index: HitColumn,
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
            let bytes = column.bytes_mut().expect("zeroed columns are owned");
            match asked {
                Some(field) => sink.set(field, bytes),
                None => sink.position = Some(bytes),
            }
        }
        let mut ray_index = try_zeroed(h, "the hits' ray indices")?;
        write_all_hits_and_rays(scene, rays, &all, &mut sink, &mut ray_index)?;
        let ray_index = HitColumn::I64(ray_index);
        Ok((HitColumns { offsets: all.offsets, ray_index, columns }, all.hits))
    }
}

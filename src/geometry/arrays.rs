//! Host-side checks and packing of user input: vertices, faces, instance transforms and rays.
//! Everything here runs before anything reaches the GPU, so bad input becomes an error naming the
//! argument and the first offending row, never undefined behaviour on the device.

use crate::error::{invalid_value, Result};

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
    #[inline(always)]
    pub fn row_f32(&self, i: usize) -> [f32; 3] {
        match self {
            Vec3s::F32(v) => [v[3 * i], v[3 * i + 1], v[3 * i + 2]],
            Vec3s::F64(v) => [v[3 * i] as f32, v[3 * i + 1] as f32, v[3 * i + 2] as f32],
        }
    }

    #[inline(always)]
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
            crate::geometry::align::align_up(2 * self.len() as u64, 4)
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
            (Indices::U32(v), None) => out[..4 * v.len()].copy_from_slice(bytemuck::cast_slice(v)),
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

pub(crate) fn fmt_row(row: [f64; 3]) -> String {
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

/// Query points must be finite in f64 (none is fine).
pub fn check_points(name: &str, points: Vec3s) -> Result<()> {
    use rayon::prelude::*;
    // Blocks of rows on all cores (a pass over the caller's array that should cost nothing next
    // to the query); the first bad row of the first bad block is named.
    const ROWS: usize = 1 << 14;
    let finite = |rows: std::ops::Range<usize>| rows.clone().all(|i| points.row_f64(i).iter().all(|c| c.is_finite()));
    let n = points.rows();
    let bad_block = super::parallel::install(|| {
        (0..n.div_ceil(ROWS)).into_par_iter().position_first(|b| !finite(b * ROWS..(n.min((b + 1) * ROWS))))
    });
    let Some(block) = bad_block else { return Ok(()) };
    let i = (block * ROWS..n).find(|&i| !finite(i..i + 1)).expect("a bad row in the block");
    Err(invalid_value(format!("{name} row {i} is not finite: {}", fmt_row(points.row_f64(i)))))
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

/// Writes vertices as tightly packed float32 xyz.
pub fn write_vertices_f32(vertices: Vec3s, out: &mut [u8]) {
    match vertices {
        Vec3s::F32(v) => out[..4 * v.len()].copy_from_slice(bytemuck::cast_slice(v)),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::tests::invalid_message as message;

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
}

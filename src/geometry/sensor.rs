//! Sensors whose rays the shaders generate (cameras and spinning lidars): the f32 parameters the
//! caller's sensor (python/vkray/sensors.py) derives, and the host's twin of the shaders'
//! generator (shaders/common.glsl `sensor_ray`), for the tiers and rays the host traces itself.
//! Both combine the same f32 values with the same operations in the same order, and neither
//! fuses multiply-adds (Rust never contracts), so that every ray is the same bit for bit.

use crate::error::{invalid_value, Result};

/// What kind of sensor, as the shaders' SENSOR_* constants number them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SensorKind {
    Pinhole = 1,
    Orthographic = 2,
    Lidar = 3,
}

/// A sensor's rays: `rows` × `columns` of them, row by row (image rows, or lidar channels).
#[derive(Clone, Debug)]
pub struct SensorRays {
    pub kind: SensorKind,
    /// Pinhole and lidar: every ray's origin; orthographic: the corner the pixel grid starts at.
    pub origin: [f32; 3],
    /// Pinhole: a, b, c with direction a px + (b py + c) (Open3D's order); orthographic: U, V, D with origin
    /// (origin + U px) + V py and direction D; lidar: the rows of the sensor-to-world rotation.
    pub axes: [[f32; 3]; 3],
    pub columns: u32,
    pub rows: u32,
    /// Added to a pixel's column and row (pixel centres: 0.5).
    pub pixel_offset: f32,
    pub tmin: f64,
    pub tmax: f64,
    /// Lidar: (cos, sin) of each step's azimuth, then of each channel's elevation.
    pub table: Vec<f32>,
}

impl SensorRays {
    /// Checks what the shaders rely on: a kind's table, sizes, finite parameters, an interval.
    pub fn check(&self) -> Result<()> {
        if self.columns == 0 || self.rows == 0 {
            return Err(invalid_value(format!(
                "a sensor needs at least one ray, got {} × {}",
                self.rows, self.columns
            )));
        }
        if (self.columns as u64) * (self.rows as u64) > u32::MAX as u64 {
            return Err(invalid_value("a sensor's rays must number below 2**32"));
        }
        let finite = self.origin.iter().chain(self.axes.iter().flatten()).chain(&self.table).all(|x| x.is_finite());
        if !finite || !self.pixel_offset.is_finite() {
            return Err(invalid_value("a sensor's parameters must be finite in float32"));
        }
        let table = 2 * (self.columns as usize + self.rows as usize);
        if self.kind == SensorKind::Lidar && self.table.len() != table {
            return Err(invalid_value(format!("a lidar's table needs {table} values, got {}", self.table.len())));
        }
        if !(self.tmin >= 0.0 && (self.tmin as f32).is_finite() && self.tmax >= self.tmin) {
            return Err(invalid_value(format!(
                "a sensor's range must have 0 <= tmin <= tmax, got [{}, {}]",
                self.tmin, self.tmax
            )));
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.columns as usize * self.rows as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Ray `i`'s origin and direction, as the shaders generate it.
    #[inline]
    pub fn ray(&self, i: usize) -> ([f32; 3], [f32; 3]) {
        let (column, row) = (i % self.columns as usize, i / self.columns as usize);
        let px = column as f32 + self.pixel_offset;
        let py = row as f32 + self.pixel_offset;
        let [a, b, c] = self.axes;
        match self.kind {
            SensorKind::Pinhole => (self.origin, [0, 1, 2].map(|j| a[j] * px + (b[j] * py + c[j]))),
            SensorKind::Orthographic => ([0, 1, 2].map(|j| (self.origin[j] + a[j] * px) + b[j] * py), c),
            SensorKind::Lidar => {
                let channel = 2 * (self.columns as usize + row);
                let (ce, se) = (self.table[channel], self.table[channel + 1]);
                let (ca, sa) = (self.table[2 * column], self.table[2 * column + 1]);
                let (lx, ly, lz) = (ce * ca, ce * sa, se);
                (self.origin, self.axes.map(|r| (r[0] * lx + r[1] * ly) + r[2] * lz))
            }
        }
    }

    /// The origins whose distance to a scene bounds every ray's: the one origin, or the corners
    /// of an orthographic grid (distance to a point is convex, so a corner is farthest).
    pub fn extreme_origins(&self) -> Vec<[f32; 3]> {
        match self.kind {
            SensorKind::Orthographic => {
                let (w, h) = (self.columns as usize, self.rows as usize);
                [0, w - 1, (h - 1) * w, h * w - 1].iter().map(|&i| self.ray(i).0).collect()
            }
            _ => vec![self.origin],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole() -> SensorRays {
        SensorRays {
            kind: SensorKind::Pinhole,
            origin: [1.0, 2.0, 3.0],
            axes: [[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [-0.32, -0.24, 1.0]],
            columns: 64,
            rows: 48,
            pixel_offset: 0.5,
            tmin: 0.0,
            tmax: f64::INFINITY,
            table: Vec::new(),
        }
    }

    #[test]
    fn pinhole_rays_run_row_by_row_through_pixel_centres() {
        let s = pinhole();
        s.check().unwrap();
        let (o, d) = s.ray(64 + 2);
        assert_eq!(o, [1.0, 2.0, 3.0]);
        assert_eq!(d, [0.01f32 * 2.5 + (0.0 * 1.5 - 0.32), 0.0 * 2.5 + (0.01f32 * 1.5 - 0.24), 1.0]);
    }

    #[test]
    fn lidar_rays_follow_their_tables() {
        let table = vec![1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0];
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let s = SensorRays { kind: SensorKind::Lidar, axes: identity, columns: 2, rows: 2, table, ..pinhole() };
        s.check().unwrap();
        assert_eq!(s.ray(0).1, [1.0, 0.0, 0.0]);
        assert_eq!(s.ray(1).1, [0.0, 1.0, 0.0]);
        assert_eq!(s.ray(2).1, [0.0, 0.0, 1.0]);
    }

    #[test]
    fn bad_sensors_are_refused() {
        assert!(SensorRays { columns: 0, ..pinhole() }.check().is_err());
        assert!(SensorRays { origin: [f32::NAN, 0.0, 0.0], ..pinhole() }.check().is_err());
        assert!(SensorRays { tmin: 2.0, tmax: 1.0, ..pinhole() }.check().is_err());
        assert!(SensorRays { kind: SensorKind::Lidar, ..pinhole() }.check().is_err());
    }
}

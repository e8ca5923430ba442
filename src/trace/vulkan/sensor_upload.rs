//! Sensors on the device: the record (and lidar table) the shaders generate a query's rays from,
//! in the frame and tier the query traces in.

use std::sync::Arc;

use glam::DVec3;

use crate::error::Result;
use crate::geometry::rays::Frame;
use crate::geometry::sensor::SensorRays;
use crate::gpu::context::Context;
use crate::gpu::memory::{Buffer, Uploads, GEOMETRY_INPUT};
use crate::gpu::records::Sensor;

/// The `Sensor` record of `sensor` for a query in `frame`: the fast tier's origin moved to the
/// scene's frame as the host moves uploaded rays (f32 of the f64 difference) and its interval
/// widened as theirs; the exact tier's in the world, with the frame's shift and interval in f64.
/// `table`: the device address of the lidar's table.
pub fn record(sensor: &SensorRays, frame: &Frame, exact: bool, table: u64) -> Sensor {
    let origin = if exact {
        sensor.origin
    } else {
        (DVec3::from_array(sensor.origin.map(f64::from)) - frame.shift).as_vec3().to_array()
    };
    let [tmin, tmax] = crate::geometry::rays::widened(sensor.tmin, sensor.tmax);
    let axis = |k: usize, w: f32| {
        let a = sensor.axes[k];
        [a[0], a[1], a[2], w]
    };
    Sensor {
        origin: [origin[0], origin[1], origin[2], tmin],
        axes: [axis(0, tmax), axis(1, 0.0), axis(2, 0.0)],
        kind: sensor.kind as u32,
        columns: sensor.columns,
        rows: sensor.rows,
        pixel_offset: sensor.pixel_offset,
        table,
        tmin64: sensor.tmin,
        tmax64: sensor.tmax,
        shift: frame.shift.to_array(),
    }
}

/// Uploads the record (and the lidar's table after it) to device memory, for one query.
pub fn upload(ctx: &Arc<Context>, sensor: &SensorRays, frame: &Frame, exact: bool) -> Result<Buffer> {
    let record_bytes = std::mem::size_of::<Sensor>();
    let table: &[u8] = bytemuck::cast_slice(&sensor.table);
    let mut uploads = Uploads::default();
    let buffer =
        uploads.buffer(ctx, (record_bytes + table.len().max(4)) as u64, GEOMETRY_INPUT, "sensor", |out, address| {
            let record = record(sensor, frame, exact, address + record_bytes as u64);
            out[..record_bytes].copy_from_slice(bytemuck::bytes_of(&record));
            out[record_bytes..record_bytes + table.len()].copy_from_slice(table);
        })?;
    ctx.run_commands(|cmd| {
        uploads.record(ctx, cmd);
        Ok(())
    })?;
    Ok(buffer)
}

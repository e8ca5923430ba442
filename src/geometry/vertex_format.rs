//! How a mesh's vertices are stored on the device: float32, or quantized to 16 bits.

use super::arrays::{write_vertices_f32, Vec3s};
use crate::error::{invalid_value, Result};

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

#[cfg(test)]
mod tests {
    use super::*;

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
}

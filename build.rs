//! Compiles the GLSL in shaders/ to SPIR-V 1.4 with glslc; src/shaders.rs embeds the results.

use std::path::PathBuf;
use std::process::Command;

const SHADERS: &[&str] = &[
    "trace_ray_query.comp",
    "raygen.rgen",
    "closest_hit.rchit",
    "miss.rmiss",
    "trace_exact_ray_query.comp",
    "raygen_exact.rgen",
    "intersection_exact.rint",
    "sphere.rint",
];

fn main() {
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    println!("cargo:rerun-if-env-changed=GLSLC");
    println!("cargo:rerun-if-changed=shaders");
    for name in SHADERS {
        let source = PathBuf::from("shaders").join(name);
        let target = out.join(format!("{name}.spv"));
        let status = Command::new(&glslc)
            .args(["--target-env=vulkan1.2", "--target-spv=spv1.4", "-O", "-Werror", "-o"])
            .arg(&target)
            .arg(&source)
            .status()
            .unwrap_or_else(|e| panic!("could not run {glslc} (Debian package glslc): {e}"));
        assert!(status.success(), "{glslc} failed on {}", source.display());
    }
}

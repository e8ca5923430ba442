//! Compiles the GLSL in shaders/ to SPIR-V 1.4 with glslc; src/gpu/shaders.rs embeds the results.
//! Modules keep their names (OpName, OpMemberName: `gpu::records`' tests find the records and
//! their members by name) but no other debug information.

use std::path::PathBuf;
use std::process::{Command, ExitStatus};
use std::time::{Duration, Instant};

const SHADERS: &[&str] = &[
    "trace_ray_query.comp",
    "raygen.rgen",
    "closest_hit.rchit",
    "miss.rmiss",
    "trace_exact_ray_query.comp",
    "raygen_exact.rgen",
    "intersection_exact.rint",
    "sphere.rint",
    "any_hit_all.rahit",
    "any_hit_opacity.rahit",
    "closest_point.comp",
    "winding.comp",
    "pack_rays.comp",
    "point_order.comp",
    "sign_points.comp",
];

/// How long glslc may take over one shader (each takes well under 5 s): some shapes of code with
/// `precise` values send glslang 2023.2 into minutes and gigabytes (shaders/exact.glsl `add_cap`),
/// which should fail the build with a name rather than hang it.
const GLSLC_LIMIT: Duration = Duration::from_secs(120);

/// Runs `command` to its end, or kills it after `limit`.
fn run_within(command: &mut Command, limit: Duration) -> std::io::Result<ExitStatus> {
    let mut child = command.spawn()?;
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait()? {
            return Ok(status);
        }
        if started.elapsed() > limit {
            child.kill()?;
            child.wait()?;
            return Err(std::io::Error::other(format!("no answer within {} s: killed", limit.as_secs())));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn main() {
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    println!("cargo:rerun-if-env-changed=GLSLC");
    println!("cargo:rerun-if-changed=shaders");
    for name in SHADERS {
        let source = PathBuf::from("shaders").join(name);
        let target = out.join(format!("{name}.spv"));
        let mut command = Command::new(&glslc);
        command
            .args(["--target-env=vulkan1.2", "--target-spv=spv1.4", "-O", "-g", "-Werror", "-o"])
            .arg(&target)
            .arg(&source);
        let status = run_within(&mut command, GLSLC_LIMIT)
            .unwrap_or_else(|e| panic!("could not run {glslc} (Debian package glslc) on {}: {e}", source.display()));
        assert!(status.success(), "{glslc} failed on {}", source.display());
        let spirv = std::fs::read(&target).expect("glslc wrote its output");
        std::fs::write(&target, names_only(&spirv)).expect("target is writable");
    }
}

/// The module without the debug instructions `-g` adds besides names: source text, file names,
/// line numbers, processing notes. Without `-g`, glslc's optimizer strips them all, names too; the
/// code is the same either way.
fn names_only(spirv: &[u8]) -> Vec<u8> {
    const DROPPED: [u32; 7] = [
        2,   // OpSourceContinued
        3,   // OpSource
        4,   // OpSourceExtension
        7,   // OpString
        8,   // OpLine
        317, // OpNoLine
        330, // OpModuleProcessed
    ];
    let words: Vec<u32> = spirv.chunks_exact(4).map(|b| u32::from_le_bytes(b.try_into().unwrap())).collect();
    assert!(spirv.len() % 4 == 0 && words.len() >= 5 && words[0] == 0x0723_0203, "glslc wrote little-endian SPIR-V");
    let mut kept = words[..5].to_vec();
    let mut at = 5;
    while at < words.len() {
        let count = (words[at] >> 16) as usize;
        assert!(count > 0 && at + count <= words.len(), "malformed SPIR-V instruction at word {at}");
        if !DROPPED.contains(&(words[at] & 0xFFFF)) {
            kept.extend_from_slice(&words[at..at + count]);
        }
        at += count;
    }
    kept.iter().flat_map(|w| w.to_le_bytes()).collect()
}

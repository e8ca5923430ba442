//! Compiles the GLSL in shaders/ to SPIR-V 1.4 with glslc; src/gpu/shaders.rs embeds the results.
//! Modules keep their names (OpName, OpMemberName: `gpu::records`' tests find the records and
//! their members by name) but no other debug information.
//!
//! spirv/ holds the same modules, committed, so that a build from the sdist needs no glslc: where
//! glslc is absent (not on PATH, or `GLSLC` names no file), each shader's committed module is used
//! when spirv/manifest.txt's hash of its source (with the headers it includes) is the hash of the
//! source here; otherwise the build fails naming the shader. Where glslc is present, it compiles as
//! always, and a committed module that differs from its output (or a stale hash) is a warning here
//! and a failure in tests/test_packaging.py. `VKRAY_UPDATE_SPIRV=1 cargo check` rewrites spirv/.

use std::collections::{BTreeMap, BTreeSet};
use std::io::ErrorKind;
use std::path::{Path, PathBuf};
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
    "cap_winding.comp",
    "list_offsets.comp",
    "hit_columns.comp",
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

/// Where the committed modules live (not in shaders/: every file there but the headers is a shader).
const SPIRV_DIR: &str = "spirv";
/// Each shader's hashes: `<shader> <source hash> <module hash> <headers it includes>`.
const MANIFEST: &str = "spirv/manifest.txt";
/// The one command that refreshes spirv/ after a shader changes.
const UPDATE_COMMAND: &str = "VKRAY_UPDATE_SPIRV=1 cargo check";

fn main() {
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    let update = std::env::var("VKRAY_UPDATE_SPIRV").is_ok_and(|v| v == "1");
    println!("cargo:rerun-if-env-changed=GLSLC");
    println!("cargo:rerun-if-env-changed=VKRAY_UPDATE_SPIRV");
    println!("cargo:rerun-if-changed=shaders");
    println!("cargo:rerun-if-changed={SPIRV_DIR}");
    let committed = read_manifest();
    let mut manifest = Vec::new();
    let mut stale = Vec::new();
    for name in SHADERS {
        let (source_hash, headers) = source_hash(name);
        let entry = committed.get(*name);
        let spirv = match compile(&glslc, name, &out) {
            Some(spirv) => {
                let current = entry.is_some_and(|e| e.source == source_hash && e.module == fnv1a(&spirv))
                    && std::fs::read(committed_path(name)).is_ok_and(|c| c == spirv);
                if !current {
                    stale.push(*name);
                }
                spirv
            }
            None => {
                assert!(
                    !update,
                    "VKRAY_UPDATE_SPIRV=1 needs glslc (Debian package glslc; or GLSLC=<path>): could not run {glslc}"
                );
                committed_module(name, source_hash, entry, &glslc)
            }
        };
        std::fs::write(out.join(format!("{name}.spv")), &spirv).expect("OUT_DIR is writable");
        manifest.push(format!("{name} {source_hash:016x} {:016x} {}", fnv1a(&spirv), headers.join(",")));
    }
    if update {
        write_committed(&glslc, &manifest);
    } else if !stale.is_empty() {
        println!(
            "cargo:warning=spirv/ is out of date with shaders/ for {} (a build without glslc would fail or embed old code): \
             run `{UPDATE_COMMAND}` and commit spirv/",
            stale.join(", ")
        );
    }
}

/// The committed module of `name` where its recorded hashes are those of the source here and of
/// the module file; else the build fails, naming the shader.
fn committed_module(name: &str, source_hash: u64, entry: Option<&Entry>, glslc: &str) -> Vec<u8> {
    let install = format!(
        "glslc was not found ({glslc}); install it (Debian/Ubuntu package glslc, or the Vulkan SDK; \
         GLSLC=<path> names it) to compile shaders/{name}"
    );
    let Some(entry) = entry else { panic!("{MANIFEST} has no entry for shaders/{name}: {install}") };
    assert!(
        entry.source == source_hash,
        "shaders/{name} (or a header it includes) differs from the source its committed SPIR-V \
         {SPIRV_DIR}/{name}.spv was compiled from: {install}"
    );
    let path = committed_path(name);
    let spirv = std::fs::read(&path).unwrap_or_else(|e| panic!("could not read {}: {e}; {install}", path.display()));
    assert!(
        fnv1a(&spirv) == entry.module,
        "{} is not the module {MANIFEST} records for it (damaged?): {install}",
        path.display()
    );
    spirv
}

/// glslc's module of shaders/`name`, debug information but names stripped; None where glslc
/// cannot be found. Any other failure fails the build.
fn compile(glslc: &str, name: &str, out: &Path) -> Option<Vec<u8>> {
    let source = PathBuf::from("shaders").join(name);
    let target = out.join(format!("{name}.glslc.spv"));
    let mut command = Command::new(glslc);
    command
        .args(["--target-env=vulkan1.2", "--target-spv=spv1.4", "-O", "-g", "-Werror", "-o"])
        .arg(&target)
        .arg(&source);
    let status = match run_within(&mut command, GLSLC_LIMIT) {
        Ok(status) => status,
        Err(e) if e.kind() == ErrorKind::NotFound => return None,
        Err(e) => panic!("could not run {glslc} (Debian package glslc) on {}: {e}", source.display()),
    };
    assert!(status.success(), "{glslc} failed on {}", source.display());
    let spirv = std::fs::read(&target).expect("glslc wrote its output");
    Some(names_only(&spirv))
}

fn committed_path(name: &str) -> PathBuf {
    PathBuf::from(SPIRV_DIR).join(format!("{name}.spv"))
}

/// A shader's recorded hashes.
struct Entry {
    source: u64,
    module: u64,
}

/// spirv/manifest.txt by shader name (empty where there is none).
fn read_manifest() -> BTreeMap<String, Entry> {
    let Ok(text) = std::fs::read_to_string(MANIFEST) else { return BTreeMap::new() };
    let hex = |s: Option<&str>| s.and_then(|s| u64::from_str_radix(s, 16).ok());
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .filter_map(|l| {
            let mut fields = l.split_whitespace();
            let name = fields.next()?.to_string();
            Some((name, Entry { source: hex(fields.next())?, module: hex(fields.next())? }))
        })
        .collect()
}

/// Writes every module and the manifest to spirv/ (and removes modules of shaders that are gone).
fn write_committed(glslc: &str, manifest: &[String]) {
    let dir = Path::new(SPIRV_DIR);
    std::fs::create_dir_all(dir).expect("spirv/ can be made");
    for entry in std::fs::read_dir(dir).expect("spirv/ is readable") {
        let path = entry.expect("spirv/ is readable").path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        if path.extension().is_some_and(|e| e == "spv") && !SHADERS.iter().any(|s| format!("{s}.spv") == name) {
            std::fs::remove_file(&path).expect("spirv/ is writable");
        }
    }
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    for name in SHADERS {
        std::fs::copy(out.join(format!("{name}.spv")), committed_path(name)).expect("spirv/ is writable");
    }
    let version = Command::new(glslc)
        .arg("--version")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).lines().next().unwrap_or_default().to_string())
        .unwrap_or_default();
    let text = format!(
        "# SPIR-V of shaders/, compiled by build.rs with {version}; refreshed by `{UPDATE_COMMAND}`.\n\
         # A build without glslc uses spirv/<shader>.spv where the source hash below is that of the source.\n\
         # <shader> <FNV-1a 64 of its source and the headers it includes> <FNV-1a 64 of the module> <headers>\n{}\n",
        manifest.join("\n")
    );
    std::fs::write(MANIFEST, text).expect("spirv/ is writable");
}

/// The hash of shaders/`name` and every header it includes (transitively), with those headers'
/// names. Each file counts by its name and its text with `\r\n` read as `\n` (a checkout with
/// Windows line ends compiles to the same module). tests/test_packaging.py computes the same.
fn source_hash(name: &str) -> (u64, Vec<String>) {
    let read = |file: &str| {
        let path = Path::new("shaders").join(file);
        std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("could not read {}: {e}", path.display()))
            .replace("\r\n", "\n")
    };
    let mut headers = BTreeSet::new();
    let mut pending = vec![read(name)];
    let text = pending[0].clone();
    while let Some(source) = pending.pop() {
        for include in includes(&source) {
            if headers.insert(include.clone()) {
                pending.push(read(&include));
            }
        }
    }
    let mut bytes = Vec::new();
    for (file, text) in std::iter::once((name.to_string(), text)).chain(headers.iter().map(|h| (h.clone(), read(h)))) {
        bytes.extend_from_slice(format!("{file}\0{}\0", text.len()).as_bytes());
        bytes.extend_from_slice(text.as_bytes());
    }
    (fnv1a(&bytes), headers.into_iter().collect())
}

/// The files `#include "..."` lines of `source` name.
fn includes(source: &str) -> Vec<String> {
    source
        .lines()
        .filter_map(|line| {
            let rest = line.trim_start().strip_prefix('#')?.trim_start().strip_prefix("include")?;
            let rest = rest.trim_start().strip_prefix('"')?;
            Some(rest[..rest.find('"')?].to_string())
        })
        .collect()
}

/// FNV-1a, 64 bits: a change check (not a defence against forgery), written out here because
/// the build script has no dependencies.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
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

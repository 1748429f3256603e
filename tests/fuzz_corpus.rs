//! The fuzz targets' committed seeds (`fuzz/seeds/TARGET/`) replayed through the targets'
//! own code (`fuzz/src/lib.rs`, included here) as an ordinary test.
//!
//! CI cannot afford a sanitizer build of rayd for every run, so this is its share of the
//! fuzzing: every seed, and every input a fuzz run found to crash (kept as a seed named
//! after what it found), goes through exactly what `cargo fuzz run TARGET` runs, on every
//! `cargo test`. Longer runs are `scripts/fuzz.sh SECONDS` (BENCHMARKS.md §16).

#[path = "../fuzz/src/lib.rs"]
mod targets;

use std::path::Path;

/// Runs every seed of `target` through `f`; there must be some.
fn replay(target: &str, f: fn(&[u8])) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/seeds")
        .join(target);
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no seeds in {}", dir.display());
    for file in files {
        let bytes = std::fs::read(&file).unwrap();
        eprintln!("{target}: {}", file.display());
        f(&bytes);
    }
}

#[test]
fn gltf_glb_seeds() {
    replay("gltf_glb", targets::gltf_glb);
}

#[test]
fn gltf_json_seeds() {
    replay("gltf_json", targets::gltf_json);
}

#[test]
fn tri1_seeds() {
    replay("tri1", targets::tri1);
}

#[test]
fn ray1_seeds() {
    replay("ray1", targets::ray1);
}

#[test]
fn hit1_seeds() {
    replay("hit1", targets::hit1);
}

#[test]
fn http_seeds() {
    replay("http", targets::http);
}

//! Fuzz target `gltf_glb`: see `rayd_fuzz::gltf_glb`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::gltf_glb(data));

//! Fuzz target `gltf_json`: see `rayd_fuzz::gltf_json`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::gltf_json(data));

//! Fuzz target `http`: see `rayd_fuzz::http`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::http(data));

//! Fuzz target `tri1`: see `rayd_fuzz::tri1`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::tri1(data));

//! Fuzz target `ray1`: see `rayd_fuzz::ray1`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::ray1(data));

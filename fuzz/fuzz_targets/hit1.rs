//! Fuzz target `hit1`: see `rayd_fuzz::hit1`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayd_fuzz::hit1(data));

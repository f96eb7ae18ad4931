#![no_main]
//! See `rayfarm_fuzz::ray_batch` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::ray_batch(data));

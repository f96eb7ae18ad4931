#![no_main]
//! See `rayfarm_fuzz::mesh` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::mesh(data));

#![no_main]
//! See `rayfarm_fuzz::manifest` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::manifest(data));

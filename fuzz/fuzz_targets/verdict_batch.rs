#![no_main]
//! See `rayfarm_fuzz::verdict_batch` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::verdict_batch(data));

#![no_main]
//! See `rayfarm_fuzz::transfer_function` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::transfer_function(data));

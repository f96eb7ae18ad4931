#![no_main]
//! See `rayfarm_fuzz::domain_request` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::domain_request(data));

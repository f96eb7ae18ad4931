#![no_main]
//! See `rayfarm_fuzz::job_api_request` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::job_api_request(data));

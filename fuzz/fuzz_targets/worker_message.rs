#![no_main]
//! See `rayfarm_fuzz::worker_message` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::worker_message(data));

#![no_main]
//! See `rayfarm_fuzz::peer_bundle` for what is checked.

libfuzzer_sys::fuzz_target!(|data: &[u8]| rayfarm_fuzz::peer_bundle(data));

//! `marea::fuzzing::shm_frames`: see that module for what is generated and what is checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| marea::fuzzing::shm_frames(data));

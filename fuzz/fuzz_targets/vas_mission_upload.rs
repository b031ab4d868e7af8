//! `vas::mavlink_cm::fuzz_mission_upload`: MAVLink mission requests and acks in random order
//! into the VAS's mission upload machine.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| vas::mavlink_cm::fuzz_mission_upload(data));

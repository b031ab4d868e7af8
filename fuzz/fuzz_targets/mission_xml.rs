//! Mission files for `usal run`: generated missions of realistic shape (nodes, services, a radio,
//! a station), a share bent or damaged, through the launcher's parser. The launcher is a binary
//! crate, so its mission module and generator are included here as source.
#![no_main]

#[allow(dead_code)]
#[path = "../../src/run/mission.rs"]
mod mission;

libfuzzer_sys::fuzz_target!(|data: &[u8]| mission::fuzz::check(data));

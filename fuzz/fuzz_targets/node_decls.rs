//! `marea::fuzzing::node_decls`: see that module for what is generated and what is checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| marea::fuzzing::node_decls(data));

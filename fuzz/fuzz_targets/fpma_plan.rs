//! `flightplan::fuzzing::plan_xml`: generated plans of realistic size, bent, parsed and expanded.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| flightplan::fuzzing::plan_xml(data));

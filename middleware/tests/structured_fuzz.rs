//! The structure-aware fuzz harnesses of `marea::fuzzing` (the ones `fuzz/` runs
//! under libFuzzer) run here on stable over a bounded number of seeded inputs, plus every input
//! a fuzzer once failed on (`fuzz/regressions/<target>/`), so `cargo test` keeps
//! what the fuzzers found fixed.
//!
//! Each harness panics when one of its properties fails (see `marea::fuzzing`); a test fails
//! with the seed that made the input, so a failure is reproducible.

use std::path::Path;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};

/// Inputs per harness, and the wall-clock cap per harness (debug builds are slow; the cap only
/// shortens the run, it asserts nothing).
const CASES: u64 = 400;
const CAP: Duration = Duration::from_secs(4);

fn run(target: &str, harness: fn(&[u8])) {
    // What the fuzzers found, first.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/regressions")
        .join(target);
    if let Ok(entries) = std::fs::read_dir(&dir) {
        for e in entries.flatten() {
            let bytes = std::fs::read(e.path()).expect("regression input readable");
            harness(&bytes);
        }
    }
    let started = Instant::now();
    for seed in 0..CASES {
        if started.elapsed() > CAP {
            break;
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x5EED_F022);
        let len = rng.random_range(0..4096usize);
        let mut data = vec![0u8; len];
        rng.fill(&mut data[..]);
        let result = std::panic::catch_unwind(|| harness(&data));
        if let Err(e) = result {
            // Kept where a regression input can be copied from.
            let keep = std::env::temp_dir().join(format!("structured_fuzz-{target}-{seed}"));
            let _ = std::fs::write(&keep, &data);
            panic!(
                "{target}: seed {seed} failed (input kept in {}): {e:?}",
                keep.display()
            );
        }
    }
}

#[test]
fn structured_fuzz_message() {
    run("message", marea::fuzzing::message);
}

#[test]
fn structured_fuzz_decl_batch() {
    run("decl_batch", marea::fuzzing::decl_batch);
}

#[test]
fn structured_fuzz_udp_datagrams() {
    run("udp_datagrams", marea::fuzzing::udp_datagrams);
}

#[test]
fn structured_fuzz_stp_frames() {
    run("stp_frames", marea::fuzzing::stp_frames);
}

#[cfg(feature = "shm")]
#[test]
fn structured_fuzz_shm_frames() {
    run("shm_frames", marea::fuzzing::shm_frames);
}

#[test]
fn structured_fuzz_file_chunks() {
    run("file_chunks", marea::fuzzing::file_chunks);
}

#[test]
fn reference_matcher_is_right_on_known_cases() {
    use marea::fuzzing::reference_match as m;
    assert!(m("*/vas/position", "rover1/vas/position"));
    assert!(m("**/vas/position", "vas/position"));
    assert!(m("rover1/**", "rover1"));
    assert!(!m("a/*", "a/b/c"));
    assert!(m("**/**/b", "a/a/b"));
    assert!(!m("**/**/zz", "a/a/b"));
}

#[test]
fn structured_fuzz_node_decls() {
    run("node_decls", marea::fuzzing::node_decls);
}

//! The plan XML harness of `flightplan::fuzzing` (target `fpma_plan` of `fuzz/`) on
//! stable, over a bounded number of seeded inputs plus every input a fuzzer once failed on
//! (`fuzz/regressions/fpma_plan/`).

use std::path::Path;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};

#[test]
fn structured_fuzz_plan_xml() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/fpma_plan");
    if let Ok(entries) = std::fs::read_dir(&dir) {
        for e in entries.flatten() {
            flightplan::fuzzing::plan_xml(
                &std::fs::read(e.path()).expect("regression input readable"),
            );
        }
    }
    // A cap on the wall-clock time only shortens the run in slow debug builds.
    let started = Instant::now();
    for seed in 0..300u64 {
        if started.elapsed() > Duration::from_secs(6) {
            break;
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0xF1A9);
        let mut data = vec![0u8; rng.random_range(0..4096usize)];
        rng.fill(&mut data[..]);
        if let Err(e) = std::panic::catch_unwind(|| flightplan::fuzzing::plan_xml(&data)) {
            let keep = std::env::temp_dir().join(format!("structured_fuzz-fpma_plan-{seed}"));
            let _ = std::fs::write(&keep, &data);
            panic!(
                "seed {seed} failed (input kept in {}): {e:?}",
                keep.display()
            );
        }
    }
}

#[test]
fn the_plan_generator_makes_plans_that_parse() {
    let mut parsed = 0;
    for seed in 0..100u64 {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut data = vec![0u8; 4096];
        rng.fill(&mut data[..]);
        match flightplan::fuzzing::generated_plan_parses(&data) {
            Some(Ok(())) => parsed += 1,
            Some(Err(e)) if seed < 8 => eprintln!("seed {seed}: {e}"),
            _ => {}
        }
    }
    assert!(parsed >= 10, "only {parsed} of 100 generated plans parse");
}

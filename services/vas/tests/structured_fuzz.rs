//! The mission upload harness (`vas::mavlink_cm::fuzz_mission_upload`, target
//! `vas_mission_upload` of `fuzz/`) on stable, over a bounded number of seeded
//! inputs plus every input a fuzzer once failed on (`fuzz/regressions/vas_mission_upload/`).

use std::path::Path;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};

#[test]
fn structured_fuzz_mission_upload() {
    let dir =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/vas_mission_upload");
    if let Ok(entries) = std::fs::read_dir(&dir) {
        for e in entries.flatten() {
            let bytes = std::fs::read(e.path()).expect("regression input readable");
            vas::mavlink_cm::fuzz_mission_upload(&bytes);
        }
    }
    // A cap on the wall-clock time only shortens the run in slow debug builds.
    let started = Instant::now();
    for seed in 0..500u64 {
        if started.elapsed() > Duration::from_secs(4) {
            break;
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x7A5);
        let mut data = vec![0u8; rng.random_range(0..2048usize)];
        rng.fill(&mut data[..]);
        if let Err(e) = std::panic::catch_unwind(|| vas::mavlink_cm::fuzz_mission_upload(&data)) {
            let keep = std::env::temp_dir().join(format!("structured_fuzz-vas-{seed}"));
            let _ = std::fs::write(&keep, &data);
            panic!(
                "seed {seed} failed (input kept in {}): {e:?}",
                keep.display()
            );
        }
    }
}

//! What the FPMa's process tests share: building and starting `vas` and `mavsim` beside the
//! `fpma` binary, stopping them, and reading mavsim's log.
// Each test file uses its own part of this module.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::OnceLock;
use std::time::Duration;

use tokio::process::{Child, Command};
use tokio::time::timeout;

/// `vas` and `mavsim`, built once into this test's target directory.
pub fn sibling_bins() -> &'static (PathBuf, PathBuf) {
    static BINS: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    BINS.get_or_init(|| {
        // <target>/debug/deps/<test binary>: the target directory is three levels up.
        let exe = std::env::current_exe().expect("test binary path");
        let target = exe
            .ancestors()
            .nth(3)
            .expect("test binary inside <target>/<profile>/deps")
            .to_owned();
        let status = std::process::Command::new(env!("CARGO"))
            .args(["build", "-p", "vas", "-p", "mavsim", "--bins"])
            .env("CARGO_TARGET_DIR", &target)
            .status()
            .expect("running cargo build -p vas -p mavsim");
        assert!(status.success(), "building vas and mavsim failed");
        let vas = target.join("debug").join("vas");
        let sim = target.join("debug").join("mavsim");
        assert!(
            vas.exists() && sim.exists(),
            "no binaries in {}",
            target.display()
        );
        (vas, sim)
    })
}

/// Starts `bin` (killed when dropped); its stderr goes to the test's.
pub fn spawn(bin: &Path, args: &[&str], stdout: Stdio) -> Child {
    Command::new(bin)
        .args(args)
        .stdout(stdout)
        .stderr(Stdio::inherit())
        .kill_on_drop(true)
        .spawn()
        .unwrap_or_else(|e| panic!("spawn {}: {e}", bin.display()))
}

/// Kills `c` and waits for it, at most 20 s.
pub async fn kill(mut c: Child) {
    let _ = c.start_kill();
    let _ = timeout(Duration::from_secs(20), c.wait()).await;
}

/// mavsim's `item_reached` records as (lat, lon).
pub fn sim_reached(log: &Path) -> Vec<(f64, f64)> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|r| r["event"] == "item_reached")
        .filter_map(|r| Some((r["lat"].as_f64()?, r["lon"].as_f64()?)))
        .collect()
}

/// The same point, to a micro-degree.
pub fn close(a: (f64, f64), b: (f64, f64)) -> bool {
    (a.0 - b.0).abs() < 1e-6 && (a.1 - b.1).abs() < 1e-6
}

/// The operator's "Start": waits until the FPMa says its plan is ready (variable `ready`), then
/// puts the VAS in WAYPOINT_NAVIGATION (the FPMa never does, issue 15); returns the state the
/// VAS left.
pub async fn start_when_ready(
    ready: &marea::VariableSubscriber<fpma::api::Readiness>,
    change: &marea::Function<usal_types::StateChangeRequest, usal_types::StateChangeReply>,
    within: Duration,
) -> usal_types::FlightState {
    timeout(within, async {
        while !ready.recv().await.expect("fpma ready").value.ready {}
    })
    .await
    .expect("the FPMa never said its plan was ready");
    let to = usal_types::FlightState::WaypointNavigation;
    change
        .call(&usal_types::StateChangeRequest { to }, within)
        .await
        .expect("the operator's WAYPOINT_NAVIGATION")
        .from
}

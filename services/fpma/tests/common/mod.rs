//! What the FPMa's process tests share: building and starting `mavsim`, `vas` and `fpma`, a
//! ground node, stopping them, and reading mavsim's log.
// Each test file uses its own part of this module.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::OnceLock;
use std::time::Duration;

use marea::{NetworkConfig, Node};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio::time::timeout;

/// How long one start-up step may take.
const START: Duration = Duration::from_secs(30);

/// `vas` and `mavsim`, built once into this test's target directory.
pub fn sibling_bins() -> &'static (PathBuf, PathBuf) {
    static BINS: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    BINS.get_or_init(|| {
        (
            test_support::workspace_bin("vas"),
            test_support::workspace_bin("mavsim"),
        )
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

/// Starts mavsim on a free UDP port (`--udp 127.0.0.1:0`, then `args`); returns it and the
/// address it printed.
pub async fn start_mavsim(args: &[&str]) -> (Child, String) {
    let (_, sim_bin) = sibling_bins();
    let mut all = vec!["--udp", "127.0.0.1:0"];
    all.extend_from_slice(args);
    let mut sim = spawn(sim_bin, &all, Stdio::piped());
    let line = timeout(
        START,
        BufReader::new(sim.stdout.take().expect("piped stdout"))
            .lines()
            .next_line(),
    )
    .await
    .expect("mavsim printed its address")
    .expect("reading mavsim's stdout")
    .expect("mavsim exited early");
    let addr = line
        .strip_prefix("MAVSIM_UDP=")
        .expect("MAVSIM_UDP=")
        .to_owned();
    (sim, addr)
}

/// Starts the VAS of namespace `rover1` in `domain` on the mavsim at `addr`, with `extra`
/// arguments.
pub fn start_vas(addr: &str, domain: &str, extra: &[&str]) -> Child {
    let (vas_bin, _) = sibling_bins();
    let endpoint = format!("udpout:{addr}");
    let mut args = vec![
        "--endpoint",
        &endpoint,
        "--domain",
        domain,
        "--namespace",
        "rover1",
    ];
    args.extend_from_slice(extra);
    spawn(vas_bin, &args, Stdio::null())
}

/// Starts `fpma run` for namespace `rover1` in `domain`, flying a `vehicle` (`rover`,
/// `aircraft`), with its own plans and state directories (never the user's: a test starts
/// without a plan unless it put one there), and `extra` arguments.
pub fn start_fpma(
    domain: &str,
    vehicle: &str,
    plans: &Path,
    state: &Path,
    extra: &[&str],
) -> Child {
    let plans = plans.to_str().expect("UTF-8 temp path");
    let state = state.to_str().expect("UTF-8 temp path");
    let mut args = vec![
        "run",
        "--domain",
        domain,
        "--namespace",
        "rover1",
        "--vehicle",
        vehicle,
        "--plans-dir",
        plans,
        "--state-dir",
        state,
    ];
    args.extend_from_slice(extra);
    spawn(Path::new(env!("CARGO_BIN_EXE_fpma")), &args, Stdio::null())
}

/// The ground station's node in `domain`.
pub async fn ground(domain: &str) -> Node {
    let mut cfg = NetworkConfig::ethernet_loopback("ground");
    cfg.domain = domain.to_owned();
    Node::open(&cfg).await.expect("ground node")
}

/// Kills `c` and waits for it, at most 20 s.
pub async fn kill(mut c: Child) {
    test_support::stop(&mut c).await;
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
/// puts the VAS in WAYPOINT_NAVIGATION (the FPMa never does: the flight state is the
/// operator's); returns the state the VAS left.
pub async fn start_when_ready(
    ready: &marea::VariableSubscriber<flightplan::api::Readiness>,
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

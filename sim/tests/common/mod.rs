//! Test harness: runs the real `mavsim` binary as a child process and connects a manager to it.

#![allow(dead_code)] // Each test file uses a different part of the harness.

use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use vas::mavlink_cm::{ManagerConfig, MavEvent, MavlinkManager, MissionItem};

/// Bound on every await of the tests.
pub const STEP: Duration = Duration::from_secs(20);
/// Home used by every test.
pub const HOME: (f64, f64, f64) = (41.2757, 1.9881, 10.0);

/// A running mavsim; killed on drop.
pub struct Sim {
    child: Child,
    /// Endpoint string for the manager.
    pub endpoint: String,
    /// The `--log` file.
    pub log: PathBuf,
    _dir: tempfile::TempDir,
}

/// How to reach the simulator.
#[derive(Clone, Copy, Debug)]
pub enum Via {
    Udp,
    /// UDP on this local port (to restart a simulator at the same address).
    UdpAt(u16),
    Pty,
}

impl Sim {
    /// Starts mavsim with `extra` arguments and waits for its endpoint line.
    pub async fn start(via: Via, extra: &[&str]) -> Sim {
        let dir = tempfile::tempdir().expect("tempdir");
        let log = dir.path().join("mavsim.jsonl");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mavsim"));
        cmd.arg("--home")
            .arg(format!("{},{},{}", HOME.0, HOME.1, HOME.2))
            .arg("--log")
            .arg(&log)
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true);
        match via {
            Via::Udp => cmd.args(["--udp", "127.0.0.1:0"]),
            Via::UdpAt(port) => cmd.args(["--udp", &format!("127.0.0.1:{port}")]),
            Via::Pty => cmd.arg("--pty"),
        };
        let mut child = cmd.spawn().expect("spawn mavsim");
        let stdout = child.stdout.take().expect("piped stdout");
        let mut lines = BufReader::new(stdout).lines();
        let line = tokio::time::timeout(STEP, lines.next_line())
            .await
            .expect("mavsim printed no endpoint in time")
            .expect("reading mavsim stdout")
            .expect("mavsim exited before printing its endpoint");
        let endpoint = if let Some(addr) = line.strip_prefix("MAVSIM_UDP=") {
            format!("udpout:{addr}")
        } else if let Some(path) = line.strip_prefix("MAVSIM_PTY=") {
            format!("serial:{path}:57600")
        } else {
            panic!("unexpected mavsim output {line:?}");
        };
        Sim {
            child,
            endpoint,
            log,
            _dir: dir,
        }
    }

    /// A connected manager.
    pub async fn manager(&self) -> MavlinkManager {
        let cfg = ManagerConfig {
            request_timeout: Duration::from_millis(500),
            ..ManagerConfig::default()
        };
        connect(&self.endpoint, cfg).await
    }

    /// The UDP port mavsim bound (UDP simulators only).
    pub fn udp_port(&self) -> u16 {
        self.endpoint
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .expect("a UDP endpoint")
    }

    /// The log lines so far, parsed.
    pub fn log_records(&self) -> Vec<serde_json::Value> {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .map(|l| serde_json::from_str(l).expect("log line is JSON"))
            .collect()
    }

    /// The log records of one event kind.
    pub fn log_events(&self, event: &str) -> Vec<serde_json::Value> {
        self.log_records()
            .into_iter()
            .filter(|r| r["event"] == event)
            .collect()
    }

    /// Stops mavsim with SIGTERM-equivalent kill and waits.
    pub async fn stop(mut self) {
        let _ = self.child.start_kill();
        let _ = tokio::time::timeout(STEP, self.child.wait()).await;
    }
}

/// A manager on `endpoint` with `cfg`, once the autopilot's heartbeat is seen.
pub async fn connect(endpoint: &str, cfg: ManagerConfig) -> MavlinkManager {
    let mgr = MavlinkManager::open(endpoint, cfg).await.expect("endpoint");
    mgr.wait_connected(STEP).await.expect("mavsim heartbeat");
    mgr
}

/// Home item plus `n` waypoints every `spacing` metres north of home.
pub fn line_mission(n: usize, spacing: f64, east: f64) -> Vec<MissionItem> {
    let m_per_deg_lat = 111_319.49;
    let m_per_deg_lon = m_per_deg_lat * HOME.0.to_radians().cos();
    let mut items = vec![MissionItem::waypoint(HOME.0, HOME.1, 0.0)];
    for i in 1..=n {
        items.push(MissionItem::waypoint(
            HOME.0 + spacing * i as f64 / m_per_deg_lat,
            HOME.1 + east / m_per_deg_lon,
            0.0,
        ));
    }
    items
}

/// Bounds a future by [`STEP`].
pub async fn bounded<F: std::future::Future>(what: &str, f: F) -> F::Output {
    tokio::time::timeout(STEP, f)
        .await
        .unwrap_or_else(|_| panic!("timed out: {what}"))
}

/// Uploads `items`, arms and switches to AUTO: the vehicle flies them. Returns the manager's
/// events from before the arming on.
pub async fn start_mission(
    mgr: &MavlinkManager,
    items: &[MissionItem],
) -> tokio::sync::broadcast::Receiver<MavEvent> {
    bounded("upload", mgr.mission_upload(items))
        .await
        .expect("upload");
    let events = mgr.subscribe();
    bounded("arm", mgr.arm(true)).await.expect("arm");
    bounded("auto", mgr.set_mode("AUTO")).await.expect("auto");
    events
}

//! Test harness: the real `mavsim` and `vas` binaries as child processes, and a ground
//! station (a marea node in the test process) that talks to the VAS over UDP.

#![allow(dead_code)] // Each test file uses a different part of the harness.

pub mod mavsdk;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::OnceLock;
use std::time::Duration;

use marea::{EventSubscriber, Function, NetworkConfig, Node, Service, VariableSubscriber};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use usal_types::{
    Alarm, FlightState, QueueStatus, StateChangeReply, StateChangeRequest, StateChanged, Waypoint,
    WaypointReached,
};

/// Bound on every single wait of the tests.
pub const STEP: Duration = Duration::from_secs(20);
/// Home of every simulated vehicle.
pub const HOME: (f64, f64) = (41.2757, 1.9881);

/// The `mavsim` binary, built once per test process into this test's own target directory.
pub fn mavsim_bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| test_support::workspace_bin("mavsim"))
}

/// The `marea-radio` radio emulator (a bin of the root package `usal`), built like mavsim.
pub fn marea_radio_bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| test_support::workspace_bin("marea-radio"))
}

/// A running `marea-radio`: two pty pairs joined by an emulated 3DR radio link. Killed on
/// drop.
pub struct Radio {
    child: Child,
    /// The latest counters it printed (`--stats-ms`).
    stats: std::sync::Arc<std::sync::Mutex<Option<serde_json::Value>>>,
    /// How many outages it announced starting (`--outage-on-signal`).
    outages: tokio::sync::watch::Receiver<u64>,
    /// The ground side's device (the VAS opens it).
    pub ground: String,
    /// The air side's device (mavsim opens it).
    pub air: String,
}

impl Radio {
    /// Starts the emulator with these extra arguments (`--loss`, `--corrupt`, `--seed`...).
    pub async fn start(args: &[&str]) -> Radio {
        let mut child = Command::new(marea_radio_bin())
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .expect("spawn marea-radio");
        let stdout = child.stdout.take().expect("piped stdout");
        let mut lines = BufReader::new(stdout).lines();
        let line = tokio::time::timeout(STEP, lines.next_line())
            .await
            .expect("marea-radio printed no devices in time")
            .expect("reading marea-radio stdout")
            .expect("marea-radio exited early");
        let ports: serde_json::Value =
            serde_json::from_str(&line).unwrap_or_else(|e| panic!("{line:?}: {e}"));
        let dev = |side: &str| {
            ports[side]
                .as_str()
                .unwrap_or_else(|| panic!("no {side} device in {line:?}"))
                .to_owned()
        };
        let stats: std::sync::Arc<std::sync::Mutex<Option<serde_json::Value>>> =
            std::sync::Arc::default();
        let latest = std::sync::Arc::clone(&stats);
        let (outage_started, outages) = tokio::sync::watch::channel(0u64);
        // Ends with the child's stdout.
        tokio::spawn(async move {
            while let Ok(Some(line)) = lines.next_line().await {
                let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) else {
                    continue;
                };
                if v["event"] == "outage" {
                    outage_started.send_modify(|n| *n += 1);
                } else {
                    *latest.lock().unwrap_or_else(|p| p.into_inner()) = Some(v);
                }
            }
        });
        Radio {
            ground: dev("ground"),
            air: dev("air"),
            child,
            stats,
            outages,
        }
    }

    /// Cuts the link now (run it with `--outage-on-signal MS`): returns once the emulator
    /// announced the outage.
    pub async fn cut(&mut self) {
        let before = *self.outages.borrow_and_update();
        let pid = self.child.id().expect("marea-radio running");
        let sent = std::process::Command::new("kill")
            .args(["-USR1", &pid.to_string()])
            .status()
            .expect("run kill");
        assert!(sent.success(), "SIGUSR1 to marea-radio failed");
        tokio::time::timeout(STEP, self.outages.wait_for(|n| *n > before))
            .await
            .expect("marea-radio announced no outage")
            .expect("marea-radio exited");
    }

    /// The latest counters printed (run it with `--stats-ms`).
    pub fn stats(&self) -> Option<serde_json::Value> {
        self.stats.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        test_support::stop(&mut self.child).await;
    }
}

/// A running mavsim, killed on drop.
pub struct Sim {
    child: Child,
    /// `127.0.0.1:PORT` it listens on, or its serial device.
    pub addr: String,
    /// Its `--log` file.
    pub log: PathBuf,
}

impl Sim {
    /// Starts mavsim on `bind` (`127.0.0.1:0` for any port) logging to `log`.
    pub async fn start(bind: &str, speedup: f64, log: &Path) -> Sim {
        Sim::start_with(bind, speedup, log, &[]).await
    }

    /// [`Sim::start`] with extra mavsim arguments (`--vehicle copter`, `--quiet-progress`).
    pub async fn start_with(bind: &str, speedup: f64, log: &Path, extra: &[&str]) -> Sim {
        let args: Vec<&str> = ["--udp", bind].iter().chain(extra).copied().collect();
        Sim::spawn(&args, "MAVSIM_UDP=", speedup, log).await
    }

    /// Starts mavsim on the serial device (or pty slave) `path`; `addr` is the path.
    pub async fn start_serial(path: &str, speedup: f64, log: &Path) -> Sim {
        Sim::spawn(&["--serial", path], "MAVSIM_SERIAL=", speedup, log).await
    }

    async fn spawn(link: &[&str], prefix: &str, speedup: f64, log: &Path) -> Sim {
        let mut child = Command::new(mavsim_bin())
            .args(link)
            .args(["--speedup", &speedup.to_string()])
            .arg("--home")
            .arg(format!("{},{},10", HOME.0, HOME.1))
            .arg("--log")
            .arg(log)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .expect("spawn mavsim");
        let stdout = child.stdout.take().expect("piped stdout");
        let line = tokio::time::timeout(STEP, BufReader::new(stdout).lines().next_line())
            .await
            .expect("mavsim printed no address in time")
            .expect("reading mavsim stdout")
            .expect("mavsim exited early");
        let addr = line
            .strip_prefix(prefix)
            .unwrap_or_else(|| panic!("unexpected mavsim output {line:?}"))
            .to_owned();
        Sim {
            child,
            addr,
            log: log.to_owned(),
        }
    }

    /// The log records of one event kind.
    pub fn log_events(&self, event: &str) -> Vec<serde_json::Value> {
        log_events(&self.log, event)
    }

    /// Every record of the log, in order.
    pub fn log_records(&self) -> Vec<serde_json::Value> {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect()
    }

    /// The mission's story in the log (uploads, current-item changes, reaches, completion,
    /// mode changes), one record per line: for a failure message to say what the vehicle did.
    pub fn mission_story(&self) -> String {
        const EVENTS: [&str; 7] = [
            "mission_uploaded",
            "do_command",
            "mission_partial_write",
            "current_changed",
            "item_reached",
            "mission_complete",
            "mode_changed",
        ];
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter(|l| {
                serde_json::from_str::<serde_json::Value>(l)
                    .is_ok_and(|r| EVENTS.iter().any(|e| r["event"] == *e))
            })
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// Waits until the log's records of `event` satisfy `done` (polling the file: mavsim
    /// flushes each line, and no other signal says a record was written); panics with `what`
    /// after `within`. Returns those records.
    pub async fn wait_log(
        &self,
        event: &str,
        within: Duration,
        what: &str,
        done: impl Fn(&[serde_json::Value]) -> bool,
    ) -> Vec<serde_json::Value> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let records = self.log_events(event);
            if done(&records) {
                return records;
            }
            assert!(tokio::time::Instant::now() < deadline, "{what}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        test_support::stop(&mut self.child).await;
    }
}

/// The records of `event` in a mavsim log.
pub fn log_events(log: &Path, event: &str) -> Vec<serde_json::Value> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|r| r["event"] == event)
        .collect()
}

/// A running `vas`, killed on drop.
pub struct VasProc {
    child: Child,
}

impl VasProc {
    /// Starts the `vas` binary on `endpoint` in middleware `domain`, namespace `rover1`
    /// (telemetry at 4 Hz unless `extra` says otherwise).
    pub fn start(endpoint: &str, domain: &str, extra: &[&str]) -> VasProc {
        let rate: &[&str] = if extra.contains(&"--telemetry-hz") {
            &[]
        } else {
            &["--telemetry-hz", "4"]
        };
        let child = Command::new(env!("CARGO_BIN_EXE_vas"))
            .args(["--endpoint", endpoint, "--domain", domain])
            .args(["--namespace", "rover1"])
            .args(rate)
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .expect("spawn vas");
        VasProc { child }
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        test_support::stop(&mut self.child).await;
    }
}

/// A unique middleware domain, so parallel tests do not see each other's VAS.
pub fn unique_domain(tag: &str) -> String {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "vas-{tag}-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

/// The ground side of a test: what the FPMa and the FMo use of the VAS.
pub struct Ground {
    pub node: Node,
    pub svc: Service,
    pub change_state: Function<StateChangeRequest, StateChangeReply>,
    pub push: Function<Vec<Waypoint>, QueueStatus>,
    pub clear: Function<(), QueueStatus>,
    pub reached: EventSubscriber<WaypointReached>,
    pub changes: EventSubscriber<StateChanged>,
    pub alarms: EventSubscriber<Alarm>,
    pub state: VariableSubscriber<FlightState>,
}

impl Ground {
    /// Opens a node in `domain` and waits until the VAS answers.
    pub async fn open(domain: &str) -> Ground {
        let mut cfg = NetworkConfig::ethernet_loopback("ground");
        cfg.domain = domain.to_owned();
        let node = Node::open(&cfg).await.expect("ground node");
        let svc = node.service("gcs").expect("service");
        let g = Ground {
            change_state: svc.function("rover1/vas/change_state").unwrap(),
            push: svc.function("rover1/vas/push_waypoints").unwrap(),
            clear: svc.function("rover1/vas/clear_waypoints").unwrap(),
            reached: svc.subscribe_event("rover1/vas/waypoint_reached").unwrap(),
            changes: svc.subscribe_event("rover1/vas/state_changed").unwrap(),
            alarms: svc.subscribe_event("rover1/vas/alarm").unwrap(),
            state: svc.subscribe_variable("rover1/vas/flight_state").unwrap(),
            node,
            svc,
        };
        assert!(
            g.change_state.wait_provider(STEP).await,
            "the VAS was not discovered"
        );
        g
    }

    /// Waits until the flight state is `want`.
    pub async fn wait_state(&self, want: FlightState, within: Duration) {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            match self.state.recv_timeout(left).await {
                Ok(s) if s.value == want => return,
                Ok(_) => {}
                Err(e) => panic!("flight state never became {want}: {e}"),
            }
        }
    }

    /// Asks for a state change.
    pub async fn request(&self, to: FlightState) -> Result<StateChangeReply, String> {
        self.change_state
            .call(&StateChangeRequest { to }, STEP)
            .await
            .map_err(|e| e.to_string())
    }

    /// Pushes waypoints in chunks of 20.
    pub async fn push_all(&self, wps: &[Waypoint]) {
        for chunk in wps.chunks(20) {
            self.push
                .call(&chunk.to_vec(), STEP)
                .await
                .expect("push_waypoints");
        }
    }

    /// Flies `wps` from PARKING: pushes them, asks for WAYPOINT_NAVIGATION, checks that the VAS
    /// reports every waypoint reached once and in order (each within [`STEP`]), then waits for
    /// PARKING. `what` names the run in failure messages.
    pub async fn fly_in_order(&self, wps: &[Waypoint], what: &str) {
        self.push_all(wps).await;
        let reply = self.request(FlightState::WaypointNavigation).await;
        assert!(reply.is_ok(), "{what}: {reply:?}");
        let mut seen = Vec::new();
        while seen.len() < wps.len() {
            let r = tokio::time::timeout(STEP, self.reached.recv())
                .await
                .unwrap_or_else(|_| panic!("{what}: stalled after {} waypoints", seen.len()))
                .expect("waypoint_reached");
            seen.push(r.value.seq);
        }
        assert_eq!(
            seen,
            (0..wps.len() as u64).collect::<Vec<_>>(),
            "{what}: VAS reports in order"
        );
        self.wait_state(FlightState::Parking, STEP).await;
    }

    /// Waits for an alarm whose text contains `needle`.
    pub async fn wait_alarm(&self, needle: &str, within: Duration) -> Alarm {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            match self.alarms.recv_timeout(left).await {
                Ok(a) if a.value.text.contains(needle) => return a.value,
                Ok(_) => {}
                Err(e) => panic!("no alarm containing {needle:?}: {e}"),
            }
        }
    }
}

/// The last queue status the VAS published on `queue` (panics when none came).
pub fn latest_queue_status(queue: &VariableSubscriber<QueueStatus>) -> QueueStatus {
    let mut last = None;
    while let Some(Ok(s)) = queue.try_recv() {
        last = Some(s.value);
    }
    last.expect("queue status published")
}

/// `n` waypoints zigzagging north of home, `spacing` metres apart, seq from 0.
pub fn zigzag(n: usize, spacing: f64) -> Vec<Waypoint> {
    let m_per_deg_lat = 111_319.49;
    let m_per_deg_lon = m_per_deg_lat * HOME.0.to_radians().cos();
    (0..n)
        .map(|i| {
            let north = spacing * (i + 1) as f64;
            let east = if i % 2 == 0 { 0.0 } else { spacing / 2.0 };
            Waypoint {
                seq: i as u64,
                lat: HOME.0 + north / m_per_deg_lat,
                lon: HOME.1 + east / m_per_deg_lon,
                alt: 0.0,
                speed: 0.0,
                fly_over: false,
                leg: format!("leg{}", i / 50),
                ..Waypoint::default()
            }
        })
        .collect()
}

/// The (lat, lon) of `item_reached` records, for comparison with waypoints.
pub fn reached_points(records: &[serde_json::Value]) -> Vec<(f64, f64)> {
    records
        .iter()
        .map(|r| {
            (
                r["lat"].as_f64().expect("lat"),
                r["lon"].as_f64().expect("lon"),
            )
        })
        .collect()
}

/// Index of the waypoint at `p` (within 1e-6 degrees), if any.
pub fn which(wps: &[Waypoint], p: (f64, f64)) -> Option<usize> {
    wps.iter()
        .position(|w| (w.lat - p.0).abs() < 1e-6 && (w.lon - p.1).abs() < 1e-6)
}

//! The MAVSDK vehicle (`tests/python/mavsdk_vehicle.py`) as a child process, and the Python
//! that runs it: a MAVLink implementation not written here, for the conformance suite.
//!
//! Python is found as `USAL_TEST_PYTHON`, else the checkout's `.venv-test/bin/python`
//! (`.ci/run` creates it from `tests/python/requirements.txt`). Where Python 3 exists but the
//! venv does not, it is created here, under a file lock so tests running in parallel do not
//! race; only where `python3` is absent is the suite skipped, saying so.
//!
//! Self-contained (std, tokio, serde_json) so the waypoint benchmark can include it too.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, ChildStdin, Command};
use tokio::sync::mpsc;

/// The checkout's root (this file is `services/vas/tests/common/mavsdk.rs`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .find(|p| p.join("tests/python/requirements.txt").is_file())
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")))
}

fn runs(cmd: &Path, args: &[&str]) -> bool {
    std::process::Command::new(cmd)
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// What the test venv holds (`tests/python/requirements.txt`): a venv lacking one of them is
/// brought up to date.
const IMPORTS: &[&str] = &["-c", "import mavsdk, pymavlink, zenoh"];

/// The Python that has `mavsdk`, `pymavlink` and `zenoh`, creating the venv if needed; `None` (after
/// printing why) only where no `python3` exists, outside CI (under `CI` the test fails there). Blocking: call it off the async runtime.
///
/// # Panics
/// When `USAL_TEST_PYTHON` lacks the packages, or Python exists but the venv cannot be made:
/// those are broken set-ups to fix, not reasons to skip.
pub fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("USAL_TEST_PYTHON") {
        let p = PathBuf::from(p);
        assert!(
            runs(&p, IMPORTS),
            "USAL_TEST_PYTHON={} cannot import mavsdk, pymavlink and zenoh",
            p.display()
        );
        return Some(p);
    }
    let root = repo_root();
    let venv = root.join(".venv-test");
    let py = venv.join("bin/python");
    if runs(&py, IMPORTS) {
        return Some(py);
    }
    let python3 = PathBuf::from("python3");
    if !runs(&python3, &["--version"]) {
        test_support::tool_missing(
            "python3 (the MAVSDK conformance suite's vehicle)",
            "see docs/autopilots.md, \"Autopilots we did not write\"",
        );
        return None;
    }
    // One creator at a time; the others wait, then find it made.
    let lock = DirLock::acquire(&root.join(".venv-test.lock"));
    if !runs(&py, IMPORTS) {
        eprintln!(
            "creating {} from tests/python/requirements.txt",
            venv.display()
        );
        let ok = std::process::Command::new(&python3)
            .args(["-m", "venv"])
            .arg(&venv)
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "python3 -m venv {} failed", venv.display());
        let ok = std::process::Command::new(&py)
            .args(["-m", "pip", "install", "--quiet", "-r"])
            .arg(root.join("tests/python/requirements.txt"))
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "pip install into {} failed", venv.display());
    }
    drop(lock);
    assert!(
        runs(&py, IMPORTS),
        "{} cannot import mavsdk, pymavlink and zenoh",
        py.display()
    );
    Some(py)
}

/// A lock between processes: a directory, created atomically by its holder and removed on
/// drop. One left by a creator that died (older than [`DirLock::STALE`]) is taken over.
struct DirLock(PathBuf);

impl DirLock {
    /// A venv install takes a minute or two on a slow machine.
    const STALE: Duration = Duration::from_secs(15 * 60);

    fn acquire(path: &Path) -> DirLock {
        let deadline = std::time::Instant::now() + Self::STALE + Duration::from_secs(60);
        loop {
            match std::fs::create_dir(path) {
                Ok(()) => return DirLock(path.to_owned()),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let stale = std::fs::metadata(path)
                        .and_then(|m| m.modified())
                        .ok()
                        .and_then(|t| t.elapsed().ok())
                        .is_some_and(|age| age > Self::STALE);
                    if stale {
                        let _ = std::fs::remove_dir(path);
                        continue;
                    }
                    assert!(
                        std::time::Instant::now() < deadline,
                        "{} held too long",
                        path.display()
                    );
                    // No signal to wait on between processes: poll.
                    std::thread::sleep(Duration::from_millis(200));
                }
                Err(e) => panic!("creating the lock {}: {e}", path.display()),
            }
        }
    }
}

impl Drop for DirLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir(&self.0);
    }
}

pub use test_support::free_udp_port;

/// The running MAVSDK vehicle: its events as JSON values; killed on drop (and its stdin
/// closing stops it too).
pub struct MavsdkVehicle {
    child: Child,
    _stdin: Option<ChildStdin>,
    /// Every JSON line it printed, in order.
    pub events: mpsc::UnboundedReceiver<serde_json::Value>,
    /// The UDP port it listens on.
    pub port: u16,
}

impl MavsdkVehicle {
    /// Starts the vehicle with `python` on a free port at `speedup`, and waits for its
    /// `ready` line (up to `wait`).
    ///
    /// # Panics
    /// When it cannot start or does not get ready in time.
    pub async fn start(python: &Path, speedup: f64, wait: Duration) -> MavsdkVehicle {
        let port = free_udp_port();
        let script = repo_root().join("tests/python/mavsdk_vehicle.py");
        let mut child = Command::new(python)
            .arg(&script)
            .args(["--port", &port.to_string()])
            .args(["--speedup", &speedup.to_string()])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", script.display()));
        let stdin = child.stdin.take();
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, mut events) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            let mut lines = BufReader::new(stdout).lines();
            while let Ok(Some(line)) = lines.next_line().await {
                if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
                    if tx.send(v).is_err() {
                        return;
                    }
                }
            }
        });
        let ready = tokio::time::timeout(wait, async {
            while let Some(ev) = events.recv().await {
                if ev["event"] == "ready" {
                    return true;
                }
            }
            false
        })
        .await;
        assert!(
            matches!(ready, Ok(true)),
            "the MAVSDK vehicle did not get ready: {ready:?}"
        );
        MavsdkVehicle {
            child,
            _stdin: stdin,
            events,
            port,
        }
    }

    /// Every event printed so far.
    pub fn drain(&mut self) -> Vec<serde_json::Value> {
        let mut all = Vec::new();
        while let Ok(ev) = self.events.try_recv() {
            all.push(ev);
        }
        all
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        test_support::stop(&mut self.child).await;
    }
}

/// What the vehicle did with a plan of waypoints at `plan` (lat, lon), from its events.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Flown {
    /// Plan indices reached, in order.
    pub reached: Vec<usize>,
    /// Plan waypoints never reached.
    pub skipped: usize,
    /// Reaches of a waypoint already reached.
    pub repeated: usize,
    /// Times the current item, in a mission, became a waypoint already reached or a point
    /// not in the plan (home): the vehicle turned back.
    pub backtracks: usize,
}

/// Scores the vehicle's `events` against the plan's points.
pub fn score(events: &[serde_json::Value], plan: &[(f64, f64)]) -> Flown {
    let which = |ev: &serde_json::Value| {
        let (lat, lon) = (ev["lat"].as_f64()?, ev["lon"].as_f64()?);
        plan.iter()
            .position(|p| (p.0 - lat).abs() < 1e-6 && (p.1 - lon).abs() < 1e-6)
    };
    let mut f = Flown::default();
    let mut done = vec![false; plan.len()];
    let mut in_mission = false;
    let mut next = 0usize;
    for ev in events {
        match ev["event"].as_str() {
            Some("mode") => in_mission = ev["mode"] == "MISSION",
            Some("reached") => match which(ev) {
                Some(i) if done[i] => f.repeated += 1,
                Some(i) => {
                    done[i] = true;
                    f.reached.push(i);
                    next = next.max(i + 1);
                }
                None => f.backtracks += 1,
            },
            Some("current") if in_mission => match which(ev) {
                Some(i) if i + 1 < next => f.backtracks += 1,
                None => f.backtracks += 1,
                _ => {}
            },
            _ => {}
        }
    }
    f.skipped = done.iter().filter(|d| !**d).count();
    f
}

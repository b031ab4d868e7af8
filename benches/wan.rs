//! `cargo bench --bench wan`: the rover mission with its ground station beyond one LAN, as JSON
//! lines `{"metric": ..., "value": ..., "unit": ...}`.
//!
//! The release `usal run config/missions/rover-wan-failsafe.xml --until-complete` (it builds the
//! binaries it misses): air and ground on LANs of their own, each reaching a Zenoh router
//! through a gateway; the ground's gateway through `marea-wan` (150 ms round trip, 1 % segment
//! loss, 2 Mbit/s); the router killed and restarted 10 s in; the ground's path cut for 30 s,
//! 20 s in.
//!
//! - `zenoh.wan.mission_completed`: 1 when the run ended 0 with the plan completed as planned
//!   (every waypoint reached, in order, as the station saw it);
//! - `zenoh.wan.failsafes_seen`: of the two the outage must fire (the VAS holding on the lost
//!   link, resuming when it returns), how many the station's summary names;
//! - `zenoh.wan.flight_s`: the flight's wall-clock time, outage included.

use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};

use anyhow::{bail, Context};

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

/// Kills the launcher (and so its children) if the bench stops early.
struct Launcher(Child);

impl Drop for Launcher {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn main() -> anyhow::Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().context("temporary directory")?;
    let log = std::fs::File::create(dir.path().join("usal.log")).context("usal log")?;
    let mut child = Command::new(env!("CARGO_BIN_EXE_usal"))
        .args([
            "--json",
            "run",
            "config/missions/rover-wan-failsafe.xml",
            "--until-complete",
            "--timeout-s",
            "600",
        ])
        .current_dir(root)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .context("starting usal run")?;
    let out = child.stdout.take().context("usal stdout")?;
    let mut launcher = Launcher(child);
    let mut summary = None;
    for line in std::io::BufReader::new(out).lines() {
        let Ok(line) = line else { break };
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
            if v["event"] == "summary" {
                summary = Some(v);
            }
        }
    }
    // stdout closed: usal is exiting (its --timeout-s bounds the run).
    let status = launcher.0.wait().context("waiting for usal")?;
    let Some(v) = summary else {
        let log = std::fs::read_to_string(dir.path().join("usal.log")).unwrap_or_default();
        let tail = &log[log.len().saturating_sub(3000)..];
        bail!("the WAN mission printed no summary ({status})\nusal's log ends with:\n{tail}");
    };
    let s = &v["summary"];
    let completed = status.success() && s["completed"] == true && s["in_order"] == true;
    metric(
        "zenoh.wan.mission_completed",
        f64::from(u8::from(completed)),
        "bool",
    );
    let fired: Vec<String> = s["failsafes"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|f| {
                    format!(
                        "{} {}",
                        f["kind"].as_str().unwrap_or(""),
                        f["action"].as_str().unwrap_or("")
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    let seen = ["link-lost hold", "link-restored resume"]
        .iter()
        .filter(|f| fired.iter().any(|x| x == *f))
        .count();
    metric("zenoh.wan.failsafes_seen", seen as f64, "count");
    metric(
        "zenoh.wan.flight_s",
        s["elapsed_s"].as_f64().unwrap_or(f64::NAN),
        "s",
    );
    eprintln!("wan: {status}; failsafes {fired:?}");
    Ok(())
}

//! A ground station alongside: the `vas` binary forwards MAVLink between mavsim and an extra
//! endpoint (`--forward`, the `<forward>` element), where a pymavlink ground station
//! (`tests/python/second_gcs.py`) sees the autopilot and uploads a mission of its own. The VAS
//! notices it (the autopilot's MISSION_ACK to that station), stops feeding its queue instead of
//! fighting, reads the mission back and raises `mission_changed`.

mod common;

use std::process::Stdio;
use std::time::Duration;

use common::mavsdk::{free_udp_port, python, repo_root};
use common::*;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::process::Command;
use usal_types::{FlightState, MissionChanged};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_ground_station_is_forwarded_and_its_mission_followed() {
    let Some(py) = tokio::task::spawn_blocking(python)
        .await
        .expect("finding python")
    else {
        return;
    };
    let run = async {
        let dir = tempfile::tempdir().unwrap();
        let sim = Sim::start("127.0.0.1:0", 5.0, &dir.path().join("sim.jsonl")).await;
        let port = free_udp_port();
        let mut gcs = Command::new(&py)
            .arg(repo_root().join("tests/python/second_gcs.py"))
            .args(["--port", &port.to_string()])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .expect("starting second_gcs.py");
        let mut gcs_in = gcs.stdin.take().expect("stdin");
        let mut gcs_out = BufReader::new(gcs.stdout.take().expect("stdout")).lines();
        let domain = unique_domain("forward");
        let vas = VasProc::start(
            &format!("udpout:{}", sim.addr),
            &domain,
            &["--forward", &format!("udpout:127.0.0.1:{port}")],
        );
        let g = Ground::open(&domain).await;
        let changed = g
            .svc
            .subscribe_event::<MissionChanged>("rover1/vas/mission_changed")
            .unwrap();
        g.wait_state(FlightState::Parking, STEP).await;

        // The other station sees the autopilot through the VAS.
        let mut next_json = async || -> serde_json::Value {
            let line = tokio::time::timeout(STEP, gcs_out.next_line())
                .await
                .expect("second GCS silent")
                .expect("reading its output")
                .expect("second GCS exited");
            serde_json::from_str(&line).expect("a JSON line")
        };
        let hb = next_json().await;
        assert_eq!(hb["event"], "heartbeat", "{hb}");
        assert_eq!(hb["system"], 1);

        // USAL flies its plan ...
        let wps = zigzag(30, 10.0);
        g.push_all(&wps).await;
        g.request(FlightState::WaypointNavigation)
            .await
            .expect("WAYPOINT_NAVIGATION");
        for _ in 0..2 {
            tokio::time::timeout(STEP, g.reached.recv())
                .await
                .expect("progress")
                .expect("waypoint_reached");
        }
        // ... until the other station uploads its own mission.
        let theirs = [
            (HOME.0, HOME.1),
            (HOME.0 + 0.0002, HOME.1 + 0.0002),
            (HOME.0 + 0.0004, HOME.1),
            (HOME.0 + 0.0006, HOME.1 + 0.0002),
        ];
        let line: Vec<String> = theirs.iter().map(|p| format!("{},{}", p.0, p.1)).collect();
        gcs_in
            .write_all(format!("upload {}\n", line.join(";")).as_bytes())
            .await
            .unwrap();
        let up = next_json().await;
        assert_eq!(up["event"], "uploaded", "{up}");
        assert_eq!(up["result"], 0, "accepted: {up}");

        let ev = tokio::time::timeout(STEP, changed.recv())
            .await
            .expect("mission_changed raised")
            .expect("mission_changed");
        assert!(ev.value.by.contains("system 250"), "{:?}", ev.value);
        let got: Vec<(f64, f64)> = ev.value.waypoints.iter().map(|w| (w.lat, w.lon)).collect();
        assert_eq!(got.len(), 4, "{got:?}");
        for (a, b) in got.iter().zip(&theirs).skip(1) {
            assert!(
                (a.0 - b.0).abs() < 1e-6 && (a.1 - b.1).abs() < 1e-6,
                "{got:?}"
            );
        }
        // Not fought: the VAS writes nothing more to the autopilot's mission.
        let writes = |sim: &Sim| {
            sim.log_events("mission_uploaded").len() + sim.log_events("mission_partial_write").len()
        };
        let after = writes(&sim);
        tokio::time::sleep(Duration::from_secs(3)).await;
        assert_eq!(
            writes(&sim),
            after,
            "the VAS rewrote the other station's mission"
        );
        let last = sim.log_events("mission_uploaded");
        assert_eq!(last.last().map(|e| e["count"].clone()), Some(4.into()));

        drop(gcs_in);
        let _ = gcs.start_kill();
        vas.kill().await;
        sim.kill().await;
        g.node.shutdown().await;
    };
    tokio::time::timeout(STEP * 6, run)
        .await
        .expect("the forwarding test is bounded");
}

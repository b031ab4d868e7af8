//! The `vas` binary flies `mavsim` over a serial radio link emulated by `marea-radio` (two pty
//! pairs, a 64 kbit/s half-duplex air link) losing and corrupting 1 % of the bytes: the
//! 200-waypoint run through a 5-slot rolling queue still completes without a stop, every
//! waypoint reached once and in order: no transfer broken by the radio left a stale slot in the
//! vehicle's path.

mod common;

use std::time::{Duration, Instant};

use common::*;
use usal_types::FlightState;

/// Wall-clock bound on the whole flight (it takes about 115 s: 200 legs of 5.6 simulated
/// seconds at 10×; the wrap to slot 1 has one leg of slack, and a corrupted length byte can
/// hold a MAVLink parser up for a few hundred milliseconds).
const FLIGHT: Duration = Duration::from_secs(200);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_hundred_waypoints_over_a_lossy_radio() {
    let dir = tempfile::tempdir().unwrap();
    // 0.5 % of the bytes lost and 0.5 % corrupted, in each direction.
    let radio = Radio::start(&[
        "--loss",
        "0.005",
        "--corrupt",
        "0.005",
        "--seed",
        "5",
        "--stats-ms",
        "1000",
    ])
    .await;
    let sim = Sim::start_serial(&radio.air, 10.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("radio");
    let vas = VasProc::start(
        &format!("serial:{}:57600", radio.ground),
        &domain,
        &[
            "--queue-size",
            "5",
            "--request-timeout-ms",
            "60",
            "--retries",
            "30",
            // Steady downlink traffic also flushes a parser stuck on a corrupted length byte.
            "--telemetry-hz",
            "10",
            "--status-hz",
            "10",
            // 1 Hz heartbeats lose a fifth of their frames here.
            "--heartbeat-timeout-ms",
            "6000",
        ],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;

    // One begins a landing sequence: its DO_LAND_START comes and goes on board through the
    // radio too (whole uploads, which never renumber the waypoint the vehicle drives to).
    let mut wps = zigzag(200, 10.0);
    wps[170].land_start = true;
    g.push_all(&wps).await;
    let reply = g.request(FlightState::WaypointNavigation).await;
    assert!(reply.is_ok(), "{reply:?}");

    let started = Instant::now();
    let mut seen = Vec::new();
    let mut left_navigation = None;
    while seen.len() < wps.len() {
        let mut left = FLIGHT.saturating_sub(started.elapsed()).min(STEP);
        if let Some(c) = &left_navigation {
            // The autopilot holds after the last item; the report of that item may come
            // after the mode change, but not much later.
            left = left.min(Duration::from_secs(5));
            assert!(
                seen.len() + 1 >= wps.len(),
                "left navigation after {} waypoints: {c:?}",
                seen.len()
            );
        }
        tokio::select! {
            r = g.reached.recv() => seen.push(r.expect("waypoint_reached").value.seq),
            c = g.changes.recv() => {
                let c = c.expect("state_changed").value;
                if c.from == FlightState::WaypointNavigation {
                    left_navigation = Some(c);
                }
            }
            _ = tokio::time::sleep(left) => panic!(
                "stalled after {} waypoints (state change: {left_navigation:?})",
                seen.len()
            ),
        }
    }
    eprintln!("200 waypoints over the radio in {:?}", started.elapsed());
    assert_eq!(seen, (0..200).collect::<Vec<u64>>(), "VAS reports in order");
    g.wait_state(FlightState::Parking, STEP).await;

    // mavsim's own log: every waypoint reached once, in order.
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    if let Some(bad) = (0..order.len()).find(|&i| order[i] != Some(i)) {
        // What the autopilot was told around the first wrong reach, for the CI log.
        let t = sim.log_events("item_reached")[bad]["t_sim"]
            .as_f64()
            .unwrap_or(0.0);
        for line in std::fs::read_to_string(&sim.log)
            .unwrap_or_default()
            .lines()
        {
            let r: serde_json::Value = serde_json::from_str(line).unwrap_or_default();
            if (t - 40.0..=t + 1.0).contains(&r["t_sim"].as_f64().unwrap_or(-1e9)) {
                eprintln!("mavsim: {line}");
            }
        }
    }
    assert_eq!(
        order,
        (0..200).map(Some).collect::<Vec<_>>(),
        "mavsim reached every waypoint once, in order"
    );
    let markers: Vec<u64> = sim
        .log_events("do_command")
        .iter()
        .filter_map(|e| e["command"].as_u64())
        .collect();
    // Passed before its waypoint; over this radio a marker kept at a passed slot (it may not
    // go while the vehicle drives past it) can be passed once more before the upload that
    // removes it: a no-op in sequence, never a waypoint out of order (checked above).
    assert!(
        (1..=2).contains(&markers.len()) && markers.iter().all(|&c| c == 189),
        "the DO_LAND_START was passed: {markers:?}"
    );
    // The radio really did damage the stream.
    let stats = radio.stats().expect("marea-radio counters");
    let damaged = |dir: &str| {
        stats[dir]["lost"].as_u64().unwrap_or(0) + stats[dir]["corrupted"].as_u64().unwrap_or(0)
    };
    assert!(
        damaged("ground_to_air") > 0 && damaged("air_to_ground") > 0,
        "no byte errors injected: {stats}"
    );
    eprintln!("radio: {stats}");
    vas.kill().await;
    sim.kill().await;
    radio.kill().await;
    g.node.shutdown().await;
}

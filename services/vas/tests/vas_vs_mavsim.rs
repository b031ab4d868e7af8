//! The `vas` binary against the `mavsim` binary over real UDP MAVLink, driven from a ground
//! node over the middleware: the rolling queue, the command checker, a simulator restart.

mod common;

use common::*;
use usal_types::FlightState;

/// 200 waypoints through a 5-slot rolling queue: all reached in order, none skipped or
/// repeated (mavsim's own log), and no HOLD before the last one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_hundred_waypoints_through_five_slots() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 40.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("queue");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--queue-size", "5"],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;

    let wps = zigzag(200, 10.0);
    g.fly_in_order(&wps, "mavsim").await;

    let reached = sim.log_events("item_reached");
    let order: Vec<Option<usize>> = reached_points(&reached)
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(
        order,
        (0..200).map(Some).collect::<Vec<_>>(),
        "mavsim reached every waypoint once, in order"
    );
    // HOLD (rover mode 4) only after the last item: the vehicle never stopped on the way.
    let last_reach = reached.last().unwrap()["t_sim"].as_f64().unwrap();
    for m in sim.log_events("mode_changed") {
        if m["to"] == 4 && m["from"] == 10 {
            assert!(
                m["t_sim"].as_f64().unwrap() >= last_reach,
                "HOLD early: {m}"
            );
        }
    }
    assert_left_auto_once(&sim);
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// An autopilot that moves its current item on well after reporting a reach, to the item
/// after the one reached whatever was set meanwhile (MAVSDK's mission server, slow under load):
/// the VAS's set-current for the next window lands before it and is overridden, sending the
/// vehicle one slot too far. The VAS sees the advance past a target the vehicle is far from,
/// sets it back, and every waypoint is reached, in order, none skipped.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_advance_of_the_autopilot_never_skips_a_waypoint() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let sim = Sim::start_with(
        "127.0.0.1:0",
        10.0,
        &log,
        &["--late-advance-ms", "900", "--autopilot", "generic"],
    )
    .await;
    let domain = unique_domain("late-advance");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--queue-size", "4"],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let wps = zigzag(14, 25.0);
    g.push_all(&wps).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    let mut seen = Vec::new();
    while seen.len() < wps.len() {
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .unwrap_or_else(|_| panic!("stalled after {seen:?}:\n{}", sim.mission_story()))
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    assert_eq!(seen, (0..14).collect::<Vec<u64>>());
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(
        order,
        (0..14).map(Some).collect::<Vec<_>>(),
        "mavsim reached every waypoint once, in order:\n{}",
        sim.mission_story()
    );
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// The command checker refuses with its reason; an accepted change reaches the autopilot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn transitions_checked_and_applied() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 10.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("states");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;

    let e = g.request(FlightState::TakeOff).await.unwrap_err();
    assert!(e.contains("TAKE_OFF is not a state of a rover"), "{e}");
    let e = g
        .request(FlightState::WaypointNavigation)
        .await
        .unwrap_err();
    assert!(e.contains("no waypoints queued"), "{e}");
    let e = g.request(FlightState::Parking).await.unwrap_err();
    assert!(e.contains("already in PARKING"), "{e}");

    let reply = g.request(FlightState::Directed).await.expect("DIRECTED");
    assert_eq!(
        (reply.from, reply.to),
        (FlightState::Parking, FlightState::Directed)
    );
    let changed = tokio::time::timeout(STEP, async {
        loop {
            let c = g.changes.recv().await.expect("state_changed");
            if c.value.to == FlightState::Directed {
                return c.value;
            }
        }
    })
    .await
    .expect("state_changed event");
    assert_eq!(changed.cause, "request");
    // mavsim went HOLD (PARKING) then MANUAL (DIRECTED).
    let modes: Vec<u64> = sim
        .log_events("mode_changed")
        .iter()
        .filter_map(|m| m["to"].as_u64())
        .collect();
    assert!(modes.ends_with(&[4, 0]), "mavsim modes {modes:?}");

    // MANUAL is the failsafe: no way back to navigation.
    g.request(FlightState::Manual).await.expect("MANUAL");
    let e = g
        .request(FlightState::WaypointNavigation)
        .await
        .unwrap_err();
    assert!(e.contains("failsafe"), "{e}");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// The waypoint queue, published best effort and on change, is published again though
/// unchanged (every 2 s, with the flight state): a fleet that missed the change (a datagram
/// lost on a busy host) still learns its waypoints are queued instead of waiting for them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_waypoint_queue_is_published_again_though_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 10.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("queue-again");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let queue = g
        .svc
        .subscribe_variable::<usal_types::QueueStatus>("rover1/vas/queue")
        .unwrap();
    let wps = zigzag(3, 10.0);
    g.push_all(&wps).await;
    // The value set by the push, then the same value again with nothing changed.
    let mut seen = 0;
    let twice = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        while seen < 2 {
            let q = queue.recv().await.expect("queue");
            if q.value.queued == wps.len() as u64 {
                seen += 1;
            }
        }
    })
    .await;
    assert!(
        twice.is_ok(),
        "the queue with 3 waypoints seen {seen} time(s) in 10 s"
    );
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// mavsim dies mid-flight and comes back at the same address: the VAS raises an alarm,
/// reconnects and, as configured (`--resume-after-reboot`), re-uploads its window, resumes
/// with an alarm saying so and finishes the plan.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn autopilot_restart_mid_flight() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 20.0, &dir.path().join("sim1.jsonl")).await;
    let addr = sim.addr.clone();
    let domain = unique_domain("restart");
    let vas = VasProc::start(
        &format!("udpout:{addr}"),
        &domain,
        &["--heartbeat-timeout-ms", "1000", "--resume-after-reboot"],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let wps = zigzag(30, 10.0);
    g.push_all(&wps).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");

    let mut seen = Vec::new();
    while seen.len() < 8 {
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .expect("progress before the restart")
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    sim.kill().await;
    g.wait_alarm("heartbeat lost", STEP).await;
    let sim2 = Sim::start(&addr, 20.0, &dir.path().join("sim2.jsonl")).await;
    let a = g.wait_alarm("resumed WAYPOINT_NAVIGATION", STEP).await;
    assert!(a.text.contains("resumeAfterReboot"), "{a:?}");

    while seen.last() != Some(&29) {
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .unwrap_or_else(|_| panic!("stalled after {seen:?}"))
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    // Every waypoint reported once, in order, across the restart.
    let mut sorted = seen.clone();
    sorted.dedup();
    assert_eq!(seen, sorted, "no repeats");
    assert_eq!(seen, (0..30).collect::<Vec<u64>>());
    // The new autopilot flew the rest in order, starting where the old one stopped.
    let order: Vec<usize> = reached_points(&sim2.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p).expect("a plan waypoint"))
        .collect();
    let first = *order.first().expect("the new mavsim reached waypoints");
    assert!((7..=9).contains(&first), "resumed at {first}");
    assert_eq!(order, (first..30).collect::<Vec<_>>());
    vas.kill().await;
    sim2.kill().await;
    g.node.shutdown().await;
}

/// An autopilot that reports no progress at all (no MISSION_ITEM_REACHED, no "Reached" text,
/// MISSION_CURRENT only in answer to a set-current): the VAS follows the vehicle's position
/// instead, and the rolling queue still delivers every waypoint once, in order, without a stop.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn progress_from_position_when_the_autopilot_reports_none() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let sim = Sim::start_with("127.0.0.1:0", 10.0, &log, &["--quiet-progress"]).await;
    let domain = unique_domain("quiet");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--queue-size", "5", "--telemetry-hz", "10"],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let wps = zigzag(30, 10.0);
    g.push_all(&wps).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    let mut seen = Vec::new();
    while seen.len() < wps.len() {
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .unwrap_or_else(|_| panic!("stalled after {seen:?}"))
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    assert_eq!(seen, (0..30).collect::<Vec<u64>>());
    g.wait_state(FlightState::Parking, STEP).await;
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(order, (0..30).map(Some).collect::<Vec<_>>());
    assert_left_auto_once(&sim);
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A copter: TAKE_OFF climbs straight up (GUIDED + MAV_CMD_NAV_TAKEOFF), then the waypoints
/// are flown with the speeds they ask for (DO_CHANGE_SPEED when each becomes the target, back
/// to WPNAV_SPEED for one that asks for none).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn copter_takes_off_and_flies_the_waypoint_speeds() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let sim = Sim::start_with("127.0.0.1:0", 10.0, &log, &["--vehicle", "copter"]).await;
    let domain = unique_domain("copter");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--vehicle", "copter", "--telemetry-hz", "10"],
    );
    let g = Ground::open(&domain).await;
    let position = g
        .svc
        .subscribe_variable::<usal_types::Position>("rover1/vas/position")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    let mut wps = zigzag(5, 30.0);
    for (w, speed) in wps.iter_mut().zip([0.0, 0.0, 8.0, 8.0, 0.0]) {
        w.alt = 12.0;
        w.speed = speed;
    }
    wps[1].fly_over = true;
    g.push_all(&wps).await;
    g.request(FlightState::TakeOff).await.expect("TAKE_OFF");
    // Home is at 10 m AMSL: wait for 12 m above it, where it was sent.
    let climbed = tokio::time::timeout(STEP, async {
        loop {
            let p = position.recv().await.expect("position").value;
            if p.alt >= 10.0 + 11.5 {
                return p;
            }
        }
    })
    .await
    .expect("the copter climbed");
    let north = (climbed.lat - HOME.0) * 111_319.49;
    assert!(north.abs() < 1.0, "climbed where it stood: {climbed:?}");
    assert_eq!(sim.log_events("takeoff_complete").len(), 1);

    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    let mut seen = Vec::new();
    while seen.len() < wps.len() {
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .unwrap_or_else(|_| panic!("stalled after {seen:?}"))
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    assert_eq!(seen, (0..5).collect::<Vec<u64>>());
    let speeds: Vec<f64> = sim
        .log_events("speed_changed")
        .iter()
        .filter_map(|r| r["speed"].as_f64())
        .collect();
    // 8 m/s towards waypoints 2 and 3, then WPNAV_SPEED (5 m/s) again towards 4.
    assert_eq!(speeds, [8.0, 5.0]);
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(order, (0..5).map(Some).collect::<Vec<_>>());
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A copter flown one waypoint at a time, the next pushed only once the last was reached (a
/// fleet sending an investigator from point to point): every mission ends at its one item,
/// which stays current on the autopilot, and each next one reuses that slot. Every reach is
/// reported, the third as the first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_copter_sent_one_waypoint_at_a_time_reaches_each() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let sim = Sim::start_with("127.0.0.1:0", 10.0, &log, &["--vehicle", "copter"]).await;
    let domain = unique_domain("copter-one");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--vehicle", "copter", "--telemetry-hz", "10"],
    );
    let g = Ground::open(&domain).await;
    let position = g
        .svc
        .subscribe_variable::<usal_types::Position>("rover1/vas/position")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    let mut wps = zigzag(4, 25.0);
    for w in &mut wps {
        w.alt = 10.0;
    }
    g.push_all(&wps[..1]).await;
    g.request(FlightState::TakeOff).await.expect("TAKE_OFF");
    tokio::time::timeout(STEP, async {
        while position.recv().await.expect("position").value.alt_rel < 9.5 {}
    })
    .await
    .expect("the copter climbed");
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    for (k, w) in wps.iter().enumerate() {
        if k > 0 {
            g.push_all(std::slice::from_ref(w)).await;
        }
        let r = tokio::time::timeout(STEP, g.reached.recv())
            .await
            .unwrap_or_else(|_| {
                panic!(
                    "waypoint {k} never reported reached:\n{}",
                    sim.mission_story()
                )
            })
            .expect("waypoint_reached");
        assert_eq!(r.value.seq, w.seq);
    }
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(order, (0..4).map(Some).collect::<Vec<_>>());
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// mavsim's log shows the rover left AUTO (mode 10) exactly once: at the end of the mission,
/// never mid-way for lack of a next waypoint.
fn assert_left_auto_once(sim: &Sim) {
    let auto_exits = sim
        .log_events("mode_changed")
        .into_iter()
        .filter(|m| m["from"] == 10)
        .count();
    assert_eq!(auto_exits, 1, "left AUTO only once, at the end");
}

/// Waypoints that begin a landing sequence go on board behind a DO_LAND_START, through a
/// 5-slot rolling queue that wraps around them (ArduPilot's partial writes, PX4's whole
/// uploads): the autopilot passes each marker once, just before its waypoint, every waypoint
/// is reached once and in order, and the VAS never sees the vehicle head back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn landing_markers_ride_the_rolling_queue_on_ardupilot() {
    landing_markers_fly_in_order("ardupilot").await;
}

/// [`landing_markers_ride_the_rolling_queue_on_ardupilot`] on an autopilot that resets its
/// current item on every whole upload.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn landing_markers_ride_the_rolling_queue_on_px4() {
    landing_markers_fly_in_order("px4").await;
}

async fn landing_markers_fly_in_order(profile: &str) {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        30.0,
        &dir.path().join("sim.jsonl"),
        &["--autopilot", profile],
    )
    .await;
    let domain = unique_domain(&format!("markers-{profile}"));
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--queue-size", "5"],
    );
    let g = Ground::open(&domain).await;
    let queue = g
        .svc
        .subscribe_variable::<usal_types::QueueStatus>("rover1/vas/queue")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    // Marked waypoints at every offset from a wrap of the 5-slot window.
    let marked = [3, 9, 14, 16, 20, 25];
    let mut wps = zigzag(28, 10.0);
    for &i in &marked {
        wps[i].land_start = true;
    }
    g.fly_in_order(&wps, profile).await;

    // mavsim's story: each marker passed once, the next thing it reached the marked waypoint.
    let story: Vec<serde_json::Value> = sim
        .log_records()
        .into_iter()
        .filter(|e| {
            e["event"] == "item_reached" || (e["event"] == "do_command" && e["command"] == 189)
        })
        .collect();
    let mut passed = Vec::new();
    for (k, e) in story.iter().enumerate() {
        if e["event"] == "do_command" {
            let next = story[k + 1..]
                .iter()
                .find(|e| e["event"] == "item_reached")
                .expect("a waypoint follows the marker");
            passed.push(which(&wps, reached_points(std::slice::from_ref(next))[0]));
        }
    }
    assert_eq!(
        passed,
        marked.iter().map(|&i| Some(i)).collect::<Vec<_>>(),
        "{profile}: markers passed, each before its waypoint; mavsim's log:\n{}",
        sim.mission_story()
    );
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    assert_eq!(
        order,
        (0..wps.len()).map(Some).collect::<Vec<_>>(),
        "{profile}: every waypoint reached once, in order; mavsim's log:\n{}",
        sim.mission_story()
    );
    let last = latest_queue_status(&queue);
    assert_eq!(last.backtracks, 0, "{profile}: {last:?}");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

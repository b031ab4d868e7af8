//! Pilot in command, the `vas` binary against the `mavsim` binary over real UDP MAVLink: a
//! rebooted autopilot is not resumed without the operator (unless configured, see
//! `vas_vs_mavsim::autopilot_restart_mid_flight`); explicit ARM and DISARM, return to launch,
//! take-off, DIRECTED flight on a bearing and landing, each checked by the VAL's command
//! checker and executed by mavsim; `allowed_changes` tells stations what may be asked.

mod common;

use std::time::Duration;

use common::*;
use marea::{Function, VariableSubscriber};
use usal_types::{
    AllowedChanges, AutopilotStatus, CommandReply, DirectedTarget, FlightState, Position,
    VehicleCommand,
};

const M_PER_DEG: f64 = 111_319.49;

fn command_fn(g: &Ground) -> Function<VehicleCommand, CommandReply> {
    g.svc.function("rover1/vas/command").unwrap()
}

async fn command(
    f: &Function<VehicleCommand, CommandReply>,
    c: VehicleCommand,
) -> Result<CommandReply, String> {
    f.call(&c, STEP).await.map_err(|e| e.to_string())
}

/// Waits until `allowed_changes` satisfies `want`.
async fn wait_allowed(
    v: &VariableSubscriber<AllowedChanges>,
    what: &str,
    want: impl Fn(&AllowedChanges) -> bool,
) -> AllowedChanges {
    tokio::time::timeout(STEP, async {
        loop {
            let a = v.recv().await.expect("allowed_changes").value;
            if want(&a) {
                return a;
            }
        }
    })
    .await
    .unwrap_or_else(|_| panic!("allowed_changes never showed {what}"))
}

/// Waits until a position satisfies `want`.
async fn wait_position(
    v: &VariableSubscriber<Position>,
    what: &str,
    within: Duration,
    want: impl Fn(&Position) -> bool,
) -> Position {
    tokio::time::timeout(within, async {
        loop {
            let p = v.recv().await.expect("position").value;
            if want(&p) {
                return p;
            }
        }
    })
    .await
    .unwrap_or_else(|_| panic!("the vehicle never {what}"))
}

fn metres_from_home(p: &Position) -> (f64, f64) {
    (
        (p.lat - HOME.0) * M_PER_DEG,
        (p.lon - HOME.1) * M_PER_DEG * HOME.0.to_radians().cos(),
    )
}

/// mavsim dies mid-plan and a new one (booting disarmed in MANUAL) answers at the same
/// address. With `resumeAfterReboot` off (the default) the VAS neither re-arms it nor puts it
/// back in AUTO: it follows the state the autopilot reports and an alarm tells the operator to
/// restart; the operator's WAYPOINT_NAVIGATION then finishes the plan.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rebooted_autopilot_waits_for_the_operator() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 20.0, &dir.path().join("sim1.jsonl")).await;
    let addr = sim.addr.clone();
    let domain = unique_domain("reboot");
    let vas = VasProc::start(
        &format!("udpout:{addr}"),
        &domain,
        &["--heartbeat-timeout-ms", "1000"],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let wps = zigzag(20, 10.0);
    g.push_all(&wps).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    let mut seen = Vec::new();
    while seen.len() < 5 {
        let r = g
            .reached
            .recv_timeout(STEP)
            .await
            .expect("waypoint_reached");
        seen.push(r.value.seq);
    }
    sim.kill().await;
    g.wait_alarm("heartbeat lost", STEP).await;
    let log2 = dir.path().join("sim2.jsonl");
    let sim2 = Sim::start(&addr, 20.0, &log2).await;
    let a = g
        .wait_alarm("the operator must restart WAYPOINT_NAVIGATION", STEP)
        .await;
    assert!(a.text.contains("resumeAfterReboot is off"), "{a:?}");
    // The VAL follows the autopilot: MANUAL after boot is a rover's DIRECTED.
    g.wait_state(FlightState::Directed, STEP).await;
    assert!(
        sim2.log_events("armed").is_empty(),
        "the VAS re-armed the rebooted autopilot: {:?}",
        sim2.log_events("armed")
    );
    assert!(
        !sim2
            .log_events("mode_changed")
            .iter()
            .any(|m| m["to"] == 10),
        "the VAS put the rebooted autopilot in AUTO"
    );
    // The operator restarts the plan where it was.
    let reply = g
        .request(FlightState::WaypointNavigation)
        .await
        .expect("the operator's WAYPOINT_NAVIGATION");
    assert_eq!(reply.from, FlightState::Directed);
    while seen.last() != Some(&19) {
        let r = g
            .reached
            .recv_timeout(STEP)
            .await
            .unwrap_or_else(|e| panic!("stalled after {seen:?}: {e}"));
        seen.push(r.value.seq);
    }
    let mut sorted = seen.clone();
    sorted.dedup();
    assert_eq!(seen, sorted, "no repeats");
    vas.kill().await;
    sim2.kill().await;
    g.node.shutdown().await;
}

/// ARM and DISARM only parked (and only when they change something), refused while
/// navigating with the reason; RETURN_TO_LAUNCH drives a rover home; `allowed_changes`
/// follows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rover_arms_disarms_and_returns_to_launch() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 10.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("arm");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    let cmd = command_fn(&g);
    let allowed = g
        .svc
        .subscribe_variable::<AllowedChanges>("rover1/vas/allowed_changes")
        .unwrap();
    let position = g
        .svc
        .subscribe_variable::<Position>("rover1/vas/position")
        .unwrap();
    assert!(cmd.wait_provider(STEP).await, "command not discovered");
    g.wait_state(FlightState::Parking, STEP).await;
    let a = wait_allowed(&allowed, "PARKING, disarmed", |a| {
        a.from == Some(FlightState::Parking) && !a.armed
    })
    .await;
    assert_eq!(a.commands, ["ARM"]);
    assert!(a.states.contains(&FlightState::ReturnToLaunch), "{a:?}");

    let r = command(&cmd, VehicleCommand::Arm).await.expect("ARM");
    assert_eq!((r.command.as_str(), r.state), ("ARM", FlightState::Parking));
    assert_eq!(sim.log_events("armed").last().unwrap()["armed"], true);
    wait_allowed(&allowed, "DISARM once armed", |a| a.commands == ["DISARM"]).await;
    let e = command(&cmd, VehicleCommand::Arm).await.unwrap_err();
    assert!(e.contains("already armed"), "{e}");
    command(&cmd, VehicleCommand::Disarm).await.expect("DISARM");
    assert_eq!(sim.log_events("armed").last().unwrap()["armed"], false);
    let directed = VehicleCommand::Directed(DirectedTarget {
        alt: 10.0,
        speed: 2.0,
        bearing: 90.0,
    });
    let e = command(&cmd, directed).await.unwrap_err();
    assert!(e.contains("rover"), "{e}");

    // Navigating: no disarming, with the reason.
    g.push_all(&zigzag(8, 15.0)).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigate");
    for _ in 0..2 {
        g.reached
            .recv_timeout(STEP)
            .await
            .expect("waypoint_reached");
    }
    let e = command(&cmd, VehicleCommand::Disarm).await.unwrap_err();
    assert!(
        e.contains("DISARM refused in WAYPOINT_NAVIGATION") && e.contains("PARKING"),
        "{e}"
    );
    let away = wait_position(&position, "left home", STEP, |p| {
        let (n, e) = metres_from_home(p);
        n.hypot(e) > 15.0
    })
    .await;
    assert!(metres_from_home(&away).0 > 10.0);

    // Return to launch: mavsim's RTL, and the rover drives back home.
    let r = g
        .request(FlightState::ReturnToLaunch)
        .await
        .expect("RETURN_TO_LAUNCH");
    assert_eq!(r.from, FlightState::WaypointNavigation);
    assert!(
        sim.log_events("mode_changed").iter().any(|m| m["to"] == 11),
        "mavsim not in RTL"
    );
    wait_position(&position, "came home", Duration::from_secs(60), |p| {
        let (n, e) = metres_from_home(p);
        n.hypot(e) < 3.0
    })
    .await;
    let a = wait_allowed(&allowed, "RETURN_TO_LAUNCH", |a| {
        a.from == Some(FlightState::ReturnToLaunch)
    })
    .await;
    assert!(a.states.contains(&FlightState::Parking), "{a:?}");
    g.request(FlightState::Parking).await.expect("PARKING");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A copter takes off, flies DIRECTED on a bearing at the altitude and speed asked, then
/// lands and is disarmed on the ground. A DIRECTED target that cannot be flown is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn copter_takes_off_flies_a_bearing_and_lands() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        10.0,
        &dir.path().join("sim.jsonl"),
        &["--vehicle", "copter"],
    )
    .await;
    let domain = unique_domain("directed");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--vehicle", "copter"],
    );
    let g = Ground::open(&domain).await;
    let cmd = command_fn(&g);
    let position = g
        .svc
        .subscribe_variable::<Position>("rover1/vas/position")
        .unwrap();
    let autopilot = g
        .svc
        .subscribe_variable::<AutopilotStatus>("rover1/vas/autopilot")
        .unwrap();
    assert!(cmd.wait_provider(STEP).await, "command not discovered");
    g.wait_state(FlightState::Parking, STEP).await;
    let target = DirectedTarget {
        alt: 25.0,
        speed: 5.0,
        bearing: 90.0,
    };
    // On the ground: DIRECTED needs a take-off first.
    let e = command(&cmd, VehicleCommand::Directed(target))
        .await
        .unwrap_err();
    assert!(e.contains("PARKING") && e.contains("TAKE_OFF"), "{e}");

    g.request(FlightState::TakeOff).await.expect("TAKE_OFF");
    wait_position(&position, "climbed to 10 m", STEP, |p| p.alt_rel > 9.5).await;
    let e = command(
        &cmd,
        VehicleCommand::Directed(DirectedTarget {
            speed: 0.0,
            ..target
        }),
    )
    .await
    .unwrap_err();
    assert!(e.contains("speed"), "{e}");
    let r = command(&cmd, VehicleCommand::Directed(target))
        .await
        .expect("DIRECTED");
    assert_eq!(r.state, FlightState::Directed);
    g.wait_state(FlightState::Directed, STEP).await;
    assert_eq!(sim.log_events("repositioned").len(), 1);
    // East, at 25 m, going on.
    let p = wait_position(
        &position,
        "flew 60 m east at 25 m",
        Duration::from_secs(60),
        |p| metres_from_home(p).1 > 60.0 && (p.alt_rel - 25.0).abs() < 1.5,
    )
    .await;
    assert!(metres_from_home(&p).0.abs() < 5.0, "off the bearing: {p:?}");

    g.request(FlightState::Landing).await.expect("LANDING");
    // Descending it is LANDING, not yet parked: a pilot sees PARKING only once it is down.
    wait_position(&position, "descending", Duration::from_secs(60), |p| {
        p.alt_rel < 15.0
    })
    .await;
    let mut seen = Vec::new();
    while let Some(Ok(s)) = g.state.try_recv() {
        seen.push(s.value);
    }
    assert!(
        seen.iter().all(|s| *s != FlightState::Parking),
        "parked in the air: {seen:?}"
    );
    wait_position(&position, "landed", Duration::from_secs(60), |p| {
        p.alt_rel < 0.3
    })
    .await;
    tokio::time::timeout(STEP, async {
        while autopilot.recv().await.expect("autopilot").value.armed {}
    })
    .await
    .expect("disarmed on the ground");
    g.wait_state(FlightState::Parking, STEP).await;
    assert_eq!(sim.log_events("landed").len(), 1);
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A plane takes off in ArduPlane's TAKEOFF mode, flies DIRECTED on a bearing, returns to
/// launch and circles over home, then lands: an approach and NAV_LAND in AUTO, parked once
/// down and disarmed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plane_takes_off_flies_a_bearing_returns_and_lands() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        20.0,
        &dir.path().join("sim.jsonl"),
        &["--vehicle", "plane"],
    )
    .await;
    let domain = unique_domain("plane");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--vehicle", "plane"],
    );
    let g = Ground::open(&domain).await;
    let cmd = command_fn(&g);
    let position = g
        .svc
        .subscribe_variable::<Position>("rover1/vas/position")
        .unwrap();
    assert!(cmd.wait_provider(STEP).await, "command not discovered");
    g.wait_state(FlightState::Parking, STEP).await;
    g.request(FlightState::TakeOff).await.expect("TAKE_OFF");
    assert!(
        sim.log_events("mode_changed")
            .iter()
            .any(|m| m["name"] == "TAKEOFF"),
        "mavsim not in TAKEOFF"
    );
    wait_position(&position, "climbed to 45 m", Duration::from_secs(60), |p| {
        p.alt_rel > 45.0
    })
    .await;
    let target = DirectedTarget {
        alt: 60.0,
        speed: 20.0,
        bearing: 180.0,
    };
    let r = command(&cmd, VehicleCommand::Directed(target))
        .await
        .expect("DIRECTED");
    assert_eq!(r.state, FlightState::Directed);
    // South of home, 60 m up.
    let p = wait_position(
        &position,
        "flew south at 60 m",
        Duration::from_secs(60),
        |p| metres_from_home(p).0 < -600.0 && (p.alt_rel - 60.0).abs() < 3.0,
    )
    .await;
    assert!(p.heading > 90.0 && p.heading < 270.0, "{p:?}");
    let r = g
        .request(FlightState::ReturnToLaunch)
        .await
        .expect("RETURN_TO_LAUNCH");
    assert_eq!(r.from, FlightState::Directed);
    wait_position(
        &position,
        "came back over home",
        Duration::from_secs(90),
        |p| {
            let (n, e) = metres_from_home(p);
            n.hypot(e) < 150.0
        },
    )
    .await;
    // LANDING is a landing, not RTL: DO_LAND_START, an approach from the side the plane is
    // on, NAV_LAND on home in AUTO, down on the strip and disarmed, then parked.
    let r = g.request(FlightState::Landing).await.expect("LANDING");
    assert_eq!(r.from, FlightState::ReturnToLaunch);
    let uploaded = sim.log_events("mission_uploaded");
    let last = uploaded.last().expect("a landing mission uploaded");
    assert_eq!(last["count"], 4, "{last}");
    assert!(
        sim.log_events("mode_changed")
            .iter()
            .any(|m| m["name"] == "AUTO"),
        "mavsim not in AUTO for the landing"
    );
    g.wait_state(FlightState::Parking, Duration::from_secs(120))
        .await;
    let p = wait_position(&position, "stopped on the ground", STEP, |p| {
        p.alt_rel.abs() < 1.0 && p.speed < 0.5
    })
    .await;
    let (n, e) = metres_from_home(&p);
    assert!(
        p.alt_rel.abs() < 1.0 && n.hypot(e) < 250.0,
        "landed {:.0} m from home at {:.1} m: {p:?}",
        n.hypot(e),
        p.alt_rel
    );
    let marker = sim.log_events("do_command");
    assert!(
        marker.iter().any(|m| m["command"] == 189 && m["seq"] == 1),
        "the landing began at its DO_LAND_START: {marker:?}"
    );
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// An autopilot whose own checks are still running answers "not now"
/// (MAV_RESULT_TEMPORARILY_REJECTED) to every mode change and arming: the VAS asks again with a
/// growing delay instead of giving up, says why in an alarm while it waits, and parks the
/// vehicle once the autopilot accepts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_autopilot_that_says_not_now_is_asked_again_until_it_parks() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        1.0,
        &dir.path().join("sim.jsonl"),
        &["--not-ready-s", "6"],
    )
    .await;
    let domain = unique_domain("notnow");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    // While the autopilot says "not now": an alarm saying so, and still configuring.
    let alarm = tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            let a = g.alarms.recv().await.expect("alarms").value;
            if a.text.contains("cannot park") {
                return a;
            }
        }
    })
    .await
    .expect("no alarm while the autopilot refused");
    assert!(
        alarm.text.contains("TEMPORARILY_REJECTED") && alarm.text.contains("asks again"),
        "{}",
        alarm.text
    );
    // Then parked, once the autopilot accepts.
    g.wait_state(FlightState::Parking, Duration::from_secs(30))
        .await;
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// Parameters: a file (Mission Planner's format) set on the autopilot at start-up, each value
/// verified and a refusal raised as an alarm, before the vehicle is parked; then read, set and
/// listed through the VAS's functions.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameters_are_set_at_start_up_then_read_set_and_listed() {
    use usal_types::ParamValue;
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("rover.params");
    std::fs::write(&file, "# start-up\nCRUISE_SPEED,3.5\nNO_SUCH_PARAM,1\n").unwrap();
    let sim = Sim::start("127.0.0.1:0", 5.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("params");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--params", file.to_str().unwrap()],
    );
    let g = Ground::open(&domain).await;
    let mut refusals = Vec::new();
    let summary = tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let a = g.alarms.recv().await.expect("alarms").value;
            if a.text.starts_with("start-up parameters:") {
                return a.text;
            }
            if a.text.contains("refused") {
                refusals.push(a.text);
            }
        }
    })
    .await
    .expect("no summary of the start-up parameters");
    assert_eq!(summary, "start-up parameters: 1 of 2 set and verified");
    assert!(
        refusals.len() == 1 && refusals[0].contains("NO_SUCH_PARAM = 1 (line 3) refused"),
        "{refusals:?}"
    );
    g.wait_state(FlightState::Parking, STEP).await;
    let get = g
        .svc
        .function::<String, ParamValue>("rover1/vas/get_param")
        .unwrap();
    let set = g
        .svc
        .function::<ParamValue, ParamValue>("rover1/vas/set_param")
        .unwrap();
    let list = g
        .svc
        .function::<(), Vec<ParamValue>>("rover1/vas/list_params")
        .unwrap();
    assert!(get.wait_provider(STEP).await, "get_param not discovered");
    let v = get.call(&"CRUISE_SPEED".to_owned(), STEP).await.unwrap();
    assert_eq!(v.value, 3.5);
    let v = set
        .call(
            &ParamValue {
                name: "CRUISE_SPEED".into(),
                value: 2.5,
            },
            STEP,
        )
        .await
        .unwrap();
    assert_eq!(v.value, 2.5);
    let all = list.call(&(), Duration::from_secs(20)).await.unwrap();
    assert!(
        all.iter()
            .any(|p| p.name == "CRUISE_SPEED" && p.value == 2.5),
        "{all:?}"
    );
    let e = get
        .call(&"NO_SUCH_PARAM".to_owned(), Duration::from_secs(20))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("no such parameter"), "{e}");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A partial mission read (`read_mission`): the items asked for, as the autopilot holds them
/// once navigation started (item 0 is ArduPilot's home); a range past the mission's end is refused
/// naming its length.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn part_of_the_mission_on_board_is_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 5.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("readmission");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let wps = zigzag(3, 20.0);
    g.push.call(&wps, STEP).await.expect("push");
    // The queue lays the waypoints out on the autopilot from slot 1 when navigation starts.
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("WAYPOINT_NAVIGATION");
    let read = g
        .svc
        .function::<(u16, u16), Vec<usal_types::Waypoint>>("rover1/vas/read_mission")
        .unwrap();
    assert!(
        read.wait_provider(STEP).await,
        "read_mission not discovered"
    );
    // Once mavsim committed the upload (home and the waypoints), read two of them back.
    sim.wait_log(
        "mission_uploaded",
        STEP,
        "the waypoints never reached the autopilot",
        |r| {
            r.iter()
                .any(|r| r["count"].as_u64().is_some_and(|c| c >= 3))
        },
    )
    .await;
    let items = read.call(&(1, 2), STEP).await.expect("read_mission");
    assert_eq!(items.len(), 2, "{items:?}");
    for (got, want) in items.iter().zip(&wps) {
        assert!(
            (got.lat - want.lat).abs() < 1e-6 && (got.lon - want.lon).abs() < 1e-6,
            "read {got:?}, pushed {want:?}"
        );
    }
    assert_eq!((items[0].seq, items[1].seq), (1, 2));
    let e = read.call(&(2, 40), STEP).await.unwrap_err().to_string();
    assert!(e.contains("2..=40") && e.contains("the mission has"), "{e}");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

/// A plane taxis: from PARKING to TAXI (armed, MANUAL), steered by the station's sticks at
/// full throttle it rolls on the ground at taxiing speed (the VAS caps the throttle), never
/// leaving it; back to PARKING it stops and disarms.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plane_taxis_on_the_ground_under_the_sticks_and_parks_disarmed() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        5.0,
        &dir.path().join("sim.jsonl"),
        &["--vehicle", "plane"],
    )
    .await;
    let domain = unique_domain("taxi");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--vehicle", "plane", "--telemetry-hz", "10"],
    );
    let g = Ground::open(&domain).await;
    let position = g
        .svc
        .subscribe_variable::<Position>("rover1/vas/position")
        .unwrap();
    let autopilot = g
        .svc
        .subscribe_variable::<usal_types::AutopilotStatus>("rover1/vas/autopilot")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    let r = g.request(FlightState::Taxi).await.expect("TAXI");
    assert_eq!((r.from, r.to), (FlightState::Parking, FlightState::Taxi));
    let sticks_node = {
        let mut cfg = marea::NetworkConfig::ethernet_loopback("station");
        cfg.domain = domain.clone();
        marea::Node::open(&cfg).await.expect("node")
    };
    let sticks = sticks_node
        .service("fmo")
        .unwrap()
        .publish_variable::<usal_types::ManualCommand>("manual_control")
        .unwrap();
    let drive = async {
        let mut tick = tokio::time::interval(Duration::from_millis(50));
        loop {
            tick.tick().await;
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_millis() as u64;
            let _ = sticks.set(&usal_types::ManualCommand {
                target: "rover1/vas".into(),
                sticks: usal_types::ManualControl {
                    throttle: 1.0,
                    pitch: 1.0,
                    roll: 0.3,
                    timestamp_ms: now,
                    ..Default::default()
                },
            });
        }
    };
    let rolled = tokio::select! {
        () = drive => unreachable!("the sticks never stop"),
        p = wait_position(&position, "rolled 40 m", Duration::from_secs(60), |p| {
            let (n, e) = metres_from_home(p);
            n.hypot(e) > 40.0
        }) => p,
    };
    // Full throttle and full pitch: a taxi, on the ground, under the take-off speed.
    assert!(rolled.alt_rel.abs() < 0.5, "{rolled:?}");
    assert!(rolled.speed > 1.0 && rolled.speed < 9.0, "{rolled:?}");
    let r = g.request(FlightState::Parking).await.expect("PARKING");
    assert_eq!(r.from, FlightState::Taxi);
    tokio::time::timeout(STEP, async {
        loop {
            let a = autopilot.recv().await.expect("autopilot").value;
            if !a.armed {
                return;
            }
        }
    })
    .await
    .expect("disarmed once parked");
    // Standing: the motor stopped.
    wait_position(&position, "stopped", Duration::from_secs(30), |p| {
        p.speed < 0.1
    })
    .await;
    vas.kill().await;
    sim.kill().await;
    sticks_node.shutdown().await;
    g.node.shutdown().await;
}

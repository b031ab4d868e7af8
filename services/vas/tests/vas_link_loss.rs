//! Lost ground link: the `vas` binary flies `mavsim` (UDP) while its ground station sits on the
//! far side of a `marea-radio` (real ptys). The station publishes its heartbeat over the radio;
//! the radio goes silent mid-mission (cut by a signal once the rover navigates); the VAS must
//! apply `linkLossAction` (hold) and, when the link returns, what `linkRecovery` says: resume
//! the navigation, or wait for the operator.
//!
//! The VAS's node has the radio and a LAN; an observer on the LAN follows its `failsafe`
//! events and flight state while the radio is down.

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::*;
use marea::{NetworkConfig, Node};
use usal_types::{
    Failsafe, FailsafeKind, FlightState, StateChangeReply, StateChangeRequest, StationHeartbeat,
};

/// How long the radio stays silent once cut.
const OUTAGE_FOR: Duration = Duration::from_secs(12);
/// Generous bound for what crosses the radio.
const RADIO: Duration = Duration::from_secs(60);

fn lan(port: u16) -> String {
    format!(
        r#"<ethernet name="lan" bind="127.0.0.1:0" multicast="239.255.77.1:{port}" interface="127.0.0.1" heartbeatMs="200" leaseMs="1500"/>"#
    )
}

/// Writes the VAS's network.xml (its LAN and the radio) and its config file.
fn vas_files(dir: &Path, domain: &str, port: u16, tty: &str, recovery: &str) -> (String, String) {
    let net = dir.join("vas-net.xml");
    std::fs::write(
        &net,
        format!(
            "<network node=\"air-vas\" namespace=\"rover1\" domain=\"{domain}\">\n  {}\n  <serial name=\"radio\" address=\"{tty}\" baudRate=\"57600\"/>\n</network>\n",
            lan(port)
        ),
    )
    .expect("write network.xml");
    let cfg = dir.join("vas.xml");
    std::fs::write(
        &cfg,
        format!(
            r#"<vas linkLossTimeoutMs="3000" linkLossAction="hold" linkRecovery="{recovery}" radioLink="radio"/>"#
        ),
    )
    .expect("write vas.xml");
    (net.display().to_string(), cfg.display().to_string())
}

async fn next_failsafe(
    sub: &marea::EventSubscriber<Failsafe>,
    kind: FailsafeKind,
    within: Duration,
) -> Failsafe {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        match sub.recv_timeout(left).await {
            Ok(f) if f.value.kind == kind => return f.value,
            Ok(_) => {}
            Err(e) => panic!("no {kind:?} failsafe: {e}"),
        }
    }
}

async fn wait_state(
    sub: &marea::VariableSubscriber<FlightState>,
    want: FlightState,
    within: Duration,
) {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        match sub.recv_timeout(left).await {
            Ok(s) if s.value == want => return,
            Ok(_) => {}
            Err(e) => panic!("flight state never became {want}: {e}"),
        }
    }
}

/// Mid-mission outage with `linkLossAction="hold"` and `linkRecovery` as given. Returns the
/// test's nodes' verdicts to the caller's assertions on recovery.
async fn outage_mid_mission(recovery: &str) {
    let dir = tempfile::tempdir().unwrap();
    let outage = OUTAGE_FOR.as_millis().to_string();
    let mut radio = Radio::start(&["--outage-on-signal", &outage, "--seed", "3"]).await;
    let sim = Sim::start("127.0.0.1:0", 2.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("linkloss");
    let port = test_support::free_udp_port();
    let (net, cfg) = vas_files(dir.path(), &domain, port, &radio.air, recovery);
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--network", &net, "-c", &cfg],
    );

    // The observer on the vehicle's LAN.
    let obs_cfg = NetworkConfig::parse(
        &format!(
            "<network node=\"observer\" domain=\"{domain}\">\n  {}\n</network>\n",
            lan(port)
        ),
        None,
    )
    .expect("observer network");
    let obs = Node::open(&obs_cfg).await.expect("observer node");
    let osvc = obs.service("observer").unwrap();
    let failsafes = osvc
        .subscribe_event::<Failsafe>("rover1/vas/failsafe")
        .unwrap();
    let state = osvc
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();

    // The ground station, behind the radio only.
    let ground_cfg = NetworkConfig::parse(
        &format!(
            "<network node=\"ground\" namespace=\"gcs\" domain=\"{domain}\">\n  <serial name=\"radio\" address=\"{}\" baudRate=\"57600\"/>\n</network>\n",
            radio.ground
        ),
        None,
    )
    .expect("ground network");
    let ground = Node::open(&ground_cfg).await.expect("ground node");
    let gsvc = ground.service("station").unwrap();
    let beat = gsvc
        .publish_variable::<StationHeartbeat>("heartbeat")
        .unwrap();
    let beating = tokio::spawn(async move {
        for seq in 0.. {
            let _ = beat.set(&StationHeartbeat {
                station: "gcs/station".into(),
                seq,
            });
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    });
    let change = gsvc
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    let push = gsvc
        .function::<Vec<usal_types::Waypoint>, usal_types::QueueStatus>("rover1/vas/push_waypoints")
        .unwrap();
    // Both: the VAS's declarations cross the radio in several batches.
    assert!(
        change.wait_provider(RADIO).await && push.wait_provider(RADIO).await,
        "the VAS was not discovered over the radio"
    );
    wait_state(&state, FlightState::Parking, RADIO).await;

    // A long zigzag: still flying well after the outage.
    let wps = zigzag(60, 10.0);
    for chunk in wps.chunks(20) {
        push.call(&chunk.to_vec(), RADIO).await.expect("push");
    }
    change
        .call(
            &StateChangeRequest {
                to: FlightState::WaypointNavigation,
            },
            RADIO,
        )
        .await
        .expect("navigation");
    wait_state(&state, FlightState::WaypointNavigation, STEP).await;

    // The outage: lost after the timeout, the rover holds.
    let cut_at = Instant::now();
    radio.cut().await;
    let lost = next_failsafe(&failsafes, FailsafeKind::LinkLost, STEP).await;
    let lost_at = cut_at.elapsed();
    assert_eq!(lost.action, "hold", "{lost:?}");
    assert!(
        lost.text.contains("no station heartbeat")
            && lost.text.contains("WAYPOINT_NAVIGATION -> PARKING"),
        "{lost:?}"
    );
    assert!(
        // linkLossTimeoutMs (3 s) counts from the last heartbeat, up to 250 ms before the cut.
        lost_at >= Duration::from_millis(2500),
        "lost {lost_at:?} after the cut: before linkLossTimeoutMs"
    );
    wait_state(&state, FlightState::Parking, STEP).await;
    let held = sim.log_events("mode_changed");
    assert!(
        held.iter().any(|m| m["to"] == 4 && m["from"] == 10),
        "mavsim went from AUTO to HOLD: {held:?}"
    );

    // The link returns.
    let back = next_failsafe(&failsafes, FailsafeKind::LinkRestored, OUTAGE_FOR + RADIO).await;
    assert!(
        cut_at.elapsed() >= OUTAGE_FOR,
        "restored {:?} after the cut, before the outage ended",
        cut_at.elapsed()
    );
    let reached_before = sim.log_events("item_reached").len();
    match recovery {
        "resume" => {
            assert_eq!(back.action, "resume", "{back:?}");
            wait_state(&state, FlightState::WaypointNavigation, STEP).await;
            // And it drives on: another waypoint is reached.
            let deadline = Instant::now() + STEP;
            while sim.log_events("item_reached").len() <= reached_before {
                assert!(
                    Instant::now() < deadline,
                    "no waypoint reached after resuming"
                );
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
        _ => {
            assert_eq!(back.action, "wait", "{back:?}");
            assert!(back.text.contains("until the operator"), "{back:?}");
            // Still parked: nobody asked for navigation. The state variable is published on
            // changes only, so its absence for a while is the proof; then the operator resumes.
            if let Ok(s) = state.recv_timeout(Duration::from_secs(3)).await {
                assert_eq!(s.value, FlightState::Parking, "moved without the operator");
            }
            change
                .call(
                    &StateChangeRequest {
                        to: FlightState::WaypointNavigation,
                    },
                    RADIO,
                )
                .await
                .expect("the operator resumes");
            wait_state(&state, FlightState::WaypointNavigation, STEP).await;
        }
    }

    beating.abort();
    vas.kill().await;
    sim.kill().await;
    radio.kill().await;
    ground.shutdown().await;
    obs.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn radio_outage_mid_mission_holds_then_resumes() {
    tokio::time::timeout(Duration::from_secs(240), outage_mid_mission("resume"))
        .await
        .expect("the test took too long");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn radio_outage_mid_mission_holds_then_waits_for_the_operator() {
    tokio::time::timeout(Duration::from_secs(240), outage_mid_mission("wait"))
        .await
        .expect("the test took too long");
}

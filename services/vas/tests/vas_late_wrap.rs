//! A wrap that comes too late: the slot writes stall (a hub between the VAS and mavsim drops
//! every MISSION_WRITE_PARTIAL_LIST and MISSION_COUNT for a while after the first waypoint), so
//! slot 1 does not hold the target when the vehicle heads for the mirror slot, and the
//! autopilot reaches the last item on board and ends its mission with waypoints left. The VAS
//! restarts the navigation instead of following the autopilot into HOLD: every waypoint is
//! still reached once, in order, and the VAL never leaves WAYPOINT_NAVIGATION before the end.

mod common;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use tokio::net::UdpSocket;
use tokio::sync::Mutex;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use usal_types::FlightState;

/// The MAVLink message id of a datagram holding one frame (v1 or v2).
fn msg_id(d: &[u8]) -> Option<u32> {
    match d.first()? {
        0xFD if d.len() >= 10 => Some(u32::from_le_bytes([d[7], d[8], d[9], 0])),
        0xFE if d.len() >= 6 => Some(u32::from(d[5])),
        _ => None,
    }
}

const MISSION_WRITE_PARTIAL_LIST: u32 = 38;
const MISSION_COUNT: u32 = 44;
const MISSION_ITEM_REACHED: u32 = 46;

/// Relays between the VAS and mavsim; from the first MISSION_ITEM_REACHED on, for `stall`,
/// drops the VAS's MISSION_WRITE_PARTIAL_LIST and MISSION_COUNT (every mission write).
/// Returns the hub's address and its two relay tasks.
async fn stalling_hub(sim: &str, stall: Duration) -> (String, [JoinHandle<()>; 2]) {
    let hub = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
    let addr = hub.local_addr().unwrap().to_string();
    let up = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
    up.connect(sim).await.unwrap();
    let vas = Arc::new(Mutex::new(None::<std::net::SocketAddr>));
    let stalling_since = Arc::new(Mutex::new(None::<Instant>));
    let down = {
        let (up, hub, vas, since) = (up.clone(), hub.clone(), vas.clone(), stalling_since.clone());
        tokio::spawn(async move {
            let mut buf = vec![0u8; 2048];
            while let Ok(n) = up.recv(&mut buf).await {
                if msg_id(&buf[..n]) == Some(MISSION_ITEM_REACHED) {
                    since.lock().await.get_or_insert_with(Instant::now);
                }
                if let Some(to) = *vas.lock().await {
                    let _ = hub.send_to(&buf[..n], to).await;
                }
            }
        })
    };
    let upward = tokio::spawn(async move {
        let mut buf = vec![0u8; 2048];
        while let Ok((n, from)) = hub.recv_from(&mut buf).await {
            *vas.lock().await = Some(from);
            let stalled = stalling_since
                .lock()
                .await
                .is_some_and(|t| t.elapsed() < stall);
            let id = msg_id(&buf[..n]);
            if stalled && matches!(id, Some(MISSION_WRITE_PARTIAL_LIST | MISSION_COUNT)) {
                continue;
            }
            let _ = up.send(&buf[..n]).await;
        }
    });
    (addr, [down, upward])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mission_ended_by_a_late_wrap_is_restarted_not_abandoned() {
    tokio::time::timeout(STEP * 8, async {
        let dir = tempfile::tempdir().unwrap();
        let sim = Sim::start_with("127.0.0.1:0", 10.0, &dir.path().join("sim.jsonl"), &[]).await;
        let (link, relay) = stalling_hub(&sim.addr, Duration::from_millis(2500)).await;
        let domain = unique_domain("late-wrap");
        let vas = VasProc::start(
            &format!("udpout:{link}"),
            &domain,
            &["--queue-size", "4", "--request-timeout-ms", "300"],
        );
        let g = Ground::open(&domain).await;
        g.wait_state(FlightState::Parking, STEP).await;
        let n = 14;
        let wps = zigzag(n, 10.0);
        g.fly_in_order(&wps, "late wrap").await;
        // The autopilot did end its mission early (the situation under test) ...
        let completes = sim.log_events("mission_complete").len();
        assert!(
            completes >= 2,
            "no early end provoked ({completes} mission ends)"
        );
        // ... and the VAL stayed in WAYPOINT_NAVIGATION until the last one: the first state
        // change out of it (waited for: the event may trail the state variable) is the
        // final PARKING, and none other follows.
        let mut changes = Vec::new();
        let left = loop {
            let c = g
                .changes
                .recv_timeout(STEP)
                .await
                .expect("state_changed out of WAYPOINT_NAVIGATION")
                .value;
            changes.push((c.from, c.to));
            if c.from == FlightState::WaypointNavigation {
                break c;
            }
        };
        assert_eq!(left.to, FlightState::Parking, "{changes:?}");
        assert!(left.cause.contains("HOLD"), "{left:?}");
        while let Some(Ok(c)) = g.changes.try_recv() {
            changes.push((c.value.from, c.value.to));
        }
        let exits = changes
            .iter()
            .filter(|(from, _)| *from == FlightState::WaypointNavigation)
            .count();
        assert_eq!(exits, 1, "{changes:?}");
        // Every waypoint reached once, in order, by the vehicle too.
        let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
            .into_iter()
            .map(|p| which(&wps, p))
            .collect();
        let mut dedup = order.clone();
        dedup.dedup();
        assert_eq!(dedup, (0..n).map(Some).collect::<Vec<_>>());
        for task in relay {
            task.abort();
        }
        vas.kill().await;
        sim.kill().await;
        g.node.shutdown().await;
    })
    .await
    .expect("late wrap flight bounded");
}

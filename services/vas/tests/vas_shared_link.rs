//! A good GCS citizen on a shared link: two vehicles (mavsim system 1 and system 2) and a
//! camera component of vehicle 2 behind one UDP link, joined by a small hub in this test (as
//! mavlink-router would). The VAS, told `targetSystem="2"`, flies vehicle 2 only, and the
//! camera's heartbeats and MISSION_CURRENT 0 (which, taken for the autopilot's, would read as a
//! drive back home) are ignored. Pinning is off, so the routing alone keeps the other traffic
//! out.

mod common;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavMessage, MavModeFlag, MavState, MavType, HEARTBEAT_DATA, MISSION_CURRENT_DATA,
};
use mavlink::MavHeader;
use tokio::net::UdpSocket;
use usal_types::{FlightState, QueueStatus};

/// Relays datagrams between the VAS (the first to send to `hub`) and every vehicle; returns
/// the hub's address. Also sends, as component 100 of system 2, a camera's heartbeat and a
/// MISSION_CURRENT 0 five times a second.
async fn hub(vehicles: &[String]) -> (String, tokio::task::JoinHandle<()>) {
    let hub = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
    let addr = hub.local_addr().unwrap().to_string();
    let mut ups = Vec::new();
    for v in vehicles {
        let s = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        s.connect(v).await.unwrap();
        ups.push(Arc::new(s));
    }
    let task = tokio::spawn(async move {
        let vas = Arc::new(tokio::sync::Mutex::new(None::<std::net::SocketAddr>));
        let mut tasks = tokio::task::JoinSet::new();
        for up in &ups {
            let (up, hub, vas) = (up.clone(), hub.clone(), vas.clone());
            tasks.spawn(async move {
                let mut buf = vec![0u8; 2048];
                while let Ok(n) = up.recv(&mut buf).await {
                    if let Some(to) = *vas.lock().await {
                        let _ = hub.send_to(&buf[..n], to).await;
                    }
                }
            });
        }
        {
            let (hub, vas) = (hub.clone(), vas.clone());
            tasks.spawn(async move {
                let mut buf = vec![0u8; 2048];
                while let Ok((n, from)) = hub.recv_from(&mut buf).await {
                    *vas.lock().await = Some(from);
                    for up in &ups {
                        let _ = up.send(&buf[..n]).await;
                    }
                }
            });
        }
        tasks.spawn(async move {
            let header = |sequence| MavHeader {
                system_id: 2,
                component_id: 100,
                sequence,
            };
            let camera = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0x0909_0000,
                mavtype: MavType::MAV_TYPE_CAMERA,
                autopilot: MavAutopilot::MAV_AUTOPILOT_GENERIC,
                base_mode: MavModeFlag::empty(),
                system_status: MavState::MAV_STATE_ACTIVE,
                mavlink_version: 3,
            });
            let current = MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
                seq: 0,
                ..Default::default()
            });
            let mut seq = 0u8;
            let mut tick = tokio::time::interval(Duration::from_millis(200));
            loop {
                tick.tick().await;
                let Some(to) = *vas.lock().await else {
                    continue;
                };
                for msg in [&camera, &current] {
                    let mut buf = Vec::new();
                    mavlink::write_v2_msg(&mut buf, header(seq), msg).unwrap();
                    seq = seq.wrapping_add(1);
                    let _ = hub.send_to(&buf, to).await;
                }
            }
        });
        while tasks.join_next().await.is_some() {}
    });
    (addr, task)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_vehicles_and_a_camera_on_one_link_the_vas_flies_its_own() {
    tokio::time::timeout(STEP * 8, async {
        let dir = tempfile::tempdir().unwrap();
        let other = Sim::start_with(
            "127.0.0.1:0",
            30.0,
            &dir.path().join("sys1.jsonl"),
            &["--sysid", "1"],
        )
        .await;
        let mine = Sim::start_with(
            "127.0.0.1:0",
            30.0,
            &dir.path().join("sys2.jsonl"),
            &["--sysid", "2"],
        )
        .await;
        let (link, relay) = hub(&[other.addr.clone(), mine.addr.clone()]).await;
        let cfg = dir.path().join("vas.xml");
        std::fs::write(&cfg, r#"<vas targetSystem="2" pinAutopilot="false"/>"#).unwrap();
        let domain = unique_domain("shared-link");
        let vas = VasProc::start(
            &format!("udpout:{link}"),
            &domain,
            &["--config", cfg.to_str().unwrap(), "--queue-size", "5"],
        );
        let g = Ground::open(&domain).await;
        let queue = g
            .svc
            .subscribe_variable::<QueueStatus>("rover1/vas/queue")
            .unwrap();
        g.wait_state(FlightState::Parking, STEP).await;
        let n = 12;
        let wps = zigzag(n, 10.0);
        g.fly_in_order(&wps, "shared link").await;

        // Vehicle 2 flew the plan, in order.
        let order: Vec<Option<usize>> = reached_points(&mine.log_events("item_reached"))
            .into_iter()
            .map(|p| which(&wps, p))
            .collect();
        assert_eq!(order, (0..n).map(Some).collect::<Vec<_>>());
        // Vehicle 1 was left alone: no mission, never armed.
        assert!(other.log_events("mission_uploaded").is_empty());
        assert!(other.log_events("armed").is_empty());
        // The camera's MISSION_CURRENT 0 was not taken for the autopilot driving home.
        let last = latest_queue_status(&queue);
        assert_eq!(last.backtracks, 0, "{last:?}");
        relay.abort();
        vas.kill().await;
        mine.kill().await;
        other.kill().await;
        g.node.shutdown().await;
    })
    .await
    .expect("shared link flight bounded");
}

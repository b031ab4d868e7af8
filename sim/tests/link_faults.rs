//! The manager against mavsim over a lossy link and across a simulator restart.

mod common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use common::{bounded, connect, line_mission, start_mission, Sim, Via, STEP};
use mavlink::dialects::ardupilotmega::MavMessage;
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use vas::mavlink_cm::{ManagerConfig, MavEvent};

/// A UDP relay between the manager and mavsim that drops the datagrams `drop_it` picks
/// (given the datagram and whether it goes to the vehicle).
struct Proxy {
    addr: SocketAddr,
    task: JoinHandle<()>,
}

impl Proxy {
    /// Drops `loss` of the datagrams in each direction, with a seeded xorshift so a failure
    /// is reproducible.
    async fn lossy(upstream: SocketAddr, loss: f64, seed: u64) -> Self {
        let mut rng = seed | 1;
        Self::start(upstream, move |_, _| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % 10_000) as f64 / 10_000.0 < loss
        })
        .await
    }

    async fn start(
        upstream: SocketAddr,
        mut drop_it: impl FnMut(&[u8], bool) -> bool + Send + 'static,
    ) -> Self {
        let front = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind front"));
        let back = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind back"));
        let addr = front.local_addr().expect("front addr");
        let task = tokio::spawn(async move {
            let mut client: Option<SocketAddr> = None;
            let mut a = vec![0u8; 65_536];
            let mut b = vec![0u8; 65_536];
            loop {
                tokio::select! {
                    r = front.recv_from(&mut a) => {
                        let Ok((n, from)) = r else { continue };
                        client = Some(from);
                        if !drop_it(&a[..n], true) {
                            let _ = back.send_to(&a[..n], upstream).await;
                        }
                    }
                    r = back.recv_from(&mut b) => {
                        let Ok((n, _)) = r else { continue };
                        if let (Some(c), false) = (client, drop_it(&b[..n], false)) {
                            let _ = front.send_to(&b[..n], c).await;
                        }
                    }
                }
            }
        });
        Self { addr, task }
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.task.abort();
    }
}

#[tokio::test]
async fn mission_transfers_survive_ten_percent_loss() {
    let sim = Sim::start(Via::Udp, &[]).await;
    let upstream: SocketAddr = format!("127.0.0.1:{}", sim.udp_port()).parse().unwrap();
    let proxy = Proxy::lossy(upstream, 0.10, 0x5eed).await;
    let cfg = ManagerConfig {
        request_timeout: Duration::from_millis(300),
        retries: 12,
        ..ManagerConfig::default()
    };
    let mgr = connect(&format!("udpout:{}", proxy.addr), cfg).await;

    let items = line_mission(20, 10.0, 0.0);
    tokio::time::timeout(Duration::from_secs(60), mgr.mission_upload(&items))
        .await
        .expect("upload in time")
        .expect("upload");
    let replacement = line_mission(3, 40.0, 20.0)[1..].to_vec();
    tokio::time::timeout(
        Duration::from_secs(60),
        mgr.mission_write_partial(5, &replacement),
    )
    .await
    .expect("partial in time")
    .expect("partial write");
    let down = tokio::time::timeout(Duration::from_secs(60), mgr.mission_download())
        .await
        .expect("download in time")
        .expect("download");
    let mut expected = items.clone();
    expected[5..8].clone_from_slice(&replacement);
    assert_eq!(down[1..], expected[1..]);
    // Exactly one commit of each: a lossy link never produced a half-written mission.
    assert_eq!(sim.log_events("mission_uploaded").len(), 1);
    assert_eq!(sim.log_events("mission_partial_write").len(), 1);
    mgr.shutdown().await;
    sim.stop().await;
}

#[tokio::test]
async fn link_lost_and_restored_across_a_restart() {
    let sim = Sim::start(Via::Udp, &[]).await;
    let port = sim.udp_port();
    let cfg = ManagerConfig {
        heartbeat_timeout: Duration::from_millis(1500),
        ..ManagerConfig::default()
    };
    let mgr = connect(&sim.endpoint, cfg).await;
    let mut events = mgr.subscribe();
    sim.stop().await;
    bounded("link lost", async {
        while !matches!(events.recv().await, Ok(MavEvent::LinkLost)) {}
    })
    .await;
    assert!(!mgr.state().link_up);

    let sim = Sim::start(Via::UdpAt(port), &[]).await;
    bounded("link restored", async {
        while !matches!(events.recv().await, Ok(MavEvent::LinkRestored)) {}
    })
    .await;
    assert!(mgr.wait_connected(STEP).await.expect("up again").link_up);
    // The restarted autopilot answers requests again.
    assert_eq!(
        bounded("param", mgr.param_get("WP_RADIUS"))
            .await
            .expect("param"),
        2.0
    );
    mgr.shutdown().await;
    sim.stop().await;
}

#[tokio::test]
async fn garbage_bytes_do_not_stop_mavsim() {
    let sim = Sim::start(Via::Udp, &[]).await;
    let target: SocketAddr = format!("127.0.0.1:{}", sim.udp_port()).parse().unwrap();
    let sock = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut rng = 0x1234_5678_9abc_def1_u64;
    for len in [0usize, 1, 7, 64, 280, 1500] {
        let mut buf = vec![0u8; len];
        for b in &mut buf {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            *b = rng as u8;
        }
        // Sprinkle frame markers so the decoder tries hard.
        for b in buf.iter_mut().step_by(11) {
            *b = 0xFD;
        }
        sock.send_to(&buf, target).await.unwrap();
    }
    let mgr = sim.manager().await;
    assert_eq!(
        bounded("param", mgr.param_get("WP_RADIUS"))
            .await
            .expect("still answering"),
        2.0
    );
    mgr.shutdown().await;
    sim.stop().await;
}

/// Whether `datagram` starts with a MAVLink frame of MISSION_CURRENT reporting item `seq`.
fn mission_current_of(datagram: &[u8], seq: u16) -> bool {
    matches!(
        mavlink::MavlinkReader::new(datagram).read_any_message::<MavMessage>(),
        Ok((_, MavMessage::MISSION_CURRENT(c))) if c.seq == seq
    )
}

/// Until the manager reports waypoint `want` reached.
async fn reached(events: &mut tokio::sync::broadcast::Receiver<MavEvent>, want: u16) {
    loop {
        match events.recv().await {
            Ok(MavEvent::WaypointReached { seq, .. }) if seq == want => return,
            Ok(_) => {}
            Err(e) => panic!("event stream: {e}"),
        }
    }
}

/// A set-current whose confirmation is lost, while the vehicle reaches the item at once and
/// goes on: the manager takes the reach as the confirmation and does not set the item again,
/// which would send the vehicle back to a waypoint it has just passed. (Every report of item
/// 1 as current is dropped here; over a lossy radio one of them was, and the VAS flew a
/// waypoint five times.)
#[tokio::test]
async fn a_set_current_confirmed_by_the_reach_is_not_repeated() {
    let sim = Sim::start(Via::Udp, &["--speedup", "10"]).await;
    let upstream: SocketAddr = format!("127.0.0.1:{}", sim.udp_port()).parse().unwrap();
    let proxy = Proxy::start(upstream, |d, to_vehicle| {
        !to_vehicle && mission_current_of(d, 1)
    })
    .await;
    let cfg = ManagerConfig {
        request_timeout: Duration::from_secs(2),
        retries: 3,
        ..ManagerConfig::default()
    };
    let mgr = connect(&format!("udpout:{}", proxy.addr), cfg).await;
    let mut events = start_mission(&mgr, &line_mission(2, 20.0, 0.0)).await;
    bounded("waypoint 1 reached", reached(&mut events, 1)).await;
    // Back to the waypoint just passed: the rover is next to it and reaches it at once.
    bounded("set current 1", mgr.mission_set_current(1))
        .await
        .expect("set current");
    bounded("waypoint 2 reached", reached(&mut events, 2)).await;
    // mavsim logs each change of its current item; a second attempt would set 1 again while
    // the rover drives to 2 (before the change, it set 1 again after a request timeout).
    let sets = sim
        .log_events("current_changed")
        .iter()
        .filter(|r| r["cause"] == "set_current")
        .count();
    assert_eq!(
        sets,
        1,
        "item 1 set once, confirmed by its reach: {:?}",
        sim.log_records()
    );
    mgr.shutdown().await;
    sim.stop().await;
}

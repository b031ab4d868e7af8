//! The manager against mavsim over a lossy link and across a simulator restart.

mod common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use common::{bounded, connect, line_mission, Sim, Via, STEP};
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use vas::mavlink_cm::{ManagerConfig, MavEvent};

/// A UDP relay that drops `loss` of the datagrams in each direction, with a
/// seeded xorshift so a failure is reproducible.
struct LossyProxy {
    addr: SocketAddr,
    task: JoinHandle<()>,
}

impl LossyProxy {
    async fn start(upstream: SocketAddr, loss: f64, seed: u64) -> Self {
        let front = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind front"));
        let back = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind back"));
        let addr = front.local_addr().expect("front addr");
        let task = tokio::spawn(async move {
            let mut rng = seed | 1;
            let mut drop_it = move || {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                (rng % 10_000) as f64 / 10_000.0 < loss
            };
            let mut client: Option<SocketAddr> = None;
            let mut a = vec![0u8; 65_536];
            let mut b = vec![0u8; 65_536];
            loop {
                tokio::select! {
                    r = front.recv_from(&mut a) => {
                        let Ok((n, from)) = r else { continue };
                        client = Some(from);
                        if !drop_it() {
                            let _ = back.send_to(&a[..n], upstream).await;
                        }
                    }
                    r = back.recv_from(&mut b) => {
                        let Ok((n, _)) = r else { continue };
                        if let (Some(c), false) = (client, drop_it()) {
                            let _ = front.send_to(&b[..n], c).await;
                        }
                    }
                }
            }
        });
        Self { addr, task }
    }
}

impl Drop for LossyProxy {
    fn drop(&mut self) {
        self.task.abort();
    }
}

#[tokio::test]
async fn mission_transfers_survive_ten_percent_loss() {
    let sim = Sim::start(Via::Udp, &[]).await;
    let upstream: SocketAddr = format!("127.0.0.1:{}", sim.udp_port()).parse().unwrap();
    let proxy = LossyProxy::start(upstream, 0.10, 0x5eed).await;
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

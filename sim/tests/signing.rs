//! MAVLink 2 signing between the VAS's manager and the real mavsim binary: with the same key
//! they fly a mission; unsigned commands (a raw socket, a manager without the key) are ignored
//! by mavsim.

mod common;

use std::os::unix::fs::PermissionsExt;
use std::time::Duration;

use common::{bounded, connect, line_mission, start_mission, Sim, Via};
use mavlink::dialects::ardupilotmega::{MavCmd, MavMessage, COMMAND_LONG_DATA};
use mavlink::{MavHeader, MavlinkVersion};
use vas::mavlink_cm::{ManagerConfig, MavlinkManager};

fn key_file(dir: &std::path::Path, byte: u8) -> std::path::PathBuf {
    let path = dir.join(format!("key{byte}"));
    std::fs::write(&path, format!("{byte:02x}").repeat(32)).expect("write key");
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    path
}

fn signing(path: &std::path::Path) -> Option<mavconn::Signing> {
    Some(mavconn::Signing {
        key: mavconn::SigningKey::load(path).expect("key"),
        link_id: 1,
    })
}

/// An unsigned COMMAND_LONG asking mavsim (system 1) to arm, as a GCS would send it.
fn unsigned_arm() -> Vec<u8> {
    let msg = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        target_system: 1,
        target_component: 1,
        command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        confirmation: 0,
        param1: 1.0,
        param2: 0.0,
        param3: 0.0,
        param4: 0.0,
        param5: 0.0,
        param6: 0.0,
        param7: 0.0,
    });
    let header = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };
    let mut buf = Vec::new();
    mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header, &msg).expect("encode");
    buf
}

#[tokio::test]
async fn signed_manager_flies_and_unsigned_commands_are_ignored() {
    let dir = tempfile::tempdir().expect("tempdir");
    let key = key_file(dir.path(), 0x5a);
    let sim = Sim::start(
        Via::Udp,
        &[
            "--signing-key",
            key.to_str().expect("utf-8"),
            "--speedup",
            "10",
        ],
    )
    .await;

    // A raw socket without the key asks mavsim to arm.
    let injector = tokio::net::UdpSocket::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let target = format!("127.0.0.1:{}", sim.udp_port());
    bounded("inject", injector.send_to(&unsigned_arm(), &target))
        .await
        .expect("send");

    // The signed manager connects and commands normally.
    let cfg = ManagerConfig {
        request_timeout: Duration::from_millis(500),
        signing: signing(&key),
        ..ManagerConfig::default()
    };
    let mgr = connect(&sim.endpoint, cfg).await;
    assert_eq!(mgr.counters().rejected_signatures(), 0);
    bounded("hold", mgr.set_mode("HOLD")).await.expect("hold");
    assert!(!mgr.state().armed, "the unsigned arm command was obeyed");
    assert!(sim.log_events("armed").is_empty());

    // A manager without the key is not even answered: mavsim only replies to the sender of
    // a correctly signed frame, so it never sees a heartbeat.
    let unsigned = MavlinkManager::open(
        &sim.endpoint,
        ManagerConfig {
            connect_wait: Duration::from_millis(500),
            ..ManagerConfig::default()
        },
    )
    .await
    .expect("open");
    assert!(bounded(
        "unsigned connect",
        unsigned.wait_connected(Duration::from_secs(2))
    )
    .await
    .is_err());
    assert!(bounded("unsigned arm", unsigned.arm(true)).await.is_err());
    unsigned.shutdown().await;
    assert!(sim.log_events("armed").is_empty());

    // And the signed one flies a mission to its end.
    start_mission(&mgr, &line_mission(2, 10.0, 0.0)).await;
    bounded("mission complete", async {
        while sim.log_events("mission_complete").is_empty() {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    assert_eq!(
        sim.log_events("armed").len(),
        1,
        "armed once, by the signed manager"
    );
    mgr.shutdown().await;
    sim.stop().await;
}

#[tokio::test]
async fn mavsim_refuses_a_key_file_others_can_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let key = key_file(dir.path(), 1);
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).expect("chmod");
    let out = bounded(
        "mavsim exits",
        tokio::process::Command::new(env!("CARGO_BIN_EXE_mavsim"))
            .args(["--udp", "127.0.0.1:0", "--signing-key"])
            .arg(&key)
            .output(),
    )
    .await
    .expect("run mavsim");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("chmod 600"), "{err}");
}

//! The camera service against a real `mavsim --camera`, over real sockets: the frames of the
//! simulated camera reach a subscriber as JPEG (`frame`) and uncompressed (`raw`), carrying
//! the camera's pose, with the point of interest under the vehicle drawn where the pose puts
//! it; a small picture comes on request (`snapshot`); the service reconnects when the camera
//! restarts.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use marea::{NetworkConfig, Node};
use usal_types::camera::CameraFrame;
use usal_types::items::camera as items;

const T: Duration = Duration::from_secs(30);
const HOME: (f64, f64) = (41.275, 1.987);

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// mavsim with a 160x120 camera serving on `listen`, a point of interest at home.
fn mavsim(listen: &str, pois: &std::path::Path) -> (Kill, String) {
    let mut child = Command::new(test_support::workspace_bin("mavsim"))
        .args([
            "--vehicle",
            "copter",
            "--udp",
            "127.0.0.1:0",
            "--camera",
            "160x120",
        ])
        .args([
            "--camera-fps",
            "10",
            "--camera-hfov",
            "90",
            "--camera-listen",
            listen,
        ])
        .args(["--home", &format!("{},{},0", HOME.0, HOME.1)])
        .arg("--poi-file")
        .arg(pois)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("mavsim starts");
    let mut lines = BufReader::new(child.stdout.take().expect("piped")).lines();
    let camera = loop {
        let line = lines.next().expect("a line").expect("stdout");
        if let Some(addr) = line.strip_prefix("MAVSIM_CAMERA=") {
            break addr.to_owned();
        }
    };
    (Kill(child), camera)
}

fn pixel(f: &CameraFrame, x: u32, y: u32) -> [u8; 3] {
    let i = ((y * f.width + x) * 3) as usize;
    [f.data[i], f.data[i + 1], f.data[i + 2]]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_of_the_simulated_camera_reach_a_subscriber_raw_as_jpeg_and_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let pois = dir.path().join("pois.txt");
    std::fs::write(&pois, format!("{},{}\n", HOME.0, HOME.1)).unwrap();
    let port = test_support::free_tcp_port();
    let listen = format!("127.0.0.1:{port}");
    let (sim, addr) = mavsim(&listen, &pois);
    assert_eq!(addr, listen);
    let domain = format!("camera-{}", std::process::id());
    let _camera = Kill(
        Command::new(test_support::workspace_bin("camera"))
            .args([
                "--source",
                &addr,
                "--domain",
                &domain,
                "--namespace",
                "uav1",
            ])
            .stdout(Stdio::null())
            .spawn()
            .expect("camera starts"),
    );
    let mut cfg = NetworkConfig::ethernet_loopback("ground");
    cfg.domain = domain;
    let node = Node::open(&cfg).await.unwrap();
    let svc = node.service("gcs").unwrap();
    let frames = items::FRAME.subscribe(&svc, "uav1/camera").unwrap();
    let raws = items::RAW.subscribe(&svc, "uav1/camera").unwrap();

    let f = frames.recv_timeout(T).await.expect("a JPEG frame").value;
    assert_eq!((f.width, f.height, f.format.as_str()), (160, 120, "jpeg"));
    assert_eq!(&f.data[..2], &[0xFF, 0xD8], "a JPEG");
    assert!((f.pose.lat - HOME.0).abs() < 1e-5 && (f.pose.lon - HOME.1).abs() < 1e-5);
    assert_eq!(f.pose.hfov_deg, 90.0);
    let age = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
        - f.taken_unix_ms;
    assert!(age < 10_000, "a live frame, not an old one: {age} ms");

    let r = raws.recv_timeout(T).await.expect("a raw frame").value;
    assert_eq!((r.format.as_str(), r.data.len()), ("rgb8", 160 * 120 * 3));
    // On the ground at home, the point of interest is under the camera: the centre is red;
    // a corner (2 m up with a 90° field: 4 m across) is grass.
    assert_eq!(pixel(&r, 80, 60), [220, 30, 30]);
    assert_ne!(pixel(&r, 2, 2), [220, 30, 30]);
    let (lat, lon) = r.ground_point(80.0, 60.0).expect("inside");
    assert!((lat - HOME.0).abs() < 1e-5 && (lon - HOME.1).abs() < 1e-5);

    let snapshot = items::SNAPSHOT.function(&svc, "uav1/camera").unwrap();
    assert!(snapshot.wait_provider(T).await);
    let small = snapshot.call(&40, T).await.expect("a snapshot");
    assert_eq!(
        (small.width, small.height, small.format.as_str()),
        (40, 30, "jpeg")
    );
    assert!(small.data.len() < f.data.len());

    // The camera restarts on the same address: frames come again.
    drop(sim);
    let (_sim, _) = mavsim(&listen, &pois);
    let restarted = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    let again = tokio::time::timeout(T, async {
        loop {
            let f = raws.recv().await.expect("raw frames").value;
            if f.taken_unix_ms >= restarted {
                return f;
            }
        }
    })
    .await
    .expect("frames after the camera restarted");
    assert_eq!(again.width, 160);
    node.shutdown().await;
}

//! `cargo bench --bench camera`: a vehicle's camera to a station, as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`.
//!
//! Real processes: the release `mavsim --camera WxH --camera-fps 10` renders frames and serves
//! them over TCP; the release `camera` service reads them and publishes them over marea (UDP on
//! loopback); this bench subscribes as a station would, for [`WINDOW`] a size:
//!
//! - `camera.<size>.jpeg.latency_ms_p50` / `_p99`: from the moment mavsim took the frame
//!   (`taken_unix_ms`) to its JPEG reaching the subscriber (the same host's clock): rendering
//!   aside, reading, compressing and crossing marea;
//! - `camera.<size>.jpeg.frames_per_s`: JPEG frames received a second (10 wanted);
//! - `camera.<size>.raw.latency_ms_p50` / `frames_per_s`: the same of the uncompressed frame
//!   (`raw`, 3 bytes a pixel: 230 KB at 320x240, 922 KB at 640x480), which marea carries in
//!   parts over UDP;
//! - `camera.<size>.jpeg.bytes`: a JPEG frame's size.
//!
//! `<size>` is `320x240` and `640x480`.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use marea::{NetworkConfig, Node};
use usal_types::items::camera as items;

/// The measurement window of each size.
const WINDOW: Duration = Duration::from_secs(10);
/// Frames a second asked of the camera.
const FPS: f64 = 10.0;

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

fn percentile(v: &mut [u64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize] as f64
}

/// The release binaries of mavsim and the camera service, built if needed.
fn binaries() -> (std::path::PathBuf, std::path::PathBuf) {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let status = Command::new(cargo)
        .args(["build", "--release", "-p", "mavsim", "-p", "camera"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .status()
        .expect("cargo runs");
    assert!(status.success(), "building mavsim and camera");
    let target = test_support::target_dir().join("release");
    (target.join("mavsim"), target.join("camera"))
}

async fn measure(mavsim: &std::path::Path, camera: &std::path::Path, size: &str) {
    let listen = format!("127.0.0.1:{}", test_support::free_tcp_port());
    let mut sim = Command::new(mavsim)
        .args([
            "--vehicle",
            "copter",
            "--udp",
            "127.0.0.1:0",
            "--camera",
            size,
        ])
        .args(["--camera-fps", &FPS.to_string(), "--camera-listen", &listen])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("mavsim starts");
    let mut lines = BufReader::new(sim.stdout.take().expect("piped")).lines();
    while !lines
        .next()
        .and_then(Result::ok)
        .is_some_and(|l| l.starts_with("MAVSIM_CAMERA="))
    {}
    let _sim = Kill(sim);
    let domain = format!("camera-bench-{}-{size}", std::process::id());
    let _camera = Kill(
        Command::new(camera)
            .args([
                "--source",
                &listen,
                "--domain",
                &domain,
                "--namespace",
                "uav1",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("camera starts"),
    );
    let mut cfg = NetworkConfig::ethernet_loopback("station");
    cfg.domain = domain;
    let node = Node::open(&cfg).await.expect("node");
    let svc = node.service("gcs").expect("service");
    for raw in [false, true] {
        let item = if raw { items::RAW } else { items::FRAME };
        let sub = item.subscribe(&svc, "uav1/camera").expect("subscribe");
        // The first frame: the camera is up and the subscription matched.
        sub.recv_timeout(Duration::from_secs(60))
            .await
            .expect("a first frame");
        let mut latencies = Vec::new();
        let mut bytes = 0usize;
        let started = Instant::now();
        while started.elapsed() < WINDOW {
            let Ok(s) = sub.recv_timeout(WINDOW).await else {
                break;
            };
            latencies.push(now_ms().saturating_sub(s.value.taken_unix_ms));
            bytes = s.value.data.len();
        }
        let rate = latencies.len() as f64 / started.elapsed().as_secs_f64();
        let kind = if raw { "raw" } else { "jpeg" };
        let base = format!("camera.{size}.{kind}");
        metric(
            &format!("{base}.latency_ms_p50"),
            percentile(&mut latencies, 0.5),
            "ms",
        );
        metric(
            &format!("{base}.latency_ms_p99"),
            percentile(&mut latencies, 0.99),
            "ms",
        );
        metric(&format!("{base}.frames_per_s"), rate, "frames/s");
        if !raw {
            metric(&format!("{base}.bytes"), bytes as f64, "bytes");
        }
        drop(sub);
    }
    node.shutdown().await;
}

fn main() {
    let (mavsim, camera) = binaries();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    for size in ["320x240", "640x480"] {
        rt.block_on(measure(&mavsim, &camera, size));
    }
}

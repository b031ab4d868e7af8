//! `cargo bench --bench waypoints`: the VAS's rolling waypoint queue (003 §3.3.2) against
//! mavsim, as JSON lines `{"metric": ..., "value": ..., "unit": ...}`.
//!
//! Real processes over real UDP MAVLink, as in production: the release `mavsim` and `vas`
//! binaries (built first), and a ground node in this process that pushes the plan to the VAS
//! and follows `waypoint_reached` over the middleware.
//!
//! - `vas.rolling_queue.waypoints_10000.*`: 10,000 waypoints 10 m apart through a 5-slot queue,
//!   mavsim accelerated [`SPEEDUP`] times. `skipped` (plan waypoints mavsim never reached) and
//!   `repeated` (reaches beyond the first of a waypoint) come from mavsim's own log of reached
//!   items and must both be 0; `sim_seconds` is simulated time from AUTO to the last reach,
//!   `wall_seconds` the ground's time from the request to the last `waypoint_reached`.
//! - `vas.cpu_percent`: CPU time of the `vas` process (from `/proc/<pid>/stat`) over
//!   [`CPU_WINDOW`] of real-time flight (no speed-up) with 10 Hz telemetry, in percent of
//!   one core.
//! - `fpma.parse_1mb_ms`: wall time of [`flightplan::parse::parse_plan`] (the document alone) on a
//!   generated valid plan of about 1 MB (a fix and a TF leg per waypoint), best of
//!   [`PARSE_RUNS`]. In process, nothing to build or start.
//! - `fpma.load_1mb_ms`: the whole load of that plan as the FPMa makes it, best of
//!   [`PARSE_RUNS`]: parse and check ([`flightplan::check::load`]: vehicle rules, the one nominal
//!   simulation, the fence), the executive started from the checked plan, the stations'
//!   geometry drawn from the check's stream, and the first look-ahead handed out.
//!
//! - `vas.conformance.mavsdk.waypoints_50.{skipped,repeated,backtracks}`: 50 waypoints 10 m
//!   apart flown by the `vas` binary on a rover built from MAVSDK's server plugins
//!   (`tests/python/mavsdk_vehicle.py`, in the venv the tests use), counted from what the
//!   vehicle reports (reached items, current-item changes); all must be 0. Skipped, saying so,
//!   where `python3` is absent.
//! - `vas.conformance.px4_profile.waypoints_50.backtracks`: the same plan on mavsim
//!   `--autopilot px4` (current item reset by every upload, no partial writes): reaches of a
//!   point before one already reached, or of a point not in the plan, plus those the VAS
//!   counted (its `queue` variable); must be 0.
//! - `vas.conformance.reset_on_upload.waypoints_50.backtracks`: the same on mavsim
//!   `--autopilot ardupilot-resetting`, a vehicle that says it is ArduPilot (item 0 home) but
//!   resets its current item after every whole upload and answers no partial write; must be 0.
//! - `vas.partial_write_probe_ms`: time the VAS's manager takes to find out that an autopilot
//!   (mavsim `--autopilot px4`) has no partial mission writes (≤ 1500 ms).
//!
//! `WP_VAS_LOG=1` lets the VAS's log through to stderr (with `RUST_LOG=vas=debug`, every
//! queue action). Arguments that do not start with `--` select figures by substring, e.g.
//! `cargo bench --bench waypoints -- fpma.parse` runs only the parse figure (seconds), while
//! the VAS figures build release binaries and fly for a minute or more.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use marea::{EventSubscriber, Function, NetworkConfig, Node, VariableSubscriber};
use usal_types::{
    FlightState, QueueStatus, StateChangeReply, StateChangeRequest, Waypoint, WaypointReached,
};

/// Waypoints of the long run.
const WAYPOINTS: usize = 10_000;
/// Simulated seconds per wall second in the long run: a 10 m leg (about 5.6 s at the rover's
/// 2 m/s) takes about 28 ms of wall time, which the queue's one-leg slack for the wrap to slot
/// 1 must absorb.
const SPEEDUP: f64 = 200.0;
/// Real-time flight over which the VAS's CPU use is measured.
const CPU_WINDOW: Duration = Duration::from_secs(10);
/// Home of the simulated rover.
const HOME: (f64, f64) = (41.2757, 1.9881);
/// Size of the generated plan for `fpma.parse_1mb_ms`.
const PARSE_BYTES: usize = 1 << 20;
/// Parses timed for `fpma.parse_1mb_ms` (the best one is reported).
const PARSE_RUNS: usize = 3;
/// Bound on each wait for a process or the middleware.
const STEP: Duration = Duration::from_secs(30);

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

/// Builds the release `mavsim` and `vas` into this bench's target directory.
fn build_bins() -> anyhow::Result<PathBuf> {
    // <target>/release/deps/<bench binary>.
    let exe = std::env::current_exe().context("bench binary path")?;
    let target = exe
        .ancestors()
        .nth(3)
        .context("bench binary inside <target>/<profile>/deps")?
        .to_owned();
    let status = Command::new(env!("CARGO"))
        .args(["build", "--release", "-p", "mavsim", "-p", "vas"])
        .env("CARGO_TARGET_DIR", &target)
        .status()
        .context("running cargo build")?;
    if !status.success() {
        bail!("building mavsim and vas failed");
    }
    Ok(target.join("release"))
}

/// A child process killed when dropped.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts mavsim on a free UDP port; returns it and its address.
fn start_sim(bins: &Path, speedup: f64, log: &Path) -> anyhow::Result<(Proc, String)> {
    start_sim_with(bins, speedup, log, &[])
}

/// [`start_sim`] with extra mavsim arguments (`--autopilot px4`).
fn start_sim_with(
    bins: &Path,
    speedup: f64,
    log: &Path,
    extra: &[&str],
) -> anyhow::Result<(Proc, String)> {
    use std::io::BufRead;
    let mut child = Command::new(bins.join("mavsim"))
        .args(["--udp", "127.0.0.1:0", "--speedup", &speedup.to_string()])
        .args(extra)
        .arg("--home")
        .arg(format!("{},{},10", HOME.0, HOME.1))
        .arg("--log")
        .arg(log)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting mavsim")?;
    let stdout = child.stdout.take().context("mavsim stdout")?;
    let proc = Proc(child);
    // mavsim prints its address at once or exits (then the line is missing).
    let mut line = String::new();
    std::io::BufReader::new(stdout)
        .read_line(&mut line)
        .context("reading mavsim's address")?;
    let addr = line
        .trim()
        .strip_prefix("MAVSIM_UDP=")
        .with_context(|| format!("unexpected mavsim output {line:?}"))?
        .to_owned();
    Ok((proc, addr))
}

fn start_vas(bins: &Path, addr: &str, domain: &str) -> anyhow::Result<Proc> {
    let child = Command::new(bins.join("vas"))
        .args(["--endpoint", &format!("udpout:{addr}"), "--domain", domain])
        .args(["--namespace", "bench1", "--queue-size", "5"])
        .args(["--telemetry-hz", "10"])
        .stdout(Stdio::null())
        .stderr(if std::env::var_os("WP_VAS_LOG").is_some() {
            Stdio::inherit()
        } else {
            Stdio::null()
        })
        .spawn()
        .context("starting vas")?;
    Ok(Proc(child))
}

/// The ground side: what the FPMa uses of the VAS.
struct Ground {
    node: Node,
    change_state: Function<StateChangeRequest, StateChangeReply>,
    push: Function<Vec<Waypoint>, QueueStatus>,
    reached: EventSubscriber<WaypointReached>,
    state: VariableSubscriber<FlightState>,
}

impl Ground {
    async fn open(domain: &str) -> anyhow::Result<Ground> {
        let mut cfg = NetworkConfig::ethernet_loopback("bench-ground");
        cfg.domain = domain.to_owned();
        let node = Node::open(&cfg).await.context("ground node")?;
        let svc = node.service("gcs")?;
        let g = Ground {
            change_state: svc.function("bench1/vas/change_state")?,
            push: svc.function("bench1/vas/push_waypoints")?,
            reached: svc.subscribe_event("bench1/vas/waypoint_reached")?,
            state: svc.subscribe_variable("bench1/vas/flight_state")?,
            node,
        };
        if !g.change_state.wait_provider(STEP).await {
            bail!("the VAS was not discovered");
        }
        g.wait_state(FlightState::Parking).await?;
        Ok(g)
    }

    async fn wait_state(&self, want: FlightState) -> anyhow::Result<()> {
        let deadline = tokio::time::Instant::now() + STEP;
        loop {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            let s = self
                .state
                .recv_timeout(left)
                .await
                .with_context(|| format!("flight state never became {want}"))?;
            if s.value == want {
                return Ok(());
            }
        }
    }

    async fn fly(&self, wps: &[Waypoint]) -> anyhow::Result<()> {
        for chunk in wps.chunks(100) {
            self.push
                .call(&chunk.to_vec(), STEP)
                .await
                .context("push_waypoints")?;
        }
        self.change_state
            .call(
                &StateChangeRequest {
                    to: FlightState::WaypointNavigation,
                },
                STEP,
            )
            .await
            .context("WAYPOINT_NAVIGATION")?;
        Ok(())
    }
}

/// `n` waypoints zigzagging north of home, 10 m apart.
fn zigzag(n: usize) -> Vec<Waypoint> {
    let m_per_deg_lat = 111_319.49;
    let m_per_deg_lon = m_per_deg_lat * HOME.0.to_radians().cos();
    (0..n)
        .map(|i| {
            let north = 10.0 * (i + 1) as f64;
            let east = if i % 2 == 0 { 0.0 } else { 5.0 };
            Waypoint {
                seq: i as u64,
                lat: HOME.0 + north / m_per_deg_lat,
                lon: HOME.1 + east / m_per_deg_lon,
                leg: format!("leg{}", i / 100),
                ..Waypoint::default()
            }
        })
        .collect()
}

/// mavsim's log records of one event kind.
fn log_events(log: &Path, event: &str) -> Vec<serde_json::Value> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|r| r["event"] == event)
        .collect()
}

/// Waypoints mavsim never reached, and reaches beyond the first of a waypoint (a reach of a
/// point that is no plan waypoint counts as repeated: the vehicle drove to a stale slot).
fn skipped_and_repeated(wps: &[Waypoint], log: &Path) -> (usize, usize) {
    // mavsim stores positions as MAVLink's 1e-7 degree integers.
    let key = |lat: f64, lon: f64| ((lat * 1e7).round() as i64, (lon * 1e7).round() as i64);
    let index: HashMap<(i64, i64), usize> = wps
        .iter()
        .enumerate()
        .map(|(i, w)| (key(w.lat, w.lon), i))
        .collect();
    let mut times = vec![0usize; wps.len()];
    let mut strays = 0;
    for r in log_events(log, "item_reached") {
        let (Some(lat), Some(lon)) = (r["lat"].as_f64(), r["lon"].as_f64()) else {
            continue;
        };
        match index.get(&key(lat, lon)) {
            Some(&i) => times[i] += 1,
            None => strays += 1,
        }
    }
    let skipped = times.iter().filter(|&&t| t == 0).count();
    let repeated = times.iter().map(|&t| t.saturating_sub(1)).sum::<usize>() + strays;
    (skipped, repeated)
}

/// Simulated seconds from the start of AUTO to the last reach.
fn sim_seconds(log: &Path) -> f64 {
    let start = log_events(log, "mode_changed")
        .iter()
        .find(|r| r["name"] == "AUTO")
        .and_then(|r| r["t_sim"].as_f64())
        .unwrap_or(0.0);
    let end = log_events(log, "item_reached")
        .last()
        .and_then(|r| r["t_sim"].as_f64())
        .unwrap_or(start);
    end - start
}

/// User plus system CPU time of `pid`, seconds.
fn cpu_seconds(pid: u32) -> anyhow::Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .with_context(|| format!("reading /proc/{pid}/stat"))?;
    // Fields after the parenthesised command name (which may hold spaces): state is field 3,
    // utime and stime fields 14 and 15.
    let rest = stat
        .rsplit_once(')')
        .map(|(_, r)| r)
        .context("malformed /proc stat")?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| -> anyhow::Result<f64> {
        Ok(fields
            .get(i - 3)
            .context("short /proc stat")?
            .parse::<u64>()? as f64)
    };
    // /proc reports in USER_HZ, which Linux fixes at 100 for user space.
    Ok((ticks(14)? + ticks(15)?) / 100.0)
}

async fn long_run(bins: &Path, dir: &Path) -> anyhow::Result<()> {
    let log = dir.join("long.jsonl");
    let (_sim, addr) = start_sim(bins, SPEEDUP, &log)?;
    let domain = format!("bench-waypoints-{}", std::process::id());
    let _vas = start_vas(bins, &addr, &domain)?;
    let g = Ground::open(&domain).await?;
    let wps = zigzag(WAYPOINTS);
    let started = Instant::now();
    g.fly(&wps).await?;
    // A vehicle that stopped early reports nothing more: bound the silence, then count.
    let mut last = started;
    let mut seen = 0usize;
    while seen < wps.len() {
        match g.reached.recv_timeout(Duration::from_secs(10)).await {
            Ok(_) => {
                seen += 1;
                last = Instant::now();
            }
            Err(e) => {
                eprintln!("waypoints: no progress after {seen} reached ({e})");
                break;
            }
        }
    }
    let wall = last.duration_since(started).as_secs_f64();
    let (skipped, repeated) = skipped_and_repeated(&wps, &log);
    let name = format!("vas.rolling_queue.waypoints_{WAYPOINTS}");
    metric(&format!("{name}.skipped"), skipped as f64, "waypoints");
    metric(&format!("{name}.repeated"), repeated as f64, "waypoints");
    metric(&format!("{name}.sim_seconds"), sim_seconds(&log), "s");
    metric(&format!("{name}.wall_seconds"), wall, "s");
    g.node.shutdown().await;
    Ok(())
}

async fn cpu_run(bins: &Path, dir: &Path) -> anyhow::Result<()> {
    let (_sim, addr) = start_sim(bins, 1.0, &dir.join("cpu.jsonl"))?;
    let domain = format!("bench-vas-cpu-{}", std::process::id());
    let vas = start_vas(bins, &addr, &domain)?;
    let g = Ground::open(&domain).await?;
    // Enough road for the window: about 20 s of driving.
    g.fly(&zigzag(40)).await?;
    let pid = vas.0.id();
    let before = cpu_seconds(pid)?;
    let t0 = Instant::now();
    tokio::time::sleep(CPU_WINDOW).await;
    let used = cpu_seconds(pid)? - before;
    metric(
        "vas.cpu_percent",
        100.0 * used / t0.elapsed().as_secs_f64(),
        "%",
    );
    g.node.shutdown().await;
    Ok(())
}

/// A valid rover plan of at least `bytes` bytes: waypoints on a lawn-mower grid 10 m apart,
/// each a `<fix>` and a TF `<leg>` to it.
fn large_plan(bytes: usize) -> String {
    use std::fmt::Write;
    // Each waypoint costs about 60 bytes of fix and 35 of leg.
    let n = bytes / 95 + 1;
    let (mut fixes, mut legs) = (String::new(), String::new());
    for i in 0..n {
        let (row, col) = (i / 100, i % 100);
        let col = if row % 2 == 0 { col } else { 99 - col };
        let lat = HOME.0 + row as f64 * 9.0e-5;
        let lon = HOME.1 + col as f64 * 1.2e-4;
        let _ = writeln!(
            fixes,
            r#"    <fix id="W{i}" lat="{lat:.6}" lon="{lon:.6}" alt="0"/>"#
        );
        let kind = if i == 0 { "IF" } else { "TF" };
        let _ = writeln!(legs, r#"    <leg type="{kind}" fix="W{i}"/>"#);
    }
    format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
         <flightPlan name=\"bench\" version=\"1\" vehicle=\"rover\" defaultSpeed=\"2\">\n\
         \x20 <fixes>\n{fixes}  </fixes>\n  <mission>\n{legs}  </mission>\n</flightPlan>\n"
    )
}

fn parse_run() -> anyhow::Result<()> {
    let src = large_plan(PARSE_BYTES);
    let mut best = Duration::MAX;
    for _ in 0..PARSE_RUNS {
        let t0 = Instant::now();
        let plan = flightplan::parse::parse_plan(&src)
            .map_err(|e| anyhow::anyhow!("the generated plan is refused: {e}"))?;
        best = best.min(t0.elapsed());
        anyhow::ensure!(
            plan.mission.len() > 10_000,
            "the generated plan is too small"
        );
    }
    metric("fpma.parse_1mb_ms", best.as_secs_f64() * 1000.0, "ms");
    Ok(())
}

fn load_run() -> anyhow::Result<()> {
    let src = large_plan(PARSE_BYTES);
    let vehicle = flightplan::vehicle::VehicleParams::rover();
    let mut best = Duration::MAX;
    for _ in 0..PARSE_RUNS {
        let t0 = Instant::now();
        let checked = flightplan::check::load(&src, &vehicle)
            .map_err(|e| anyhow::anyhow!("the generated plan is refused: {e}"))?;
        let ex = flightplan::exec::Executive::from_checked(checked);
        let geometry =
            flightplan::api::PlanGeometry::of(ex.plan(), &ex.nominal(), ex.version(), "bench.xml");
        let ahead = ex.next_waypoints(fpma::service::FpmaConfig::default().lookahead);
        best = best.min(t0.elapsed());
        anyhow::ensure!(
            geometry.total_points > 10_000 && !ahead.is_empty(),
            "the generated plan is too small"
        );
    }
    metric("fpma.load_1mb_ms", best.as_secs_f64() * 1000.0, "ms");
    Ok(())
}

#[path = "../services/vas/tests/common/mavsdk.rs"]
mod mavsdk_vehicle;

/// Waypoints of the conformance flights.
const CONFORMANCE_WAYPOINTS: usize = 50;

/// Flies [`CONFORMANCE_WAYPOINTS`] with the VAS at `endpoint`; returns the VAS's own backtrack
/// count (from its `queue` variable) once all are reported reached.
async fn conformance_flight(bins: &Path, addr: &str, tag: &str) -> anyhow::Result<u64> {
    let domain = format!("bench-{tag}-{}", std::process::id());
    let _vas = start_vas(bins, addr, &domain)?;
    let g = Ground::open(&domain).await?;
    let queue: VariableSubscriber<QueueStatus> = g
        .node
        .service("bench-queue")?
        .subscribe_variable("bench1/vas/queue")?;
    let wps = zigzag(CONFORMANCE_WAYPOINTS);
    g.fly(&wps).await?;
    let mut seen = 0usize;
    while seen < wps.len() {
        match g.reached.recv_timeout(STEP).await {
            Ok(_) => seen += 1,
            Err(e) => {
                eprintln!("{tag}: no progress after {seen} reached ({e})");
                break;
            }
        }
    }
    let _ = g.wait_state(FlightState::Parking).await;
    let mut backtracks = 0;
    while let Some(Ok(s)) = queue.try_recv() {
        backtracks = s.value.backtracks;
    }
    g.node.shutdown().await;
    Ok(backtracks)
}

async fn mavsdk_run(bins: &Path) -> anyhow::Result<()> {
    let Some(py) = tokio::task::spawn_blocking(mavsdk_vehicle::python).await? else {
        eprintln!("vas.conformance.mavsdk: skipped, python3 not found");
        return Ok(());
    };
    let mut vehicle = mavsdk_vehicle::MavsdkVehicle::start(&py, 2.0, STEP).await;
    let addr = format!("127.0.0.1:{}", vehicle.port);
    conformance_flight(bins, &addr, "mavsdk").await?;
    let plan: Vec<(f64, f64)> = zigzag(CONFORMANCE_WAYPOINTS)
        .iter()
        .map(|w| (w.lat, w.lon))
        .collect();
    let flown = mavsdk_vehicle::score(&vehicle.drain(), &plan);
    let name = format!("vas.conformance.mavsdk.waypoints_{CONFORMANCE_WAYPOINTS}");
    metric(
        &format!("{name}.skipped"),
        flown.skipped as f64,
        "waypoints",
    );
    metric(
        &format!("{name}.repeated"),
        flown.repeated as f64,
        "waypoints",
    );
    metric(
        &format!("{name}.backtracks"),
        flown.backtracks as f64,
        "backtracks",
    );
    vehicle.kill().await;
    Ok(())
}

/// Flies the conformance plan on mavsim `--autopilot <autopilot>` and prints
/// `vas.conformance.<tag>.waypoints_N.backtracks`: reaches of a point before one already
/// reached, or of a point not in the plan (mavsim's own log), plus those the VAS counted.
async fn profile_run(bins: &Path, dir: &Path, autopilot: &str, tag: &str) -> anyhow::Result<()> {
    let log = dir.join(format!("{tag}.jsonl"));
    let (_sim, addr) = start_sim_with(bins, 20.0, &log, &["--autopilot", autopilot])?;
    let vas_backtracks = conformance_flight(bins, &addr, tag).await?;
    // mavsim's reached items as the vehicle's reports.
    let reached: Vec<serde_json::Value> = log_events(&log, "item_reached")
        .into_iter()
        .map(|r| serde_json::json!({"event": "reached", "lat": r["lat"], "lon": r["lon"]}))
        .collect();
    let plan: Vec<(f64, f64)> = zigzag(CONFORMANCE_WAYPOINTS)
        .iter()
        .map(|w| (w.lat, w.lon))
        .collect();
    let flown = mavsdk_vehicle::score(&reached, &plan);
    let mut before = 0;
    let regressions = flown
        .reached
        .iter()
        .filter(|&&i| {
            let back = i < before;
            before = before.max(i);
            back
        })
        .count();
    metric(
        &format!("vas.conformance.{tag}.waypoints_{CONFORMANCE_WAYPOINTS}.backtracks"),
        (flown.backtracks + regressions) as f64 + vas_backtracks as f64,
        "backtracks",
    );
    Ok(())
}

async fn probe_run(bins: &Path, dir: &Path) -> anyhow::Result<()> {
    use vas::mavlink_cm::{ManagerConfig, MavlinkManager};
    let (_sim, addr) =
        start_sim_with(bins, 1.0, &dir.join("probe.jsonl"), &["--autopilot", "px4"])?;
    let mgr = MavlinkManager::open(&format!("udpout:{addr}"), ManagerConfig::default())
        .await
        .context("opening the manager")?;
    mgr.wait_connected(STEP).await.context("mavsim px4")?;
    let t0 = Instant::now();
    let supported = mgr.probe_partial_writes().await.context("probing")?;
    let ms = t0.elapsed().as_secs_f64() * 1000.0;
    anyhow::ensure!(!supported, "the px4 profile answered a partial write");
    metric("vas.partial_write_probe_ms", ms, "ms");
    mgr.shutdown().await;
    Ok(())
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    // `cargo bench` passes `--bench`; other arguments select figures by substring.
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |figure: &str| filters.is_empty() || filters.iter().any(|f| figure.contains(f));
    if wanted("fpma.parse_1mb_ms") {
        parse_run()?;
    }
    if wanted("fpma.load_1mb_ms") {
        load_run()?;
    }
    let (queue, cpu) = (wanted("vas.rolling_queue"), wanted("vas.cpu_percent"));
    if queue || cpu {
        let bins = build_bins()?;
        let dir = tempfile::tempdir()?;
        if queue {
            long_run(&bins, dir.path()).await?;
        }
        if cpu {
            cpu_run(&bins, dir.path()).await?;
        }
    }
    let (mavsdk, px4, resetting, probe) = (
        wanted("vas.conformance.mavsdk"),
        wanted("vas.conformance.px4_profile"),
        wanted("vas.conformance.reset_on_upload"),
        wanted("vas.partial_write_probe_ms"),
    );
    if mavsdk || px4 || resetting || probe {
        let bins = build_bins()?;
        let dir = tempfile::tempdir()?;
        if mavsdk {
            mavsdk_run(&bins).await?;
        }
        if px4 {
            profile_run(&bins, dir.path(), "px4", "px4_profile").await?;
        }
        if resetting {
            profile_run(&bins, dir.path(), "ardupilot-resetting", "reset_on_upload").await?;
        }
        if probe {
            probe_run(&bins, dir.path()).await?;
        }
    }
    Ok(())
}

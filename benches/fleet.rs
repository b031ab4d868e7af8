//! `cargo bench --bench fleet`: ten vehicles on one `usal run` on this machine, as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`.
//!
//! Real processes, as a user runs them: a generated mission of [`VEHICLES`] nodes, each with
//! its mavsim (real time, no speed-up), its VAS (10 Hz telemetry) and its FPMa, started by the
//! release `usal run` (which builds the service binaries it misses). Every node's Ethernet link
//! uses a multicast port of this run only, so the discovery group carries nothing but this
//! fleet's traffic. Once every service has started and [`SETTLE`] has passed (the Hellos and
//! declarations of start-up are over), the fleet is idle (no plan) and is measured for
//! [`WINDOW`]:
//!
//! - `fleet.ten_vehicles.discovery_bytes_per_s`: UDP payload bytes per second on the
//!   discovery multicast group (Hello, heartbeat, Bye of every node together), counted by a
//!   socket of this bench that joins the group. Steady-state declarations travel unicast
//!   only when something changes; idle, there are none.
//! - `fleet.ten_vehicles.cpu_percent`: CPU time (user + system, from `/proc/<pid>/stat`) of
//!   `usal` and every process below it, over the window's real time, in percent of one core.
//!
//! The per-program split of the CPU time goes to stderr, to show where the cost is.
//!
//! The two-vehicle search: `usal run config/missions/search.xml --until-complete --speedup 10`
//! with the release binaries, read from its `fleet_plan_summary`:
//!
//! - `fleet.search.detections_visited_ratio`: detections visited over the points of interest
//!   the mission placed (`config/search/pois.txt`), so a point never detected counts as
//!   missed (1.0 wanted);
//! - `fleet.search.completed`: 1 when the run ended 0 with the fleet plan done;
//! - `fleet.separation.violations`: times the two rovers came closer than the minimum
//!   distance (0 wanted).

use std::collections::{BTreeMap, HashMap};
use std::io::BufRead;
use std::net::{Ipv4Addr, SocketAddrV4, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};

/// Vehicles of the fleet.
const VEHICLES: usize = 10;
/// The discovery group (the default one; the port is this run's own).
const GROUP: Ipv4Addr = Ipv4Addr::new(239, 255, 77, 1);
/// From the last service started to the start of the measurement.
const SETTLE: Duration = Duration::from_secs(10);
/// The measurement window.
const WINDOW: Duration = Duration::from_secs(30);
/// Bound on the fleet's start (the launcher may build the service binaries first).
const START: Duration = Duration::from_secs(900);
/// The kernel's clock ticks per second in `/proc` (USER_HZ, fixed at 100 for user space).
const TICKS: f64 = 100.0;

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

/// `usal run`, stopped (SIGTERM, then SIGKILL) when dropped.
struct Launcher(Child);

impl Drop for Launcher {
    fn drop(&mut self) {
        // Already exited (and waited for): nothing to stop.
        if let Ok(Some(_)) = self.0.try_wait() {
            return;
        }
        let pid = self.0.id().to_string();
        let _ = Command::new("kill").args(["-TERM", &pid]).status();
        let deadline = Instant::now() + Duration::from_secs(15);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A socket in the discovery group counting the bytes and datagrams it sees.
struct Sniffer {
    port: u16,
    bytes: Arc<AtomicU64>,
    packets: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
}

impl Sniffer {
    /// Binds the group on a port of the system's choice (shared with the nodes, which bind it
    /// with SO_REUSEADDR too) and joins it on the loopback interface.
    fn start() -> anyhow::Result<Sniffer> {
        use socket2::{Domain, Protocol, Socket, Type};
        let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))
            .context("sniffer socket")?;
        s.set_reuse_address(true).context("SO_REUSEADDR")?;
        s.bind(&SocketAddrV4::new(GROUP, 0).into())
            .context("binding the discovery group")?;
        s.join_multicast_v4(&GROUP, &Ipv4Addr::LOCALHOST)
            .context("joining the discovery group on 127.0.0.1")?;
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .context("read timeout")?;
        let sock: UdpSocket = s.into();
        let port = sock.local_addr().context("sniffer address")?.port();
        let (bytes, packets, stop) = (
            Arc::new(AtomicU64::new(0)),
            Arc::new(AtomicU64::new(0)),
            Arc::new(AtomicBool::new(false)),
        );
        let (b, p, st) = (bytes.clone(), packets.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut buf = vec![0u8; 65_536];
            while !st.load(Ordering::Relaxed) {
                if let Ok(n) = sock.recv(&mut buf) {
                    b.fetch_add(n as u64, Ordering::Relaxed);
                    p.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
        Ok(Sniffer {
            port,
            bytes,
            packets,
            stop,
        })
    }

    fn counts(&self) -> (u64, u64) {
        (
            self.bytes.load(Ordering::Relaxed),
            self.packets.load(Ordering::Relaxed),
        )
    }
}

impl Drop for Sniffer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Writes the fleet's network file and mission into `dir`; returns the mission's path.
fn write_mission(dir: &Path, port: u16) -> anyhow::Result<PathBuf> {
    let mut mission = String::from("<?xml version=\"1.0\"?>\n<mission name=\"fleet-bench\">\n");
    for i in 1..=VEHICLES {
        let net = dir.join(format!("air{i}.xml"));
        std::fs::write(
            &net,
            format!(
                "<network node=\"air{i}\">\n  <ethernet bind=\"127.0.0.1:0\" multicast=\"{GROUP}:{port}\" interface=\"127.0.0.1\"/>\n</network>\n"
            ),
        )
        .with_context(|| format!("writing {}", net.display()))?;
        // Homes 100 m apart along a parallel.
        let lon = 1.987 + 0.0012 * i as f64;
        mission += &format!(
            "  <node name=\"air{i}\" namespace=\"rover{i}\" network=\"air{i}.xml\">\n    <mavsim vehicle=\"rover\" home=\"41.27500,{lon:.5},0\" speedup=\"1\"/>\n    <vas vehicle=\"rover\" queueSize=\"5\" telemetryHz=\"10\"/>\n    <fpma vehicle=\"rover\" lookahead=\"8\"/>\n  </node>\n"
        );
    }
    mission += "</mission>\n";
    let path = dir.join("fleet.xml");
    std::fs::write(&path, mission).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// `(ppid, program, utime + stime in ticks)` of every process now.
fn processes() -> HashMap<u32, (u32, String, u64)> {
    let mut out = HashMap::new();
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return out;
    };
    for e in dir.flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // pid (comm) state ppid ... utime stime: fields 4, 14 and 15; comm may hold spaces.
        let (Some(open), Some(close)) = (stat.find('('), stat.rfind(") ")) else {
            continue;
        };
        let comm = stat[open + 1..close].to_owned();
        let rest: Vec<&str> = stat[close + 2..].split(' ').collect();
        let field = |i: usize| rest.get(i).and_then(|v| v.parse::<u64>().ok());
        if let (Some(ppid), Some(u), Some(s)) = (field(1), field(11), field(12)) {
            out.insert(pid, (ppid as u32, comm, u + s));
        }
    }
    out
}

/// CPU ticks of `root` and its descendants, by pid, with their programs.
fn tree_ticks(root: u32) -> HashMap<u32, (String, u64)> {
    let all = processes();
    let mut out = HashMap::new();
    let mut todo = vec![root];
    while let Some(p) = todo.pop() {
        if let Some((_, comm, t)) = all.get(&p) {
            out.insert(p, (comm.clone(), *t));
        }
        todo.extend(
            all.iter()
                .filter(|(_, (pp, _, _))| *pp == p)
                .map(|(c, _)| *c),
        );
    }
    out
}

/// Waits for `n` `started` events on the launcher's JSON output.
fn wait_started(lines: &mpsc::Receiver<serde_json::Value>, n: usize) -> anyhow::Result<()> {
    let deadline = Instant::now() + START;
    let mut started = 0;
    while started < n {
        let left = deadline.saturating_duration_since(Instant::now());
        match lines.recv_timeout(left) {
            Ok(v) if v["event"] == "started" => started += 1,
            Ok(_) => {}
            Err(_) => bail!("only {started} of {n} services started within {START:?}"),
        }
    }
    Ok(())
}

fn run() -> anyhow::Result<()> {
    let dir = tempfile::tempdir().context("temporary directory")?;
    let sniffer = Sniffer::start()?;
    let mission = write_mission(dir.path(), sniffer.port)?;
    let log = std::fs::File::create(dir.path().join("usal.log")).context("usal log")?;
    let mut child = Command::new(env!("CARGO_BIN_EXE_usal"))
        .arg("--json")
        .arg("run")
        .arg(&mission)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .context("starting usal run")?;
    let out = child.stdout.take().context("usal stdout")?;
    let launcher = Launcher(child);
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            if let Ok(v) = serde_json::from_str(&line) {
                if tx.send(v).is_err() {
                    break;
                }
            }
        }
    });
    let started = wait_started(&rx, VEHICLES * 3);
    if let Err(e) = started {
        let log = std::fs::read_to_string(dir.path().join("usal.log")).unwrap_or_default();
        let tail = &log[log.len().saturating_sub(3000)..];
        bail!("{e:#}\nusal's log ends with:\n{tail}");
    }
    std::thread::sleep(SETTLE);

    let root = launcher.0.id();
    let before = tree_ticks(root);
    let (b0, p0) = sniffer.counts();
    let t0 = Instant::now();
    std::thread::sleep(WINDOW);
    let (b1, p1) = sniffer.counts();
    let after = tree_ticks(root);
    let secs = t0.elapsed().as_secs_f64();

    // Processes alive at both ends (a restarted one would count from its start).
    let mut by_program: BTreeMap<String, (usize, f64)> = BTreeMap::new();
    for (pid, (comm, t1)) in &after {
        let t0 = before.get(pid).map_or(0, |(_, t)| *t);
        let e = by_program.entry(comm.clone()).or_default();
        e.0 += 1;
        e.1 += t1.saturating_sub(t0) as f64 / TICKS / secs * 100.0;
    }
    let cpu: f64 = by_program.values().map(|(_, c)| c).sum();
    let services = after.len().saturating_sub(1);
    if services < VEHICLES * 3 {
        bail!("only {services} services running at the end of the window");
    }
    metric(
        "fleet.ten_vehicles.discovery_bytes_per_s",
        (b1 - b0) as f64 / secs,
        "B/s",
    );
    metric("fleet.ten_vehicles.cpu_percent", cpu, "%");
    eprintln!(
        "fleet: {} discovery datagrams/s, {:.1} B each; CPU by program (processes, % of one core):",
        (p1 - p0) as f64 / secs,
        (b1 - b0) as f64 / (p1 - p0).max(1) as f64
    );
    for (prog, (n, c)) in &by_program {
        eprintln!("  {prog:<12} {n:>3} {c:>6.1}");
    }
    drop(launcher);
    Ok(())
}

/// The search mission, once; prints its three figures.
fn run_search() -> anyhow::Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let placed = std::fs::read_to_string(root.join("config/search/pois.txt"))
        .context("reading config/search/pois.txt")?
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .count();
    let dir = tempfile::tempdir().context("temporary directory")?;
    let log = std::fs::File::create(dir.path().join("usal.log")).context("usal log")?;
    let mut child = Command::new(env!("CARGO_BIN_EXE_usal"))
        .args([
            "--json",
            "run",
            "config/missions/search.xml",
            "--until-complete",
        ])
        .args(["--speedup", "10", "--timeout-s", "600"])
        .current_dir(root)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .context("starting usal run")?;
    let out = child.stdout.take().context("usal stdout")?;
    let mut launcher = Launcher(child);
    let mut summary = None;
    for line in std::io::BufReader::new(out).lines() {
        let Ok(line) = line else { break };
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
            if v["event"] == "fleet_plan_summary" {
                summary = Some(v);
            }
        }
    }
    // stdout closed: usal is exiting (its --timeout-s bounds the run).
    let status = launcher.0.wait().context("waiting for usal")?;
    let Some(v) = summary else {
        let log = std::fs::read_to_string(dir.path().join("usal.log")).unwrap_or_default();
        let tail = &log[log.len().saturating_sub(3000)..];
        bail!("the search mission printed no summary ({status})\nusal's log ends with:\n{tail}");
    };
    let s = &v["summary"];
    let visited = s["detections"]
        .as_array()
        .map_or(0, |d| d.iter().filter(|d| d["visited"].is_array()).count());
    metric(
        "fleet.search.detections_visited_ratio",
        visited as f64 / placed.max(1) as f64,
        "ratio",
    );
    let completed = status.success() && s["done"] == true;
    metric(
        "fleet.search.completed",
        f64::from(u8::from(completed)),
        "bool",
    );
    metric(
        "fleet.separation.violations",
        s["separation"]["violations"].as_f64().unwrap_or(f64::NAN),
        "count",
    );
    eprintln!(
        "fleet search: {visited} of {placed} points visited in {:.1} s, {} separation holds, closest {:.1} m",
        s["elapsed_s"].as_f64().unwrap_or(f64::NAN),
        s["separation"]["holds"],
        s["separation"]["closest_m"].as_f64().unwrap_or(f64::NAN)
    );
    Ok(())
}

fn main() {
    // `cargo bench` passes `--bench`; other arguments select figures by substring.
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |names: &[&str]| {
        filters.is_empty() || names.iter().any(|n| filters.iter().any(|f| n.contains(f)))
    };
    let mut failed = false;
    if wanted(&[
        "fleet.search.detections_visited_ratio",
        "fleet.search.completed",
        "fleet.separation.violations",
    ]) {
        if let Err(e) = run_search() {
            eprintln!("fleet bench (search): {e:#}");
            failed = true;
        }
    }
    if wanted(&[
        "fleet.ten_vehicles.discovery_bytes_per_s",
        "fleet.ten_vehicles.cpu_percent",
    ]) {
        if let Err(e) = run() {
            eprintln!("fleet bench: {e:#}");
            failed = true;
        }
    }
    if failed {
        std::process::exit(1);
    }
}

//! The runner: `cargo run --release --manifest-path benches/peers/Cargo.toml [-- --quick]
//! [--rounds N] [--baud B] [--only SUBSTRING[,SUBSTRING...]] [--no-build]`.
//!
//! Runs every case of [`cases`] as two processes of the same peer binary (responder first, then
//! initiator), round after round so each middleware sees the same machine state, and prints
//! JSON lines `{"metric": ..., "value": ..., "unit": ...}`:
//!
//! - `peers.<figure>.<impl>`: the median over the rounds (round trip p50 in µs, one-way
//!   messages/s received, MB/s for the 1 MiB `blob1m`, summed over the subscriber processes of
//!   a `fanoutN` figure, peak RSS in KiB), with `.p99` (round trips), `.delivered` (share of
//!   sent messages received), `.anon` (idle: the anonymous memory resident at the end, in KiB:
//!   what the process holds privately, without the code and libraries it maps from files),
//!   `.spread_pct` ((max − min) / median of the rounds) and `.runs`; `rtt64_under_load` (64 B
//!   round trips while the initiator streams 4 MiB frames to the responder over the same link:
//!   a marea call, Zenoh's put at `RealTime` against a `DataLow` stream) adds `.idle_p99` (the
//!   same process's round trips before the stream starts), `.p99_to_idle` (its p99 over that,
//!   per round) and `.bulk_mb_s` (what the stream moved meanwhile);
//! - the same-run ratios (`peers.event64.marea_udp_to_zenoh_tcp`, ...): computed within each
//!   round, median over the rounds, with their own `.spread_pct`.
//!
//! Each marea case runs marea built as a node for that link would be, which matters most for the
//! idle RSS: the UDP cases run `peer-marea-udp` (marea's feature `udp` alone: no iceoryx2, no
//! serial link), the shm cases `peer-marea-shm` (feature `shm` alone: no UDP link either), the
//! serial cases, `event64_default_api` (the API and runtime services use) and `rtt64_under_load` `peer-marea`
//! (marea's default features). All come from one source file (`src/bin/peer-marea.rs`) and
//! [`build_peers`] builds them in separate cargo invocations.
//!
//! Every wait is bounded and every child is killed when its case ends.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader, Lines};
use tokio::process::{Child, ChildStdin, ChildStdout, Command};

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    /// Round trip: `pong` then `ping`.
    Rtt,
    /// One-way rate: `sub` then `pub`.
    Rate,
    /// Peak RSS of an idle node beside an idle partner.
    Idle,
}

#[derive(Clone)]
struct Case {
    /// `rtt64`, `rtt64_pinned`, `event64`, `event1k`, `idle_rss_kib`, `rtt64_serial115200`...
    figure: String,
    /// `raw_udp`, `zenoh_tcp`, `iceoryx2`, `marea_udp`, `marea_udp_var`, `marea_shm`,
    /// `marea_serial`.
    imp: &'static str,
    kind: Kind,
    /// The peer binary: `peer-udp`, `peer-zenoh`, `peer-iceoryx2`, `peer-marea` (serial),
    /// `peer-marea-udp` (marea over UDP, built without the `shm` and `serial` features) or
    /// `peer-marea-shm` (marea over shm, built with `shm` alone).
    bin: &'static str,
    size: usize,
    /// Round trips, or seconds of publishing, or seconds idle.
    param: f64,
    /// marea's link kind: `udp`, `shm`, `serial`.
    link: Option<&'static str>,
    /// The role suffix: `-event` or `-var` (marea's pub/sub), `-api` (marea's default API),
    /// `-load` (round trips under a bulk stream), `-blob` (events written in place: `loan`).
    suffix: &'static str,
    pinned: bool,
    /// Subscriber processes of a rate case (a fan-out when more than one).
    subs: usize,
}

struct Opts {
    no_build: bool,
    rounds: usize,
    quick: bool,
    baud: u32,
    only: Option<String>,
}

const USAGE: &str =
    "usage: peers [--quick] [--rounds N] [--baud B] [--only SUBSTRING[,SUBSTRING...]] [--no-build]";

/// The options, or `None` when asked for help (the usage is printed).
fn opts() -> anyhow::Result<Option<Opts>> {
    let mut o = Opts {
        no_build: false,
        rounds: 3,
        quick: false,
        baud: 115_200,
        only: None,
    };
    let mut it = std::env::args().skip(1);
    let mut rounds = None;
    while let Some(a) = it.next() {
        match a.as_str() {
            "--quick" => o.quick = true,
            "--no-build" => o.no_build = true,
            "--rounds" => rounds = Some(it.next().context("--rounds N")?.parse()?),
            "--baud" => o.baud = it.next().context("--baud B")?.parse()?,
            "--only" => o.only = Some(it.next().context("--only SUBSTRING")?),
            "--bench" => {} // cargo bench passes this
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(None);
            }
            other => bail!("unknown argument {other:?}\n{USAGE}"),
        }
    }
    o.rounds = rounds.unwrap_or(if o.quick { 1 } else { 3 });
    Ok(Some(o))
}

fn cases(o: &Opts) -> Vec<Case> {
    let (n_rtt, secs, idle) = if o.quick {
        (1000.0, 0.5, 1.0)
    } else {
        (5000.0, 2.0, 2.0)
    };
    let base = |figure: &str, imp, kind, bin, size, param| Case {
        figure: figure.to_owned(),
        imp,
        kind,
        bin,
        size,
        param,
        link: None,
        suffix: "",
        pinned: false,
        subs: 1,
    };
    let marea = |mut c: Case, link, suffix| {
        c.link = Some(link);
        c.suffix = suffix;
        c
    };
    let mut v = Vec::new();
    for pinned in [false, true] {
        let fig = if pinned { "rtt64_pinned" } else { "rtt64" };
        let mut row = vec![
            base(fig, "raw_udp", Kind::Rtt, "peer-udp", 64, n_rtt),
            base(fig, "zenoh_tcp", Kind::Rtt, "peer-zenoh", 64, n_rtt),
            base(fig, "iceoryx2", Kind::Rtt, "peer-iceoryx2", 64, n_rtt),
            marea(
                base(fig, "marea_udp", Kind::Rtt, "peer-marea-udp", 64, n_rtt),
                "udp",
                "",
            ),
            marea(
                base(fig, "marea_shm", Kind::Rtt, "peer-marea-shm", 64, n_rtt),
                "shm",
                "",
            ),
        ];
        for c in &mut row {
            c.pinned = pinned;
        }
        v.extend(row);
    }
    for (fig, size) in [("event64", 64), ("event1k", 1024)] {
        v.extend([
            base(fig, "raw_udp", Kind::Rate, "peer-udp", size, secs),
            base(fig, "zenoh_tcp", Kind::Rate, "peer-zenoh", size, secs),
            base(fig, "iceoryx2", Kind::Rate, "peer-iceoryx2", size, secs),
            marea(
                base(fig, "marea_udp", Kind::Rate, "peer-marea-udp", size, secs),
                "udp",
                "-event",
            ),
            marea(
                base(fig, "marea_shm", Kind::Rate, "peer-marea-shm", size, secs),
                "shm",
                "-event",
            ),
            marea(
                base(
                    fig,
                    "marea_udp_var",
                    Kind::Rate,
                    "peer-marea-udp",
                    size,
                    secs,
                ),
                "udp",
                "-var",
            ),
        ]);
    }
    // Large payloads: 1 MiB events, reliable (MB/s received).
    let blob_secs = if o.quick { 1.0 } else { 3.0 };
    let fig = "blob1m";
    v.extend([
        base(
            fig,
            "zenoh_tcp",
            Kind::Rate,
            "peer-zenoh",
            1 << 20,
            blob_secs,
        ),
        marea(
            base(
                fig,
                "marea_udp",
                Kind::Rate,
                "peer-marea-udp",
                1 << 20,
                blob_secs,
            ),
            "udp",
            "-event",
        ),
    ]);
    // Camera frames on one host: 4 MiB events, each written once into shared memory (marea's
    // loan, iceoryx2's `loan_slice_uninit` + `write_from_slice`), received without a copy.
    let fig = "blob4m";
    v.extend([
        base(
            fig,
            "iceoryx2",
            Kind::Rate,
            "peer-iceoryx2",
            4 << 20,
            blob_secs,
        ),
        marea(
            base(
                fig,
                "marea_shm",
                Kind::Rate,
                "peer-marea-shm",
                4 << 20,
                blob_secs,
            ),
            "shm",
            "-blob",
        ),
    ]);
    // The API services use: `raise_nowait` and `recv().await` on the multi-thread runtime,
    // marea's default features (compared with Zenoh's `event64`).
    v.push(marea(
        base(
            "event64_default_api",
            "marea_udp",
            Kind::Rate,
            "peer-marea",
            64,
            secs,
        ),
        "udp",
        "-api",
    ));
    // Fan-out: one publisher, N subscriber processes (events/s summed over them).
    for n in [10, 50] {
        let fig = format!("fanout{n}.event64");
        let mut row = [
            base(&fig, "zenoh_tcp", Kind::Rate, "peer-zenoh", 64, secs),
            // Zenoh as beyond one LAN: clients of a router (TCP on loopback).
            Case {
                suffix: "-client",
                ..base(&fig, "zenoh_router", Kind::Rate, "peer-zenoh", 64, secs)
            },
            marea(
                base(&fig, "marea_udp", Kind::Rate, "peer-marea-udp", 64, secs),
                "udp",
                "-event",
            ),
            // One host: every subscriber a process on shared memory.
            base(&fig, "iceoryx2", Kind::Rate, "peer-iceoryx2", 64, secs),
            marea(
                base(&fig, "marea_shm", Kind::Rate, "peer-marea-shm", 64, secs),
                "shm",
                "-event",
            ),
        ];
        for c in &mut row {
            c.subs = n;
        }
        v.extend(row);
    }
    // Round trips under a bulk stream (4 MiB frames), against the same processes' idle ones.
    let fig = "rtt64_under_load";
    let n_load = if o.quick { 300.0 } else { 2000.0 };
    v.extend([
        Case {
            suffix: "-load",
            ..base(fig, "zenoh_tcp", Kind::Rtt, "peer-zenoh", 64, n_load)
        },
        marea(
            base(fig, "marea_udp", Kind::Rtt, "peer-marea", 64, n_load),
            "udp",
            "-load",
        ),
    ]);
    let fig = "idle_rss_kib";
    v.extend([
        base(fig, "raw_udp", Kind::Idle, "peer-udp", 64, idle),
        base(fig, "zenoh_tcp", Kind::Idle, "peer-zenoh", 64, idle),
        base(fig, "iceoryx2", Kind::Idle, "peer-iceoryx2", 64, idle),
        marea(
            base(fig, "marea_udp", Kind::Idle, "peer-marea-udp", 64, idle),
            "udp",
            "",
        ),
        marea(
            base(fig, "marea_shm", Kind::Idle, "peer-marea-shm", 64, idle),
            "shm",
            "",
        ),
    ]);
    let b = o.baud;
    let serial_rtt = if o.quick { 30.0 } else { 100.0 };
    v.extend([
        marea(
            base(
                &format!("rtt64_serial{b}"),
                "marea_serial",
                Kind::Rtt,
                "peer-marea",
                64,
                serial_rtt,
            ),
            "serial",
            "",
        ),
        marea(
            base(
                &format!("event64_serial{b}"),
                "marea_serial",
                Kind::Rate,
                "peer-marea",
                64,
                secs.max(2.0),
            ),
            "serial",
            "-event",
        ),
    ]);
    if let Some(only) = &o.only {
        v.retain(|c| {
            let name = format!("{}.{}", c.figure, c.imp);
            only.split(',').any(|o| name.contains(o))
        });
    }
    v
}

/// `cargo run` builds only the runner: build the peer binaries beside it (same profile), so a
/// run never measures stale ones. `--no-build` skips this.
///
/// One cargo invocation per package: cargo unifies a dependency's features across the packages
/// one invocation builds, so `peer-marea-udp` built beside `peer-marea` would get marea's `shm`
/// back (and `peer-marea-shm` its `serial` and `udp`).
fn build_peers(o: &Opts) -> anyhow::Result<()> {
    if o.no_build {
        return Ok(());
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml");
    for package in ["peers", "peer-marea-udp", "peer-marea-shm"] {
        let mut cmd = std::process::Command::new(&cargo);
        cmd.args([
            "build",
            "--bins",
            "--manifest-path",
            manifest,
            "-p",
            package,
        ]);
        if !cfg!(debug_assertions) {
            cmd.arg("--release");
        }
        let status = cmd
            .status()
            .with_context(|| format!("cargo build of the peer binaries of {package}"))?;
        if !status.success() {
            bail!("cargo build of the peer binaries of {package} failed ({status})");
        }
    }
    Ok(())
}

/// One child process and its stdout lines.
struct Peer {
    what: String,
    child: Child,
    stdin: Option<ChildStdin>,
    lines: Lines<BufReader<ChildStdout>>,
}

impl Peer {
    fn spawn(case: &Case, role: &str, key: &str, link: &Option<String>) -> anyhow::Result<Peer> {
        Self::spawn_as(case, role, key, link, 0)
    }

    /// [`Self::spawn`] for subscriber `index` of a fan-out (its name in the failure messages).
    fn spawn_as(
        case: &Case,
        role: &str,
        key: &str,
        link: &Option<String>,
        index: usize,
    ) -> anyhow::Result<Peer> {
        let exe = bin_dir()?.join(case.bin);
        let mut args: Vec<String> = vec![
            role.to_owned(),
            case.size.to_string(),
            key.to_owned(),
            case.param.to_string(),
        ];
        if let Some(l) = link {
            args.push(l.clone());
        }
        let mut cmd = if case.pinned {
            let mut c = Command::new("taskset");
            c.arg("-c").arg("0").arg(&exe);
            c
        } else {
            Command::new(&exe)
        };
        cmd.args(&args)
            .env("PEERS_SUBSCRIBERS", case.subs.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true);
        let mut child = cmd
            .spawn()
            .with_context(|| format!("start {} {}", exe.display(), args.join(" ")))?;
        let stdin = child.stdin.take();
        let stdout = child.stdout.take().context("child without stdout")?;
        Ok(Peer {
            what: if case.subs > 1 {
                format!("{} {role} #{index}", case.bin)
            } else {
                format!("{} {role}", case.bin)
            },
            child,
            stdin,
            lines: BufReader::new(stdout).lines(),
        })
    }

    /// The next line that starts with `word`, its remaining words.
    async fn expect(&mut self, word: &str, within: Duration) -> anyhow::Result<Vec<String>> {
        let read = async {
            loop {
                let line = self
                    .lines
                    .next_line()
                    .await?
                    .ok_or_else(|| anyhow!("{} ended before saying {word:?}", self.what))?;
                let mut w = line.split_whitespace();
                if w.next() == Some(word) {
                    return Ok::<_, anyhow::Error>(w.map(str::to_owned).collect());
                }
            }
        };
        tokio::time::timeout(within, read)
            .await
            .map_err(|_| anyhow!("{}: no {word:?} within {within:?}", self.what))?
    }

    async fn say(&mut self, line: &str) -> anyhow::Result<()> {
        let stdin = self.stdin.as_mut().context("stdin already closed")?;
        stdin.write_all(format!("{line}\n").as_bytes()).await?;
        stdin.flush().await?;
        Ok(())
    }

    /// Closes its stdin (the peer leaves), waits a little, then kills it.
    async fn end(mut self) {
        drop(self.stdin.take());
        if tokio::time::timeout(Duration::from_secs(5), self.child.wait())
            .await
            .is_err()
        {
            let _ = self.child.kill().await;
        }
    }

    fn pid(&self) -> Option<u32> {
        self.child.id()
    }
}

fn bin_dir() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe()?;
    Ok(exe
        .parent()
        .context("runner has no directory")?
        .to_path_buf())
}

fn free_port(udp: bool) -> anyhow::Result<u16> {
    Ok(if udp {
        std::net::UdpSocket::bind("127.0.0.1:0")?
            .local_addr()?
            .port()
    } else {
        std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port()
    })
}

/// A figure in KiB of `/proc/PID/status` (`field` with its colon, e.g. `VmHWM:`).
fn status_kib(pid: u32, field: &str) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Bridges two pty masters (a null-modem cable); returns the slaves' paths and what to keep.
struct PtyCable {
    paths: (String, String),
    _slaves: (tokio_serial::SerialStream, tokio_serial::SerialStream),
    task: tokio::task::JoinHandle<()>,
}

impl PtyCable {
    fn new() -> anyhow::Result<PtyCable> {
        use tokio_serial::SerialPort;
        let (m1, s1) = tokio_serial::SerialStream::pair().context("pty pair")?;
        let (m2, s2) = tokio_serial::SerialStream::pair().context("pty pair")?;
        let p1 = s1.name().context("pty without a path")?;
        let p2 = s2.name().context("pty without a path")?;
        let task = tokio::spawn(async move {
            let (mut m1, mut m2) = (m1, m2);
            let _ = tokio::io::copy_bidirectional(&mut m1, &mut m2).await;
        });
        Ok(PtyCable {
            paths: (p1, p2),
            _slaves: (s1, s2),
            task,
        })
    }
}

impl Drop for PtyCable {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// What one run of a case measured.
#[derive(Default, Clone, Copy)]
struct Sample {
    value: f64,
    p99: Option<f64>,
    delivered: Option<f64>,
    /// Idle: the anonymous (private) memory resident at the end, in KiB.
    anon_kib: Option<f64>,
    /// Under load: the p99 of the same process's round trips before the load, in µs.
    idle_p99: Option<f64>,
    /// Under load: what the bulk stream moved during the timed round trips, in MB/s.
    bulk_mb_s: Option<f64>,
}

async fn run_case(case: &Case, key: &str, baud: u32) -> anyhow::Result<Sample> {
    let mut cable = None;
    let (key, links) = match (case.bin, case.link) {
        ("peer-zenoh", _) => (format!("{}:{key}", free_port(false)?), (None, None)),
        (_, Some("udp")) => {
            let l = Some(format!("udp:{}", free_port(true)?));
            (key.to_owned(), (l.clone(), l))
        }
        (_, Some("shm")) => (key.to_owned(), (Some("shm".into()), Some("shm".into()))),
        (_, Some("serial")) => {
            let c = PtyCable::new()?;
            let l = (
                Some(format!("serial:{}:{baud}", c.paths.0)),
                Some(format!("serial:{}:{baud}", c.paths.1)),
            );
            cable = Some(c);
            (key.to_owned(), l)
        }
        _ => (key.to_owned(), (None, None)),
    };
    let start = Duration::from_secs(30);
    let out = match case.kind {
        Kind::Rtt => {
            let mut pong = Peer::spawn(case, &format!("pong{}", case.suffix), &key, &links.0)?;
            let info = pong.expect("ready", start).await;
            let ikey = info_key(case, &key, info?);
            let mut ping = Peer::spawn(case, &format!("ping{}", case.suffix), &ikey, &links.1)?;
            let r = async {
                ping.expect("ready", start).await?;
                let w = ping.expect("result", Duration::from_secs(110)).await?;
                let under_load = (case.suffix == "-load")
                    .then(|| Ok::<_, anyhow::Error>((word(&w, 3)?, word(&w, 4)?)))
                    .transpose()?;
                Ok::<_, anyhow::Error>(Sample {
                    value: word(&w, 0)?,
                    p99: Some(word(&w, 1)?),
                    idle_p99: under_load.map(|(idle, _)| idle),
                    bulk_mb_s: under_load.map(|(_, mb)| mb),
                    ..Sample::default()
                })
            }
            .await;
            ping.end().await;
            pong.end().await;
            r
        }
        Kind::Rate => {
            let (sub_keys, pub_key) = fanout_keys(case, &key)?;
            // Zenoh through a router: the router first, on the port every other one joins.
            let router = match (case.suffix, &pub_key) {
                ("-client", Some(k)) => {
                    let mut r = Peer::spawn(case, "router", k, &links.0)?;
                    r.expect("ready", start).await?;
                    Some(r)
                }
                _ => None,
            };
            let role = format!("sub{}", case.suffix);
            let mut subs = Vec::with_capacity(sub_keys.len());
            let mut infos = Vec::new();
            for (i, k) in sub_keys.iter().enumerate() {
                let mut sub = Peer::spawn_as(case, &role, k, &links.0, i)?;
                let info = sub.expect("ready", start).await;
                subs.push(sub);
                infos.push(info?);
            }
            let ikey = match pub_key {
                Some(k) => k,
                None => info_key(case, &key, infos.swap_remove(0)),
            };
            let mut publ = Peer::spawn(case, &format!("pub{}", case.suffix), &ikey, &links.1)?;
            let r = async {
                publ.expect("ready", start).await?;
                let w = publ
                    .expect("result", Duration::from_secs_f64(case.param + 60.0))
                    .await?;
                let sent = word(&w, 0)?;
                let (mut rate, mut count) = (0.0, 0.0);
                for sub in &mut subs {
                    sub.say(&format!("stop {sent}")).await?;
                }
                for sub in &mut subs {
                    let w = sub.expect("result", Duration::from_secs(60)).await?;
                    let (n, span) = (word(&w, 0)?, word(&w, 1)?);
                    if span <= 0.0 {
                        bail!("{}: {n} of {sent} arrived, no span", sub.what);
                    }
                    rate += n / span;
                    count += n;
                }
                // Messages/s, or MB/s for the large payloads.
                let scale = if case.figure.starts_with("blob") {
                    case.size as f64 / 1e6
                } else {
                    1.0
                };
                Ok(Sample {
                    value: rate * scale,
                    delivered: Some(count / (sent * subs.len() as f64)),
                    ..Sample::default()
                })
            }
            .await;
            publ.end().await;
            for sub in subs {
                sub.end().await;
            }
            if let Some(router) = router {
                router.end().await;
            }
            r
        }
        Kind::Idle => {
            let mut a = Peer::spawn(case, "idle", &key, &links.0)?;
            let info = a.expect("ready", start).await;
            let ikey = info_key(case, &format!("{key}/partner"), info?);
            let mut b = Peer::spawn(case, "idle", &ikey, &links.1)?;
            let r = async {
                b.expect("ready", start).await?;
                tokio::time::sleep(Duration::from_secs_f64(case.param)).await;
                let pid = a.pid().context("idle peer gone")?;
                let kib = status_kib(pid, "VmHWM:").context("no VmHWM in /proc")?;
                Ok(Sample {
                    value: kib,
                    anon_kib: status_kib(pid, "RssAnon:"),
                    ..Sample::default()
                })
            }
            .await;
            b.end().await;
            a.end().await;
            r
        }
    };
    drop(cable);
    out
}

/// The KEYs of a rate case's subscribers, and its publisher's where it is not
/// [`info_key`]'s: a fan-out's Zenoh subscribers each listen on a port of their own, which the
/// publisher connects to all of (or, with a router, all join the router's port); its marea subscribers are nodes of their own names; its
/// iceoryx2 subscribers share the one service.
fn fanout_keys(case: &Case, key: &str) -> anyhow::Result<(Vec<String>, Option<String>)> {
    if case.subs == 1 {
        return Ok((vec![key.to_owned()], None));
    }
    match case.bin {
        "peer-zenoh" if case.suffix == "-client" => {
            // Every one a client of the router on one port.
            let name = key.split_once(':').map_or(key, |(_, n)| n);
            let k = format!("{}:{name}", free_port(false)?);
            Ok((vec![k.clone(); case.subs], Some(k)))
        }
        "peer-zenoh" => {
            let name = key.split_once(':').map_or(key, |(_, n)| n);
            let ports = (0..case.subs)
                .map(|_| free_port(false))
                .collect::<anyhow::Result<Vec<u16>>>()?;
            let keys = ports.iter().map(|p| format!("{p}:{name}")).collect();
            let all: Vec<String> = ports.iter().map(u16::to_string).collect();
            Ok((keys, Some(format!("{}:{name}", all.join(",")))))
        }
        b if b.starts_with("peer-marea") => Ok((
            (0..case.subs).map(|i| format!("{key}/sub{i}")).collect(),
            Some(key.to_owned()),
        )),
        // Every subscriber of the one service.
        "peer-iceoryx2" => Ok((vec![key.to_owned(); case.subs], Some(key.to_owned()))),
        other => bail!("{other}: no fan-out"),
    }
}

/// The initiator's KEY: the responder's address for raw UDP, else the run's key.
fn info_key(case: &Case, key: &str, info: Vec<String>) -> String {
    if case.bin == "peer-udp" {
        info.into_iter().next().unwrap_or_default()
    } else {
        key.to_owned()
    }
}

fn word(w: &[String], i: usize) -> anyhow::Result<f64> {
    w.get(i)
        .with_context(|| format!("result word {i} missing in {w:?}"))?
        .parse()
        .with_context(|| format!("result word {i} in {w:?}"))
}

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        s[n / 2]
    } else {
        (s[n / 2 - 1] + s[n / 2]) / 2.0
    }
}

fn spread_pct(v: &[f64]) -> f64 {
    let (lo, hi) = v
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    (hi - lo) / median(v) * 100.0
}

fn unit(figure: &str) -> &'static str {
    if figure.starts_with("rtt") {
        "us"
    } else if figure.starts_with("idle") {
        "KiB"
    } else if figure.starts_with("blob") {
        "MB/s"
    } else {
        "msgs/s"
    }
}

/// Errors are printed as a chain of causes (`peers: ...: ...`), without the backtrace anyhow
/// would add under `RUST_BACKTRACE`.
#[tokio::main]
async fn main() -> std::process::ExitCode {
    let result = match opts() {
        Ok(Some(o)) => run(o).await,
        Ok(None) => Ok(()),
        Err(e) => Err(e),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("peers: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(o: Opts) -> anyhow::Result<()> {
    build_peers(&o)?;
    let cases = cases(&o);
    for c in &cases {
        let exe = bin_dir()?.join(c.bin);
        if !exe.exists() {
            bail!(
                "{} is missing: build all binaries first (cargo run builds them)",
                exe.display()
            );
        }
    }
    // (figure, imp) -> per round.
    let mut got: BTreeMap<(String, &str), Vec<Option<Sample>>> = BTreeMap::new();
    let pid = std::process::id();
    for round in 0..o.rounds {
        for (i, c) in cases.iter().enumerate() {
            let key = format!("peers{pid}r{round}c{i}");
            eprintln!("peers: round {} {}.{}", round + 1, c.figure, c.imp);
            let s = match run_case(c, &key, o.baud).await {
                Ok(s) => Some(s),
                Err(e) => {
                    eprintln!(
                        "peers: {}.{} round {} failed: {e:#}",
                        c.figure,
                        c.imp,
                        round + 1
                    );
                    None
                }
            };
            got.entry((c.figure.clone(), c.imp)).or_default().push(s);
        }
    }
    for ((fig, imp), runs) in &got {
        let vals: Vec<f64> = runs.iter().flatten().map(|s| s.value).collect();
        if vals.is_empty() {
            continue;
        }
        let name = format!("peers.{fig}.{imp}");
        metric(&name, median(&vals), unit(fig));
        let p99: Vec<f64> = runs.iter().flatten().filter_map(|s| s.p99).collect();
        if !p99.is_empty() {
            metric(&format!("{name}.p99"), median(&p99), "us");
        }
        let d: Vec<f64> = runs.iter().flatten().filter_map(|s| s.delivered).collect();
        if !d.is_empty() {
            metric(&format!("{name}.delivered"), median(&d), "ratio");
        }
        let anon: Vec<f64> = runs.iter().flatten().filter_map(|s| s.anon_kib).collect();
        if !anon.is_empty() {
            metric(&format!("{name}.anon"), median(&anon), "KiB");
        }
        let idle: Vec<f64> = runs.iter().flatten().filter_map(|s| s.idle_p99).collect();
        if !idle.is_empty() {
            metric(&format!("{name}.idle_p99"), median(&idle), "us");
            let ratios: Vec<f64> = runs
                .iter()
                .flatten()
                .filter_map(|s| Some(s.p99? / s.idle_p99?))
                .collect();
            metric(&format!("{name}.p99_to_idle"), median(&ratios), "ratio");
            metric(
                &format!("{name}.p99_to_idle.spread_pct"),
                spread_pct(&ratios),
                "%",
            );
        }
        let bulk: Vec<f64> = runs.iter().flatten().filter_map(|s| s.bulk_mb_s).collect();
        if !bulk.is_empty() {
            metric(&format!("{name}.bulk_mb_s"), median(&bulk), "MB/s");
        }
        metric(&format!("{name}.spread_pct"), spread_pct(&vals), "%");
        metric(&format!("{name}.runs"), vals.len() as f64, "count");
    }
    // Same-run ratios: within each round, then the median over rounds.
    // (figure, implementation) over (figure, implementation).
    let ratios = [
        (
            "blob4m",
            "marea_shm",
            "blob4m",
            "iceoryx2",
            "peers.blob4m.marea_shm_to_iceoryx2",
        ),
        (
            "blob1m",
            "marea_udp",
            "blob1m",
            "zenoh_tcp",
            "peers.blob1m.marea_udp_to_zenoh_tcp",
        ),
        (
            "fanout10.event64",
            "marea_udp",
            "fanout10.event64",
            "zenoh_tcp",
            "peers.fanout10.event64.marea_udp_to_zenoh_tcp",
        ),
        (
            "fanout50.event64",
            "marea_udp",
            "fanout50.event64",
            "zenoh_tcp",
            "peers.fanout50.event64.marea_udp_to_zenoh_tcp",
        ),
        (
            "fanout10.event64",
            "marea_udp",
            "fanout10.event64",
            "zenoh_router",
            "peers.fanout10.event64.marea_udp_to_zenoh_router",
        ),
        (
            "fanout50.event64",
            "marea_udp",
            "fanout50.event64",
            "zenoh_router",
            "peers.fanout50.event64.marea_udp_to_zenoh_router",
        ),
        (
            "fanout10.event64",
            "marea_shm",
            "fanout10.event64",
            "iceoryx2",
            "peers.fanout10.event64.marea_shm_to_iceoryx2",
        ),
        (
            "fanout50.event64",
            "marea_shm",
            "fanout50.event64",
            "iceoryx2",
            "peers.fanout50.event64.marea_shm_to_iceoryx2",
        ),
        (
            "event64_default_api",
            "marea_udp",
            "event64",
            "zenoh_tcp",
            "peers.event64_default_api.marea_udp_to_zenoh_tcp",
        ),
        (
            "event64",
            "marea_udp",
            "event64",
            "zenoh_tcp",
            "peers.event64.marea_udp_to_zenoh_tcp",
        ),
        (
            "event1k",
            "marea_udp",
            "event1k",
            "zenoh_tcp",
            "peers.event1k.marea_udp_to_zenoh_tcp",
        ),
        (
            "event64",
            "marea_shm",
            "event64",
            "iceoryx2",
            "peers.event64.marea_shm_to_iceoryx2",
        ),
        (
            "event1k",
            "marea_shm",
            "event1k",
            "iceoryx2",
            "peers.event1k.marea_shm_to_iceoryx2",
        ),
        (
            "rtt64_pinned",
            "marea_udp",
            "rtt64_pinned",
            "raw_udp",
            "peers.rtt64_pinned.marea_udp_to_raw",
        ),
        (
            "rtt64_pinned",
            "marea_shm",
            "rtt64_pinned",
            "iceoryx2",
            "peers.rtt64_pinned.marea_shm_to_iceoryx2",
        ),
        (
            "rtt64",
            "marea_udp",
            "rtt64",
            "zenoh_tcp",
            "peers.rtt64.marea_udp_to_zenoh_tcp",
        ),
        (
            "rtt64",
            "marea_udp",
            "rtt64",
            "raw_udp",
            "peers.rtt64.marea_udp_to_raw",
        ),
        (
            "rtt64",
            "marea_shm",
            "rtt64",
            "iceoryx2",
            "peers.rtt64.marea_shm_to_iceoryx2",
        ),
    ];
    for (fa, a, fb, b, name) in ratios {
        let (Some(ra), Some(rb)) = (got.get(&(fa.to_owned(), a)), got.get(&(fb.to_owned(), b)))
        else {
            continue;
        };
        let per_round: Vec<f64> = ra
            .iter()
            .zip(rb)
            .filter_map(|(x, y)| Some(x.as_ref()?.value / y.as_ref()?.value))
            .collect();
        if per_round.is_empty() {
            eprintln!("peers: {name}: no round measured both {a} and {b}");
            continue;
        }
        metric(name, median(&per_round), "ratio");
        metric(&format!("{name}.spread_pct"), spread_pct(&per_round), "%");
    }
    Ok(())
}

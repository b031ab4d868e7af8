//! Helpers for cross-process tests: start real child processes, read their JSON lines with
//! deadlines, and kill them on drop so no test leaves a process behind.

#![allow(dead_code)]

pub mod attacker;
pub mod hostile;
pub mod trust;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;
pub use test_support::process::{outcome_within, Proc};

/// Arguments that put a probe in a test's own discovery domain and multicast port, with a
/// short heartbeat and lease so failures show quickly.
pub struct Net {
    pub domain: String,
    pub port: u16,
    pub heartbeat_ms: u64,
    pub lease_ms: u64,
}

impl Net {
    pub fn new(test: &str) -> Net {
        let h = test.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
        });
        let h = h ^ u64::from(std::process::id()).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        Net {
            domain: format!("{test}-{}", std::process::id()),
            port: test_support::multicast_port(h),
            heartbeat_ms: 200,
            lease_ms: 1200,
        }
    }

    pub fn probe(&self, node: &str, cmd: &[&str]) -> Proc {
        self.probe_args(node, &[], cmd)
    }

    pub fn probe_ns(&self, node: &str, namespace: &str, cmd: &[&str]) -> Proc {
        self.probe_args(node, &["--namespace", namespace], cmd)
    }

    /// A probe carrying the domain key `key` (as `<security keyFile=..>`), in `namespace`.
    pub fn keyed(&self, node: &str, namespace: &str, key: &Path, cmd: &[&str]) -> Proc {
        let key = key.to_str().expect("a UTF-8 key path");
        self.probe_args(node, &["--key-file", key, "--namespace", namespace], cmd)
    }

    /// A `network.xml` for node `node` of `namespace` in this test's domain, holding `inner`
    /// (`<access>`, `<security>`...) inside `<network>`; written into `dir`.
    pub fn network_xml(&self, dir: &Path, node: &str, namespace: &str, inner: &str) -> PathBuf {
        let xml = format!(
            r#"<network node="{node}" namespace="{namespace}" domain="{domain}">
  <ethernet bind="127.0.0.1:0" multicast="239.255.77.1:{port}" interface="127.0.0.1"
            heartbeatMs="{hb}" leaseMs="{lease}"/>
  {inner}
</network>
"#,
            domain = self.domain,
            port = self.port,
            hb = self.heartbeat_ms,
            lease = self.lease_ms,
        );
        let path = dir.join(format!("{node}.xml"));
        std::fs::write(&path, xml).expect("write network.xml");
        path
    }

    /// The multicast group the probes of this test announce on.
    pub fn group(&self) -> std::net::SocketAddrV4 {
        std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 1), self.port)
    }

    pub fn probe_args(&self, node: &str, extra: &[&str], cmd: &[&str]) -> Proc {
        let mut args: Vec<String> = vec![
            "--node".into(),
            node.into(),
            "--domain".into(),
            self.domain.clone(),
            "--mcast-port".into(),
            self.port.to_string(),
            "--heartbeat-ms".into(),
            self.heartbeat_ms.to_string(),
            "--lease-ms".into(),
            self.lease_ms.to_string(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend(cmd.iter().map(|s| s.to_string()));
        Proc::spawn(node, env!("CARGO_BIN_EXE_marea-probe"), &args)
    }
}

pub const T: Duration = Duration::from_secs(20);

/// A probe started from a `network.xml` (`extra` before the command: `--key-file ..`).
pub fn probe_with_config(
    name: &str,
    config: &Path,
    service: &str,
    extra: &[&str],
    cmd: &[&str],
) -> Proc {
    let mut args: Vec<String> = vec![
        "--config".into(),
        config.display().to_string(),
        "--service".into(),
        service.into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    args.extend(cmd.iter().map(|s| s.to_string()));
    Proc::spawn(name, env!("CARGO_BIN_EXE_marea-probe"), &args)
}

/// Makes a domain key with the real CLI (`usal keygen`), checking what it promises: mode 0600.
pub fn keygen(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    let out = Command::new(env!("CARGO_BIN_EXE_usal"))
        .args(["keygen", path.to_str().expect("utf-8 temp path")])
        .output()
        .expect("run usal keygen");
    assert!(out.status.success(), "{out:?}");
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(&path)
        .expect("the key file exists")
        .permissions()
        .mode()
        & 0o777;
    assert_eq!(mode, 0o600);
    path
}

/// `marea-probe` arguments of the hostile tests' victim: it provides `retask`, keeps sink
/// `plans` storing into `inbox`, follows `**/position`, and reports what it executed,
/// delivered and refused.
pub fn victim_cmd(inbox: &Path) -> [&str; 9] {
    [
        "victim",
        "--call",
        "retask",
        "--sink",
        "plans",
        "--dir",
        inbox.to_str().expect("a UTF-8 path"),
        "--pattern",
        "**/position",
    ]
}

/// `marea-probe` arguments publishing positions on `item` at 50 Hz until stopped.
pub fn publishing(item: &str) -> [&str; 7] {
    [
        "var-pub",
        "--item",
        item,
        "--count",
        "100000000",
        "--interval-ms",
        "20",
    ]
}

/// The outcome line of a `call` (`ok` or `error`) or a `send` (`done` or `error`).
pub fn outcome(p: &mut Proc) -> Value {
    outcome_within(p, T)
}

/// `marea-probe` arguments sending `file` to sink `to`, retrying for up to `retry_secs`.
pub fn sending<'a>(file: &'a str, to: &'a str, retry_secs: &'a str) -> [&'a str; 7] {
    [
        "send",
        "--file",
        file,
        "--to",
        to,
        "--retry-secs",
        retry_secs,
    ]
}

/// The radio emulator as a child process, killed on drop.
pub struct Radio {
    child: Child,
    pub ground: String,
    pub air: String,
    lines: mpsc::Receiver<Value>,
}

impl Radio {
    pub fn start(args: &[&str]) -> Radio {
        let mut child = Command::new(env!("CARGO_BIN_EXE_marea-radio"))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start marea-radio");
        let stdout = child.stdout.take().expect("piped");
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if let Ok(v) = serde_json::from_str::<Value>(&line) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
            }
        });
        let first = rx
            .recv_timeout(Duration::from_secs(10))
            .expect("marea-radio prints its ports");
        Radio {
            child,
            ground: first["ground"].as_str().expect("ground path").to_owned(),
            air: first["air"].as_str().expect("air path").to_owned(),
            lines: rx,
        }
    }

    /// Freezes the radio (SIGSTOP): not a byte crosses until [`Radio::resume`].
    pub fn freeze(&self) {
        let _ = Command::new("kill")
            .args(["-STOP", &self.child.id().to_string()])
            .status();
    }

    /// Lets a frozen radio carry bytes again (SIGCONT).
    pub fn resume(&self) {
        let _ = Command::new("kill")
            .args(["-CONT", &self.child.id().to_string()])
            .status();
    }

    /// Stops the radio with SIGTERM and returns its exit counters.
    pub fn stop(self) -> Value {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(5);
        while let Ok(v) = self
            .lines
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
        {
            if v["event"] == "exit" {
                return v;
            }
        }
        Value::Null
    }
}

impl Drop for Radio {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An event subscriber `name` started by `spawn` (a network's `probe`), expecting `count`
/// events on `probe/ev` (`ev-sub` options `more` after), ready.
pub fn event_reader(
    spawn: &impl Fn(&str, &[&str]) -> Proc,
    name: &str,
    count: u64,
    more: &[&str],
) -> Proc {
    let count = count.to_string();
    let mut args = vec!["ev-sub", "--pattern", "probe/ev", "--count", &count];
    args.extend_from_slice(more);
    let mut sub = spawn(name, &args);
    sub.expect_key(T, "ready");
    sub
}

/// `n` event subscribers `sub1`..`subN` of [`event_reader`], all ready.
pub fn ready_event_subscribers(
    n: usize,
    count: u64,
    spawn: impl Fn(&str, &[&str]) -> Proc,
) -> Vec<Proc> {
    (1..=n)
        .map(|i| event_reader(&spawn, &format!("sub{i}"), count, &[]))
        .collect()
}

/// A publisher `name` streaming `count` events on `ev` (`Event::stream`) once one subscriber
/// is there.
pub fn event_streamer(spawn: &impl Fn(&str, &[&str]) -> Proc, name: &str, count: u64) -> Proc {
    let count = count.to_string();
    spawn(
        name,
        &[
            "ev-pub", "--item", "ev", "--count", &count, "--subs", "1", "--stream",
        ],
    )
}

/// The stream of [`event_streamer`] finished (within two minutes) with no event lost.
pub fn expect_stream_finished(publ: &mut Proc) {
    let done = publ.expect_key(Duration::from_secs(120), "raised");
    assert_eq!(done["lost_events"], 0, "{}: {done}", publ.name);
}

/// Every subscriber of [`ready_event_subscribers`] received `count` events, in order.
pub fn expect_received_in_order(subs: &mut [Proc], count: u64) {
    for s in subs.iter_mut() {
        let r = s.expect_key(Duration::from_secs(60), "received");
        assert_eq!(r["received"], count, "{}", s.name);
        assert_eq!(r["in_order"], true, "{}: {:?}", s.name, s.seen);
    }
}

/// A stream is lossless up to the application: 150,000 events streamed to a subscriber that
/// pauses a millisecond every 100 (about 20 times slower than the publisher, so it falls
/// behind by far more than its mailbox holds, 65,536) all arrive, in order, none lost: its node
/// tells the publisher's that it is behind (`Flow`), and the stream waits.
pub fn stream_to_a_slow_reader_loses_nothing(spawn: impl Fn(&str, &[&str]) -> Proc) {
    let mut sub = event_reader(&spawn, "sub", 150000, &["--slow", "100"]);
    let mut publ = event_streamer(&spawn, "pub", 150000);
    expect_stream_finished(&mut publ);
    expect_received_in_order(std::slice::from_mut(&mut sub), 150000);
}

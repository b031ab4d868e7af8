//! Test harness shared by the station tests: a raw HTTP/1.1 client (JSON requests and the
//! server-sent-event stream), station processes started as children, unique domains.

#![allow(dead_code)] // Each test file uses a different part of the harness.

use std::process::Stdio;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::process::{Child, Command};

/// Bound on every single wait of the tests.
pub const STEP: Duration = Duration::from_secs(20);

/// A unique middleware domain, so parallel tests do not see each other.
pub fn unique_domain(tag: &str) -> String {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "gs-{tag}-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

/// A station process (fmo or fpmo), killed on drop.
pub struct Station {
    child: Child,
    /// `127.0.0.1:PORT`.
    pub addr: String,
}

impl Station {
    /// Starts `bin` with `args` plus `--listen 127.0.0.1:0` and reads the `NAME=URL` line.
    pub async fn start(bin: &str, url_var: &str, args: &[&str]) -> Station {
        let mut child = Command::new(bin)
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .expect("spawn station");
        let stdout = child.stdout.take().expect("piped stdout");
        let line = tokio::time::timeout(STEP, BufReader::new(stdout).lines().next_line())
            .await
            .expect("the station printed no URL in time")
            .expect("reading station stdout")
            .expect("the station exited early");
        let url = line
            .strip_prefix(&format!("{url_var}="))
            .unwrap_or_else(|| panic!("unexpected station output {line:?}"));
        let addr = url
            .trim_start_matches("http://")
            .trim_end_matches('/')
            .to_owned();
        Station { child, addr }
    }

    /// GET `path`: status and body.
    pub async fn get(&self, path: &str) -> (u16, String) {
        request(&self.addr, "GET", path, None).await
    }

    /// GET `path` as JSON (asserting 200).
    pub async fn get_json(&self, path: &str) -> serde_json::Value {
        let (status, body) = self.get(path).await;
        assert_eq!(status, 200, "GET {path}: {body}");
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("GET {path}: {e}: {body}"))
    }

    /// POST `body` as JSON to `path`: status and body as JSON (null when empty).
    pub async fn post(&self, path: &str, body: serde_json::Value) -> (u16, serde_json::Value) {
        let (status, text) = request(&self.addr, "POST", path, Some(&body.to_string())).await;
        let v = if text.is_empty() {
            serde_json::Value::Null
        } else {
            serde_json::from_str(&text).unwrap_or(serde_json::Value::String(text))
        };
        (status, v)
    }

    /// Polls `GET /api/state` until `pred` holds, returning that state.
    pub async fn wait_state(
        &self,
        what: &str,
        mut pred: impl FnMut(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let deadline = tokio::time::Instant::now() + STEP;
        loop {
            let s = self.get_json("/api/state").await;
            if pred(&s) {
                return s;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "never saw {what}; last state {s:#}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        let _ = self.child.start_kill();
        let _ = tokio::time::timeout(STEP, self.child.wait()).await;
    }
}

/// One HTTP/1.1 request with `Connection: close`; decodes a chunked body.
pub async fn request(addr: &str, method: &str, path: &str, body: Option<&str>) -> (u16, String) {
    tokio::time::timeout(STEP, async {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        let body = body.unwrap_or("");
        let req = format!(
            "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\
             Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        s.write_all(req.as_bytes()).await.expect("write");
        let mut raw = Vec::new();
        s.read_to_end(&mut raw).await.expect("read");
        let text = String::from_utf8_lossy(&raw).into_owned();
        let (head, rest) = text.split_once("\r\n\r\n").expect("HTTP head");
        let status: u16 = head
            .split_whitespace()
            .nth(1)
            .and_then(|c| c.parse().ok())
            .expect("status code");
        let chunked = head
            .to_ascii_lowercase()
            .contains("transfer-encoding: chunked");
        let body = if chunked {
            dechunk(rest)
        } else {
            rest.to_owned()
        };
        (status, body)
    })
    .await
    .expect("HTTP request timed out")
}

fn dechunk(mut s: &str) -> String {
    let mut out = String::new();
    while let Some((len, rest)) = s.split_once("\r\n") {
        let n = usize::from_str_radix(len.trim(), 16).unwrap_or(0);
        if n == 0 || rest.len() < n {
            break;
        }
        out.push_str(&rest[..n]);
        s = rest[n..].trim_start_matches("\r\n");
    }
    out
}

/// An open server-sent-event stream.
pub struct Sse {
    lines: tokio::io::Lines<BufReader<TcpStream>>,
}

impl Sse {
    /// Opens `GET path` and checks the answer is an event stream.
    pub async fn open(addr: &str, path: &str) -> Sse {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        let req =
            format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n");
        s.write_all(req.as_bytes()).await.expect("write");
        let mut lines = BufReader::new(s).lines();
        let mut head = String::new();
        loop {
            let l = tokio::time::timeout(STEP, lines.next_line())
                .await
                .expect("SSE head timed out")
                .expect("read")
                .expect("SSE closed in its head");
            if l.is_empty() {
                break;
            }
            head.push_str(&l);
            head.push('\n');
        }
        assert!(head.starts_with("HTTP/1.1 200"), "{head}");
        assert!(
            head.to_ascii_lowercase()
                .contains("content-type: text/event-stream"),
            "{head}"
        );
        Sse { lines }
    }

    /// The next event named `name`, its data parsed as JSON. Chunk-size lines of the chunked
    /// transfer encoding are skipped (they never start with `event:` or `data:`).
    pub async fn next(&mut self, name: &str) -> serde_json::Value {
        let mut event = String::new();
        loop {
            let l = tokio::time::timeout(STEP, self.lines.next_line())
                .await
                .expect("no SSE event in time")
                .expect("read")
                .expect("SSE stream closed");
            if let Some(e) = l.strip_prefix("event:") {
                event = e.trim().to_owned();
            } else if let Some(d) = l.strip_prefix("data:") {
                if event == name {
                    return serde_json::from_str(d.trim()).expect("SSE data is JSON");
                }
            }
        }
    }
}

/// The vehicle `label` (e.g. `rover1`) in a snapshot.
pub fn vehicle<'a>(state: &'a serde_json::Value, label: &str) -> Option<&'a serde_json::Value> {
    state["vehicles"]
        .as_array()?
        .iter()
        .find(|v| v["label"] == label)
}

/// A binary of another package of the workspace (`vas`, `mavsim`, `fpma`), built once per test
/// process into this test's own target directory.
pub fn workspace_bin(package: &str) -> std::path::PathBuf {
    use std::collections::HashMap;
    use std::sync::{Mutex, OnceLock};
    static BUILT: OnceLock<Mutex<HashMap<String, std::path::PathBuf>>> = OnceLock::new();
    let mut built = BUILT
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    if let Some(p) = built.get(package) {
        return p.clone();
    }
    // <target>/debug/deps/<test binary>: the target directory is three levels up.
    let exe = std::env::current_exe().expect("test binary path");
    let target = exe
        .ancestors()
        .nth(3)
        .expect("test binary inside <target>/<profile>/deps")
        .to_owned();
    let status = std::process::Command::new(env!("CARGO"))
        .args(["build", "-p", package, "--bin", package])
        .env("CARGO_TARGET_DIR", &target)
        .status()
        .expect("running cargo build");
    assert!(status.success(), "building {package} failed");
    let bin = target.join("debug").join(package);
    assert!(bin.exists(), "no {package} at {}", bin.display());
    built.insert(package.to_owned(), bin.clone());
    bin
}

/// A child process killed on drop.
pub struct Proc {
    child: Child,
    /// The first stdout line, when asked for.
    pub first_line: Option<String>,
}

impl Proc {
    /// Spawns `bin args`; with `read_first_line`, waits for its first stdout line.
    pub async fn start(bin: &std::path::Path, args: &[String], read_first_line: bool) -> Proc {
        let mut child = Command::new(bin)
            .args(args)
            .stdout(if read_first_line {
                Stdio::piped()
            } else {
                Stdio::null()
            })
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("spawn {}: {e}", bin.display()));
        let mut first_line = None;
        if read_first_line {
            let stdout = child.stdout.take().expect("piped stdout");
            first_line = tokio::time::timeout(STEP, BufReader::new(stdout).lines().next_line())
                .await
                .expect("no first line in time")
                .expect("reading stdout");
        }
        Proc { child, first_line }
    }

    /// Kills it and waits.
    pub async fn kill(mut self) {
        let _ = self.child.start_kill();
        let _ = tokio::time::timeout(STEP, self.child.wait()).await;
    }
}

/// Home of the simulated rover: the car park of `config/flightplans/rover-carpark.xml`.
pub const HOME: (f64, f64) = (41.275, 1.987);

/// mavsim on any UDP port at `speedup`, and a `vas` for it in `domain`, namespace `rover1`.
pub async fn rover(domain: &str, speedup: f64) -> (Proc, Proc) {
    let sim = Proc::start(
        &workspace_bin("mavsim"),
        &[
            "--udp".into(),
            "127.0.0.1:0".into(),
            "--speedup".into(),
            speedup.to_string(),
            "--home".into(),
            format!("{},{},0", HOME.0, HOME.1),
        ],
        true,
    )
    .await;
    let line = sim.first_line.clone().unwrap_or_default();
    let addr = line
        .strip_prefix("MAVSIM_UDP=")
        .unwrap_or_else(|| panic!("unexpected mavsim output {line:?}"))
        .to_owned();
    let vas = Proc::start(
        &workspace_bin("vas"),
        &[
            "--endpoint".into(),
            format!("udpout:{addr}"),
            "--domain".into(),
            domain.into(),
            "--namespace".into(),
            "rover1".into(),
        ],
        false,
    )
    .await;
    (sim, vas)
}

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
    /// The URL it printed, `http://127.0.0.1:PORT/?token=TOKEN`.
    pub url: String,
    /// Its token, required on every `/api/*` call.
    pub token: String,
}

impl Station {
    /// Starts `bin` with `args` plus `--listen 127.0.0.1:0` and reads the `NAME=URL` line.
    /// Unless `args` name their `--tiles`, the station draws no tiles (`--tiles none`): a test
    /// never loads a tile server's maps from the internet.
    pub async fn start(bin: &str, url_var: &str, args: &[&str]) -> Station {
        let no_tiles: &[&str] = if args.contains(&"--tiles") {
            &[]
        } else {
            &["--tiles", "none"]
        };
        Self::start_as_shipped(bin, url_var, &[args, no_tiles].concat()).await
    }

    /// As [`Station::start`], with the station's own defaults (its map tiles included).
    pub async fn start_as_shipped(bin: &str, url_var: &str, args: &[&str]) -> Station {
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
        let (base, token) = url
            .split_once("/?token=")
            .unwrap_or_else(|| panic!("no token in the station's URL {url:?}"));
        let addr = base.trim_start_matches("http://").to_owned();
        Station {
            child,
            addr,
            url: url.to_owned(),
            token: token.to_owned(),
        }
    }

    /// `path` with the station's token as a query parameter.
    pub fn with_token(&self, path: &str) -> String {
        let sep = if path.contains('?') { '&' } else { '?' };
        format!("{path}{sep}token={}", self.token)
    }

    /// The token as a header line for [`request_with`].
    fn token_header(&self) -> String {
        format!("X-Station-Token: {}\r\n", self.token)
    }

    /// GET `path` (with the token): status and body.
    pub async fn get(&self, path: &str) -> (u16, String) {
        request_with(&self.addr, "GET", path, None, &self.token_header()).await
    }

    /// GET `path` as JSON (asserting 200).
    pub async fn get_json(&self, path: &str) -> serde_json::Value {
        let (status, body) = self.get(path).await;
        assert_eq!(status, 200, "GET {path}: {body}");
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("GET {path}: {e}: {body}"))
    }

    /// Polls `GET /api/fleet` (the fleet view) until the first fleet's status satisfies
    /// `pred`; returns the whole answer.
    pub async fn wait_fleet(
        &self,
        what: &str,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let deadline = tokio::time::Instant::now() + STEP * 3;
        loop {
            let j = self.get_json("/api/fleet").await;
            if pred(&j["fleets"][0]["status"]) {
                return j;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "never saw {what}; last {j:#}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// POST `body` as JSON to `path`: status and body as JSON (null when empty).
    pub async fn post(&self, path: &str, body: serde_json::Value) -> (u16, serde_json::Value) {
        let (status, text) = request_with(
            &self.addr,
            "POST",
            path,
            Some(&body.to_string()),
            &self.token_header(),
        )
        .await;
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
        test_support::stop(&mut self.child).await;
    }
}

/// One HTTP/1.1 request with `Connection: close`; decodes a chunked body.
pub async fn request(addr: &str, method: &str, path: &str, body: Option<&str>) -> (u16, String) {
    request_with(addr, method, path, body, "").await
}

/// [`request`] with `extra` header lines (each ending in `\r\n`).
pub async fn request_with(
    addr: &str,
    method: &str,
    path: &str,
    body: Option<&str>,
    extra: &str,
) -> (u16, String) {
    tokio::time::timeout(STEP, async {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        let body = body.unwrap_or("");
        let req = format!(
            "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n{extra}\
             Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        s.write_all(req.as_bytes()).await.expect("write");
        // Read the head, then exactly the body its length says (some servers, chromedriver
        // among them, keep the connection open despite `Connection: close`).
        let mut r = BufReader::new(s);
        let mut head = String::new();
        loop {
            let mut line = String::new();
            if r.read_line(&mut line).await.expect("read head") == 0 || line == "\r\n" {
                break;
            }
            head.push_str(&line);
        }
        let status: u16 = head
            .split_whitespace()
            .nth(1)
            .and_then(|c| c.parse().ok())
            .expect("status code");
        let lower = head.to_ascii_lowercase();
        let length = lower
            .lines()
            .find_map(|l| l.strip_prefix("content-length:"))
            .and_then(|n| n.trim().parse::<usize>().ok());
        let mut raw = Vec::new();
        if let Some(n) = length {
            raw.resize(n, 0);
            r.read_exact(&mut raw).await.expect("read body");
        } else {
            r.read_to_end(&mut raw).await.expect("read body");
        }
        let rest = String::from_utf8_lossy(&raw).into_owned();
        let body = if lower.contains("transfer-encoding: chunked") {
            dechunk(&rest)
        } else {
            rest
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

/// Command `id` in a snapshot.
pub fn command(state: &serde_json::Value, id: u64) -> Option<&serde_json::Value> {
    state["commands"].as_array()?.iter().find(|c| c["id"] == id)
}

/// The vehicle `label` (e.g. `rover1`) in a snapshot.
pub fn vehicle<'a>(state: &'a serde_json::Value, label: &str) -> Option<&'a serde_json::Value> {
    state["vehicles"]
        .as_array()?
        .iter()
        .find(|v| v["label"] == label)
}

/// Runs the station binary `bin` on a free port with `args`, expecting it to refuse to
/// start: its stderr (which names the reason).
pub async fn station_fails_at_start(bin: &str, args: &[&str]) -> String {
    let out = tokio::time::timeout(
        STEP,
        tokio::process::Command::new(bin)
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("the station did not exit")
    .expect("running the station");
    assert!(!out.status.success(), "{args:?} accepted");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Builds the flight binaries the scenarios start (mavsim, vas, fpma) before a scenario's own
/// time bound starts: a cold build can take minutes on a shared machine.
pub fn build_flight_bins() {
    for p in ["mavsim", "vas", "fpma"] {
        workspace_bin(p);
    }
}

pub use test_support::workspace_bin;

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
        test_support::stop(&mut self.child).await;
    }
}

/// Home of the simulated rover: the car park of `config/flightplans/rover-carpark.xml`.
pub const HOME: (f64, f64) = (41.275, 1.987);

/// `fpma run` for the rover `rover1` in `domain` (plans and state under `plans`).
pub async fn fpma_rover1(domain: &str, plans: &std::path::Path) -> Proc {
    Proc::start(
        &workspace_bin("fpma"),
        &fpma_rover1_args(domain, plans),
        false,
    )
    .await
}

/// A `fleet` service running the fleet plan `plan` in `domain`, namespace `gcs`.
pub async fn fleet_service(plan: &std::path::Path, domain: &str) -> Proc {
    let args: Vec<String> = vec![
        "--plan".into(),
        plan.display().to_string(),
        "--domain".into(),
        domain.into(),
        "--namespace".into(),
        "gcs".into(),
    ];
    Proc::start(&workspace_bin("fleet"), &args, false).await
}

/// mavsim on any UDP port at `speedup`, and a `vas` for it in `domain`, namespace `rover1`.
pub async fn rover(domain: &str, speedup: f64) -> (Proc, Proc) {
    rover_named(domain, speedup, "rover1").await
}

/// The arguments of `fpma run` for the rover in `domain`, namespace `rover1`, taking plans
/// into `plans` and persisting its state in `plans/fpma-state` (not the user's state
/// directory: a test must not resume another run's plan).
pub fn fpma_rover1_args(domain: &str, plans: &std::path::Path) -> Vec<String> {
    [
        "run",
        "--domain",
        domain,
        "--namespace",
        "rover1",
        "--vehicle",
        "rover",
        "--plans-dir",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain([plans.display().to_string()])
    .chain(["--state-dir".to_string()])
    .chain([plans.join("fpma-state").display().to_string()])
    .collect()
}

/// mavsim on any UDP port at `speedup`, and a `vas` for it in `domain`, namespace `ns`.
pub async fn rover_named(domain: &str, speedup: f64, ns: &str) -> (Proc, Proc) {
    vehicle_named(domain, speedup, ns, "rover").await
}

/// A mavsim `kind` (rover, copter, plane) on any UDP port at `speedup`, and a `vas` for it
/// in `domain`, namespace `ns`.
pub async fn vehicle_named(domain: &str, speedup: f64, ns: &str, kind: &str) -> (Proc, Proc) {
    vehicle_with(domain, speedup, ns, kind, &[]).await
}

/// As [`vehicle_named`], mavsim given `sim_args` besides (a camera, say).
pub async fn vehicle_with(
    domain: &str,
    speedup: f64,
    ns: &str,
    kind: &str,
    sim_args: &[String],
) -> (Proc, Proc) {
    let mut args: Vec<String> = vec![
        "--vehicle".into(),
        kind.into(),
        "--udp".into(),
        "127.0.0.1:0".into(),
        "--speedup".into(),
        speedup.to_string(),
        "--home".into(),
        format!("{},{},0", HOME.0, HOME.1),
    ];
    args.extend_from_slice(sim_args);
    let sim = Proc::start(&workspace_bin("mavsim"), &args, true).await;
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
            ns.into(),
            "--vehicle".into(),
            kind.into(),
        ],
        false,
    )
    .await;
    (sim, vas)
}

/// A headless Chromium driven through chromedriver's WebDriver HTTP API (plain JSON over HTTP,
/// spoken with [`request`]). `None` when chromedriver or chromium is not installed
/// (`.ci/install-chromium` installs them).
pub struct Browser {
    driver: Proc,
    addr: String,
    session: String,
}

const ELEMENT_KEY: &str = "element-6066-11e4-a52e-4f735466cecf";

impl Browser {
    /// Starts chromedriver and a headless session, or `None` when they are missing.
    pub async fn start() -> Option<Browser> {
        let driver_bin = ["/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver"]
            .into_iter()
            .map(std::path::PathBuf::from)
            .find(|p| p.exists())?;
        let chromium = ["/usr/bin/chromium", "/usr/lib/chromium/chromium"]
            .into_iter()
            .find(|p| std::path::Path::new(p).exists())?;
        let port = test_support::free_tcp_port();
        let driver = Proc::start(&driver_bin, &[format!("--port={port}")], false).await;
        let addr = format!("127.0.0.1:{port}");
        // Its first line comes before it listens: wait until it accepts connections.
        let deadline = tokio::time::Instant::now() + STEP;
        while TcpStream::connect(&addr).await.is_err() {
            assert!(
                tokio::time::Instant::now() < deadline,
                "chromedriver never listened"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let caps = serde_json::json!({"capabilities": {"alwaysMatch": {"goog:chromeOptions": {
            "binary": chromium,
            "args": ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     "--window-size=1280,1000"],
        }}}});
        let (status, body) = request(&addr, "POST", "/session", Some(&caps.to_string())).await;
        assert_eq!(status, 200, "new session: {body}");
        let v: serde_json::Value = serde_json::from_str(&body).expect("session JSON");
        let session = v["value"]["sessionId"]
            .as_str()
            .expect("sessionId")
            .to_owned();
        Some(Browser {
            driver,
            addr,
            session,
        })
    }

    async fn try_cmd(
        &self,
        method: &str,
        path: &str,
        body: serde_json::Value,
    ) -> (u16, serde_json::Value, String) {
        let path = format!("/session/{}{path}", self.session);
        let b = body.to_string();
        let (status, text) = request(
            &self.addr,
            method,
            &path,
            (method == "POST").then_some(b.as_str()),
        )
        .await;
        let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
        (status, v, text)
    }

    async fn cmd(&self, method: &str, path: &str, body: serde_json::Value) -> serde_json::Value {
        let (status, v, text) = self.try_cmd(method, path, body).await;
        assert_eq!(status, 200, "{method} {path}: {text}");
        v["value"].clone()
    }

    /// Opens `url`.
    pub async fn goto(&self, url: &str) {
        self.cmd("POST", "/url", serde_json::json!({ "url": url }))
            .await;
    }

    /// Runs `script` (a function body) in the page and returns its value.
    pub async fn eval(&self, script: &str) -> serde_json::Value {
        self.cmd(
            "POST",
            "/execute/sync",
            serde_json::json!({"script": script, "args": []}),
        )
        .await
    }

    /// Polls `script` until it returns something truthy (not null/false/""/0).
    pub async fn wait_for(&self, what: &str, script: &str) -> serde_json::Value {
        let deadline = tokio::time::Instant::now() + STEP;
        loop {
            let v = self.eval(script).await;
            let truthy = match &v {
                serde_json::Value::Null => false,
                serde_json::Value::Bool(b) => *b,
                serde_json::Value::String(s) => !s.is_empty(),
                serde_json::Value::Number(n) => n.as_f64() != Some(0.0),
                _ => true,
            };
            if truthy {
                return v;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "page never showed {what}"
            );
            tokio::time::sleep(Duration::from_millis(150)).await;
        }
    }

    /// The WebDriver id of the first element matching `css`.
    pub async fn find(&self, css: &str) -> String {
        let v = self
            .cmd(
                "POST",
                "/element",
                serde_json::json!({"using": "css selector", "value": css}),
            )
            .await;
        v[ELEMENT_KEY].as_str().expect("element id").to_owned()
    }

    /// Clicks the first element matching `css`, as a user would.
    pub async fn click(&self, css: &str) {
        // The page redraws its buttons on every update, so an element found a moment ago may be
        // replaced before the click lands ("stale element reference"): find it again, a bounded
        // number of times.
        for attempt in 0..20 {
            let id = self.find(css).await;
            let (status, v, text) = self
                .try_cmd(
                    "POST",
                    &format!("/element/{id}/click"),
                    serde_json::json!({}),
                )
                .await;
            if status == 200 {
                return;
            }
            let stale = v["value"]["error"] == "stale element reference";
            assert!(stale && attempt < 19, "click {css}: {text}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Types `text` into the element matching `css` (a file input takes a path).
    pub async fn send_keys(&self, css: &str, text: &str) {
        let id = self.find(css).await;
        self.cmd(
            "POST",
            &format!("/element/{id}/value"),
            serde_json::json!({ "text": text }),
        )
        .await;
    }

    /// Presses (`down`) or releases keys, WebDriver key values (`"\u{E00D}"` is Space).
    pub async fn keys(&self, keys: &[&str], down: bool) {
        let kind = if down { "keyDown" } else { "keyUp" };
        let actions: Vec<_> = keys
            .iter()
            .map(|k| serde_json::json!({"type": kind, "value": k}))
            .collect();
        self.cmd(
            "POST",
            "/actions",
            serde_json::json!({"actions": [{"type": "key", "id": "keyboard", "actions": actions}]}),
        )
        .await;
    }

    /// Saves a PNG screenshot to `path`.
    pub async fn screenshot(&self, path: &std::path::Path) {
        let v = self
            .cmd("GET", "/screenshot", serde_json::Value::Null)
            .await;
        let png = base64_decode(v.as_str().expect("base64 screenshot"));
        std::fs::write(path, png).expect("writing the screenshot");
    }

    /// Ends the session (Chromium exits) and chromedriver.
    pub async fn close(self) {
        drop(self);
    }
}

impl Drop for Browser {
    /// Ends the session even when a test panics, so no Chromium outlives the test: a blocking
    /// DELETE with a short time limit (async is not available in `drop`), then chromedriver is
    /// killed with its `Proc`.
    fn drop(&mut self) {
        use std::io::{Read, Write};
        let Ok(mut s) = std::net::TcpStream::connect(&self.addr) else {
            return;
        };
        let _ = s.set_read_timeout(Some(Duration::from_secs(5)));
        let req = format!(
            "DELETE /session/{} HTTP/1.1\r\nHost: {}\r\nContent-Length: 0\r\n\r\n",
            self.session, self.addr
        );
        if s.write_all(req.as_bytes()).is_ok() {
            // The answer comes once the browser has quit.
            let mut buf = [0u8; 512];
            let _ = s.read(&mut buf);
        }
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => Some(c - b'A'),
        b'a'..=b'z' => Some(c - b'a' + 26),
        b'0'..=b'9' => Some(c - b'0' + 52),
        b'+' => Some(62),
        b'/' => Some(63),
        _ => None,
    };
    let mut out = Vec::with_capacity(s.len() * 3 / 4);
    let (mut acc, mut bits) = (0u32, 0);
    for v in s.bytes().filter_map(val) {
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    out
}

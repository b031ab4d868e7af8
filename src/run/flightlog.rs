//! The flight log of `usal run`: one file per run holding what the ground saw of the flight
//! (telemetry, flight states, commands and their answers, plan events, link health, the
//! launcher's own notes), so a pilot can review it later with `usal replay`.
//!
//! # Format (version 1)
//!
//! JSON lines, one record per line, gzip-compressed when the file name ends in `.gz` (the
//! default, `logs/<mission>-<UTC>.jsonl.gz`), plain otherwise. `zcat LOG | jq .` reads it.
//! The writer flushes the compressed stream every second, so the log of a run that was killed
//! is readable up to its last second (its missing gzip trailer is then reported as truncation),
//! and has the file written to the disk itself (fsync) every five seconds, so a power cut (a
//! crash landing with the ground station's battery) loses at most that much.
//!
//! The first line is the header:
//! ```json
//! {"format":"usal-flight-log","version":1,"mission":"rover-demo","mission_file":"config/missions/rover-demo.xml",
//!  "domain":"rover-demo-4242","started_utc":"2026-11-23T22:22:53Z","started_unix_ms":1795472573000}
//! ```
//! Every following line is a record with at least
//! - `t`: seconds since the run started (monotonic clock, millisecond resolution), never
//!   decreasing down the file;
//! - `kind`: `telemetry` | `state` | `plan` | `alarm` | `link` | `command` | `note` | `end`.
//!
//! Records of what travelled on the middleware (every kind but `note` and `end`, and
//! `command` for the FMo's manual control) add
//! - `item`: `variable` or `event`; `name`: the full item name (`rover1/vas/position`);
//! - `type`: the publisher's payload type; `from`: the publishing node;
//! - `raw`: the payload as it travelled (postcard), in hex: what `usal replay` publishes;
//! - `value`: the same decoded to JSON when `usal` knows the type (for reading; replay ignores it).
//!
//! The station's own commands are `command` records with `name` (the function or file sink),
//! `args` and either `answer` or `error`. `note` records carry the launcher's notes as
//! `usal --json run` prints them (`record`). The last line of a complete log is
//! `{"t":..,"kind":"end","records":N}`.
//!
//! Unknown fields are ignored by readers of the same major `version`; a reader refuses a newer
//! version.

use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use flate2::read::GzDecoder;
use flate2::write::GzEncoder;
use marea::protocol::ItemKind;
use marea::{NetworkConfig, Node};
use serde_json::{json, Value};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

/// The header's `format`.
pub const FORMAT: &str = "usal-flight-log";
/// The format version written, and the newest read.
pub const VERSION: u64 = 1;
/// How often the writer flushes the compressed stream to the OS.
const FLUSH_EVERY: Duration = Duration::from_secs(1);
/// How often the recorder has the OS write the file to the disk itself.
const SYNC_EVERY: Duration = Duration::from_secs(5);
/// How long the recorder goes on after the run ends, for values already on their way.
const LAST_WORDS: Duration = Duration::from_millis(500);

/// Why a flight log could not be written.
#[derive(Debug, thiserror::Error)]
pub enum FlightLogCreateError {
    /// The file exists: a log is never overwritten.
    #[error("{0} exists; a flight log is never overwritten (name another with --log)")]
    Exists(PathBuf),
    /// Creating the file or its directory failed.
    #[error("creating the flight log {path}: {source}")]
    Io {
        /// The log.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// Why a flight log could not be read.
#[derive(Debug, thiserror::Error)]
pub enum FlightLogReadError {
    /// The file cannot be opened.
    #[error("cannot open {path}: {source}")]
    Open {
        /// The log.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Reading stopped inside the file: a truncated gzip stream (a run that was killed) or
    /// corrupt bytes.
    #[error("{path}: truncated or corrupt after line {line}: {source}")]
    Truncated {
        /// The log.
        path: PathBuf,
        /// The last line read whole.
        line: u64,
        /// The cause.
        source: std::io::Error,
    },
    /// A line is not a JSON object of this format.
    #[error("{path}: line {line}: {what}")]
    BadLine {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// What is wrong with it.
        what: String,
    },
    /// The file has no header line.
    #[error("{0}: empty, not a flight log")]
    Empty(PathBuf),
    /// The header names a newer format version.
    #[error("{path}: flight log version {found}; this usal reads version {VERSION} and older")]
    NewerVersion {
        /// The log.
        path: PathBuf,
        /// The version found.
        found: u64,
    },
}

/// The open log of this run; records are written as they come, from any task.
pub struct FlightLog {
    path: PathBuf,
    start: Instant,
    out: Mutex<Option<Box<dyn Write + Send>>>,
    /// The file under `out`, to have it written to the disk without holding `out`.
    file: std::fs::File,
    last_flush: Mutex<Instant>,
    records: AtomicU64,
    /// The first write error, reported at the end rather than on every record.
    failed: Mutex<Option<String>>,
}

impl FlightLog {
    /// Creates the log at `path` (its directory too) and writes the header.
    ///
    /// # Errors
    /// The file exists, or cannot be created or written.
    pub fn create(
        path: &Path,
        mission: &str,
        mission_file: &Path,
        domain: &str,
    ) -> Result<Arc<FlightLog>, FlightLogCreateError> {
        let io = |source| FlightLogCreateError::Io {
            path: path.to_owned(),
            source,
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let file = match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(path)
        {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(FlightLogCreateError::Exists(path.to_owned()))
            }
            Err(e) => return Err(io(e)),
        };
        let synced = file.try_clone().map_err(io)?;
        let buffered = BufWriter::new(file);
        let mut out: Box<dyn Write + Send> = if is_gz(path) {
            Box::new(GzEncoder::new(buffered, flate2::Compression::default()))
        } else {
            Box::new(buffered)
        };
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default();
        let header = json!({
            "format": FORMAT,
            "version": VERSION,
            "mission": mission,
            "mission_file": mission_file.display().to_string(),
            "domain": domain,
            "started_utc": utc_text(now.as_secs(), true),
            "started_unix_ms": now.as_millis() as u64,
        });
        writeln!(out, "{header}").map_err(io)?;
        out.flush().map_err(io)?;
        Ok(Arc::new(FlightLog {
            path: path.to_owned(),
            start: Instant::now(),
            out: Mutex::new(Some(out)),
            file: synced,
            last_flush: Mutex::new(Instant::now()),
            records: AtomicU64::new(0),
            failed: Mutex::new(None),
        }))
    }

    /// Where it is written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Records written so far (the header not counted).
    pub fn records(&self) -> u64 {
        self.records.load(Ordering::Relaxed)
    }

    /// Appends a record of `kind` with `fields` (an object; `t` and `kind` are added).
    pub fn record(&self, kind: &str, fields: Value) {
        let mut rec = serde_json::Map::new();
        rec.insert("kind".into(), kind.into());
        match fields {
            Value::Object(o) => rec.extend(o),
            Value::Null => {}
            other => {
                rec.insert("value".into(), other);
            }
        }
        let mut out = marea::sync::lock(&self.out);
        let Some(w) = out.as_mut() else { return };
        // Stamped under the lock, so `t` never decreases down the file whichever task writes.
        rec.insert("t".into(), json!(round_ms(self.start.elapsed())));
        let line = Value::Object(rec).to_string();
        let written = writeln!(w, "{line}").and_then(|()| {
            let mut last = marea::sync::lock(&self.last_flush);
            if last.elapsed() >= FLUSH_EVERY {
                *last = Instant::now();
                w.flush()
            } else {
                Ok(())
            }
        });
        match written {
            Ok(()) => {
                self.records.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => {
                // Stop writing: the rest of the run goes on without its log.
                *out = None;
                self.failed_with("", &e);
            }
        }
    }

    /// Keeps the run's first write error (`writing PATH{to}: ERROR`), reported at the end.
    fn failed_with(&self, to: &str, e: &std::io::Error) {
        marea::sync::lock(&self.failed)
            .get_or_insert_with(|| format!("writing {}{to}: {e}", self.path.display()));
    }

    /// Flushes what was recorded to the OS (a crash of this process loses none of it).
    pub fn flush(&self) {
        let mut out = marea::sync::lock(&self.out);
        if let Some(w) = out.as_mut() {
            if let Err(e) = w.flush() {
                *out = None;
                self.failed_with("", &e);
            }
        }
    }

    /// Flushes, then has the OS write the file to the disk itself (a power cut loses none of
    /// it). Blocks for as long as the disk takes, without holding up records meanwhile.
    pub fn sync_to_disk(&self) {
        self.flush();
        if let Err(e) = self.file.sync_data() {
            self.failed_with(" to disk", &e);
        }
    }

    /// Writes the `end` record and closes the file (the gzip trailer included).
    ///
    /// # Errors
    /// The first write error of the run, naming the file.
    pub fn finish(&self) -> Result<u64, String> {
        let n = self.records();
        self.record("end", json!({"records": n + 1}));
        let out = marea::sync::lock(&self.out).take();
        if let Some(mut w) = out {
            // Dropping a GzEncoder writes its trailer; flushing first surfaces errors.
            if let Err(e) = w.flush() {
                self.failed_with("", &e);
            }
            drop(w);
            if let Err(e) = self.file.sync_all() {
                self.failed_with(" to disk", &e);
            }
        }
        match marea::sync::lock(&self.failed).clone() {
            Some(e) => Err(e),
            None => Ok(self.records()),
        }
    }
}

/// Seconds with millisecond resolution, as `t` is written.
fn round_ms(d: Duration) -> f64 {
    (d.as_millis() as f64) / 1000.0
}

fn is_gz(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "gz")
}

/// The default log of a run: `<dir>/<mission>-<UTC>.jsonl.gz` (`usal run` gives `logs`, under
/// the current directory),
/// with a `-2`, `-3`... suffix when that second already has a log (runs of one mission started
/// in the same second, as parallel tests do, each get their own).
///
/// # Errors
/// As [`FlightLog::create`], but for a name taken: the next suffix is tried then.
pub fn create_default(
    dir: &Path,
    mission: &str,
    mission_file: &Path,
    domain: &str,
) -> Result<Arc<FlightLog>, FlightLogCreateError> {
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs();
    let stem = format!("{mission}-{}", utc_text(now, false));
    let mut n = 1;
    loop {
        let name = if n == 1 {
            format!("{stem}.jsonl.gz")
        } else {
            format!("{stem}-{n}.jsonl.gz")
        };
        match FlightLog::create(&dir.join(name), mission, mission_file, domain) {
            Err(FlightLogCreateError::Exists(_)) if n < 1000 => n += 1,
            other => return other,
        }
    }
}

/// UTC time of `secs` since the epoch: `2026-11-23T22:22:53Z` (`pretty`) or `20261123T222253Z`
/// (for file names).
pub fn utc_text(secs: u64, pretty: bool) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let (h, m, s) = (rem / 3600, rem % 3600 / 60, rem % 60);
    // Days to civil date (proleptic Gregorian), after Howard Hinnant's `civil_from_days`.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let mo = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(mo <= 2);
    if pretty {
        format!("{y:04}-{mo:02}-{d:02}T{h:02}:{m:02}:{s:02}Z")
    } else {
        format!("{y:04}{mo:02}{d:02}T{h:02}{m:02}{s:02}Z")
    }
}

/// Where the air-side logs of the run whose flight log is `log` are kept: beside it, one
/// directory per node (`logs/rover-demo-20261128T094500Z.air/air/vas-air.jsonl`), written by
/// each node's VAS (`vas --air-log`) and read by `usal replay` with the ground log.
pub fn air_dir(log: &Path) -> PathBuf {
    let name = log
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let stem = name
        .strip_suffix(".jsonl.gz")
        .or_else(|| name.strip_suffix(".jsonl"))
        .or_else(|| name.strip_suffix(".gz"))
        .unwrap_or(&name);
    log.with_file_name(format!("{stem}.air"))
}

/// The record kind of a value that travelled on the middleware, from its name and type.
pub fn kind_of(name: &str, type_name: &str) -> &'static str {
    let ty = type_name.rsplit("::").next().unwrap_or(type_name);
    match ty {
        "LinkHealth" => "link",
        "FlightState" | "StateChanged" => "state",
        "Alarm" | "Failsafe" => "alarm",
        "ManualCommand" | "ManualControl" | "CommandRecord" => "command",
        _ if type_name.starts_with("flightplan::") || name.split('/').any(|s| s == "fpma") => {
            "plan"
        }
        _ => "telemetry",
    }
}

/// What the recorder subscribes to, as (kind, pattern).
pub type Interest = (ItemKind, String);

/// The interests of a run: everything the stations' VAS and FPMa publish, the FMo's manual
/// control, and link health (only the radio's over a radio, so the log adds little air
/// traffic; every link's otherwise). Without a station: every variable and event.
pub fn interests(prefixes: &[String], radio: bool) -> Vec<Interest> {
    let mut out: Vec<Interest> = Vec::new();
    if prefixes.is_empty() {
        out.push((ItemKind::Variable, "**".into()));
        out.push((ItemKind::Event, "**".into()));
        return out;
    }
    for p in prefixes {
        let pat = format!("{p}/*");
        for kind in [ItemKind::Variable, ItemKind::Event] {
            if !out.contains(&(kind, pat.clone())) {
                out.push((kind, pat.clone()));
            }
        }
    }
    out.push((ItemKind::Variable, "**/fmo/manual_control".into()));
    let link = if radio {
        "**/link/radio/stats"
    } else {
        "**/link/*/stats"
    };
    out.push((ItemKind::Variable, link.into()));
    out
}

/// Records every value matching `interests` from a node of its own joined with `config`,
/// until `stop`; flushes the log every second and has it written to the disk every five.
///
/// # Errors
/// Joining the network or declaring an interest failed.
pub async fn record_items(
    log: Arc<FlightLog>,
    config: NetworkConfig,
    interests: Vec<Interest>,
    stop: CancellationToken,
) -> anyhow::Result<()> {
    use anyhow::Context;
    let node = Node::open(&config)
        .await
        .context("flight log: joining the network")?;
    let svc = node.service("flightlog")?;
    // The subscriptions run a moment past `stop`: the last plan events of a completed run
    // reach this node about when they reach the station that ended the run.
    let done = CancellationToken::new();
    let mut tasks = JoinSet::new();
    for (kind, pattern) in interests {
        let sub = svc
            .subscribe_raw(kind, &pattern)
            .with_context(|| format!("flight log: subscribing to {pattern}"))?;
        let (log, stop) = (log.clone(), done.clone());
        let item = if kind == ItemKind::Variable {
            "variable"
        } else {
            "event"
        };
        tasks.spawn(async move {
            loop {
                let v = tokio::select! {
                    () = stop.cancelled() => break,
                    v = sub.recv() => match v { Ok(v) => v, Err(_) => break },
                };
                let mut rec = json!({
                    "item": item,
                    "name": v.name,
                    "type": v.type_name,
                    "from": v.publisher,
                    "raw": hex(&v.payload),
                });
                if let Some(Ok(value)) = usal_json::to_json(&v.type_name, &v.payload) {
                    rec["value"] = value;
                }
                log.record(kind_of(&v.name, &v.type_name), rec);
            }
        });
    }
    let mut tick = tokio::time::interval(FLUSH_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut synced = Instant::now();
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            _ = tick.tick() => {
                if synced.elapsed() >= SYNC_EVERY {
                    synced = Instant::now();
                    let log = log.clone();
                    // fsync can take the disk's time: off the runtime's workers.
                    let _ = tokio::task::spawn_blocking(move || log.sync_to_disk()).await;
                } else {
                    log.flush();
                }
            }
        }
    }
    tokio::time::sleep(LAST_WORDS).await;
    done.cancel();
    while tasks.join_next().await.is_some() {}
    drop(svc);
    node.shutdown().await;
    log.flush();
    Ok(())
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// Hex back to bytes; `None` when not an even run of hex digits.
pub fn unhex(s: &str) -> Option<Vec<u8>> {
    if s.len() % 2 != 0 {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| s.get(i..i + 2).and_then(|h| u8::from_str_radix(h, 16).ok()))
        .collect()
}

/// Reads a flight log record by record, with line numbers for errors.
pub struct LogReader {
    path: PathBuf,
    lines: Box<dyn BufRead + Send>,
    line: u64,
    buf: String,
}

impl LogReader {
    /// Opens `path` (gzip or plain, told by its first bytes) and reads its header.
    ///
    /// # Errors
    /// The file cannot be read, is empty, has no valid header, or is of a newer version.
    pub fn open(path: &Path) -> Result<(LogReader, Value), FlightLogReadError> {
        let open = |source| FlightLogReadError::Open {
            path: path.to_owned(),
            source,
        };
        let mut file = File::open(path).map_err(open)?;
        let mut magic = [0u8; 2];
        let gz = file.read_exact(&mut magic).is_ok() && magic == [0x1f, 0x8b];
        let file = File::open(path).map_err(open)?;
        let lines: Box<dyn BufRead + Send> = if gz {
            Box::new(BufReader::new(GzDecoder::new(BufReader::new(file))))
        } else {
            Box::new(BufReader::new(file))
        };
        let mut r = LogReader {
            path: path.to_owned(),
            lines,
            line: 0,
            buf: String::new(),
        };
        let header = r
            .next_value()?
            .ok_or_else(|| FlightLogReadError::Empty(path.to_owned()))?;
        if header.get("format").and_then(Value::as_str) != Some(FORMAT) {
            return Err(r.bad(format!(
                "not a flight log header (no \"format\":\"{FORMAT}\")"
            )));
        }
        match header.get("version").and_then(Value::as_u64) {
            Some(v) if v > VERSION => {
                return Err(FlightLogReadError::NewerVersion {
                    path: path.to_owned(),
                    found: v,
                })
            }
            Some(_) => {}
            None => return Err(r.bad("the header has no version".into())),
        }
        Ok((r, header))
    }

    /// An error about the last line read.
    pub fn bad(&self, what: String) -> FlightLogReadError {
        FlightLogReadError::BadLine {
            path: self.path.clone(),
            line: self.line,
            what,
        }
    }

    fn next_value(&mut self) -> Result<Option<Value>, FlightLogReadError> {
        loop {
            self.buf.clear();
            let n = self.lines.read_line(&mut self.buf).map_err(|source| {
                FlightLogReadError::Truncated {
                    path: self.path.clone(),
                    line: self.line,
                    source,
                }
            })?;
            if n == 0 {
                return Ok(None);
            }
            self.line += 1;
            if !self.buf.ends_with('\n') {
                return Err(FlightLogReadError::Truncated {
                    path: self.path.clone(),
                    line: self.line - 1,
                    source: std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        format!("line {} ends without a newline", self.line),
                    ),
                });
            }
            if self.buf.trim().is_empty() {
                continue;
            }
            let v: Value =
                serde_json::from_str(&self.buf).map_err(|e| self.bad(format!("not JSON: {e}")))?;
            if !v.is_object() {
                return Err(self.bad("not a JSON object".into()));
            }
            return Ok(Some(v));
        }
    }

    /// The next record, checked to have `t` (seconds, 0 or more) and `kind`.
    ///
    /// # Errors
    /// A truncated or corrupt file, or a line that is not a record; both name the line.
    pub fn next_record(&mut self) -> Result<Option<Record>, FlightLogReadError> {
        let Some(v) = self.next_value()? else {
            return Ok(None);
        };
        let t = v
            .get("t")
            .and_then(Value::as_f64)
            .filter(|t| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| self.bad("no time \"t\" (seconds since the start)".into()))?;
        let kind = v
            .get("kind")
            .and_then(Value::as_str)
            .ok_or_else(|| self.bad("no \"kind\"".into()))?
            .to_owned();
        Ok(Some(Record {
            line: self.line,
            t,
            kind,
            fields: v,
        }))
    }
}

/// One record of a flight log.
#[derive(Debug, Clone)]
pub struct Record {
    /// Its line in the file.
    pub line: u64,
    /// Seconds since the start of the run.
    pub t: f64,
    /// Its kind.
    pub kind: String,
    /// The whole record.
    pub fields: Value,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_text_is_the_civil_date() {
        assert_eq!(utc_text(0, true), "1970-01-01T00:00:00Z");
        assert_eq!(utc_text(951_782_400, true), "2000-02-29T00:00:00Z");
        assert_eq!(utc_text(1_795_472_573, false), "20261123T222253Z");
    }

    #[test]
    fn kinds_follow_name_and_type() {
        assert_eq!(
            kind_of("rover1/vas/position", "usal_types::Position"),
            "telemetry"
        );
        assert_eq!(
            kind_of("rover1/vas/flight_state", "usal_types::FlightState"),
            "state"
        );
        assert_eq!(
            kind_of("rover1/fpma/progress", "flightplan::api::Progress"),
            "plan"
        );
        assert_eq!(
            kind_of("gcs/link/radio/stats", "marea::node::health::LinkHealth"),
            "link"
        );
        assert_eq!(
            kind_of("gcs/fmo/manual_control", "usal_types::ManualCommand"),
            "command"
        );
    }

    #[test]
    fn a_log_round_trips_and_a_cut_one_names_its_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a/b.jsonl.gz");
        let log = FlightLog::create(&path, "m", Path::new("m.xml"), "d").unwrap();
        for i in 0..200 {
            log.record(
                "telemetry",
                json!({"name": "x/vas/n", "i": i, "pad": "y".repeat(50)}),
            );
        }
        assert_eq!(log.finish().unwrap(), 201);
        assert!(matches!(
            FlightLog::create(&path, "m", Path::new("m.xml"), "d"),
            Err(FlightLogCreateError::Exists(_))
        ));
        let (mut r, header) = LogReader::open(&path).unwrap();
        assert_eq!(header["mission"], "m");
        let mut n = 0;
        while let Some(rec) = r.next_record().unwrap() {
            n += 1;
            assert_eq!(rec.line, n + 1);
        }
        assert_eq!(n, 201);
        // Half the compressed bytes: an error naming the last whole line, not a panic.
        let bytes = std::fs::read(&path).unwrap();
        let cut = dir.path().join("cut.jsonl.gz");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let (mut r, _) = LogReader::open(&cut).unwrap();
        let err = loop {
            match r.next_record() {
                Ok(Some(_)) => {}
                Ok(None) => panic!("a cut log read to its end"),
                Err(e) => break e,
            }
        };
        assert!(matches!(err, FlightLogReadError::Truncated { .. }), "{err}");
        assert!(err.to_string().contains("after line"), "{err}");
    }

    #[test]
    fn what_was_synced_to_disk_reads_back_before_the_log_is_finished() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("live.jsonl.gz");
        let log = FlightLog::create(&path, "m", Path::new("m.xml"), "d").unwrap();
        for i in 0..10 {
            log.record("note", json!({"i": i}));
        }
        log.sync_to_disk();
        // Read as a pilot would after a power cut: every synced record, then the cut.
        let (mut r, _) = LogReader::open(&path).unwrap();
        let mut seen = Vec::new();
        let end = loop {
            match r.next_record() {
                Ok(Some(rec)) => seen.push(rec.fields["i"].as_u64().unwrap()),
                Ok(None) => break None,
                Err(e) => break Some(e),
            }
        };
        assert_eq!(seen, (0..10).collect::<Vec<_>>());
        assert!(
            matches!(end, Some(FlightLogReadError::Truncated { .. })),
            "no trailer yet: {end:?}"
        );
        assert_eq!(log.finish().unwrap(), 11);
    }

    #[test]
    fn default_logs_of_one_second_get_their_own_names() {
        let dir = tempfile::tempdir().unwrap();
        let logs = dir.path().join("logs");
        let a = create_default(&logs, "m", Path::new("m.xml"), "d").unwrap();
        let b = create_default(&logs, "m", Path::new("m.xml"), "d").unwrap();
        assert_ne!(a.path(), b.path());
        let name = a.path().file_name().unwrap().to_str().unwrap().to_owned();
        assert!(
            name.starts_with("m-") && name.ends_with("Z.jsonl.gz"),
            "{name}"
        );
    }

    #[test]
    fn hex_round_trips_and_refuses_junk() {
        assert_eq!(
            unhex(&hex(&[0, 1, 0xab, 0xff])),
            Some(vec![0, 1, 0xab, 0xff])
        );
        assert_eq!(unhex("abc"), None);
        assert_eq!(unhex("zz"), None);
    }
}

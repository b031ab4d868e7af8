//! `usal replay LOG`: plays a flight log (see `flightlog`) back into a system: every recorded
//! variable and event is published again under its recorded name and type, at the recorded
//! pace (times `--speed`), so an FMo and an FPMo joined to the same domain show the flight as
//! the pilot saw it. Nothing is called: commands in the log are shown, not sent again.
//!
//! The air-side logs the run's VASes kept beside it (`flightlog::air_dir`) are shown with it,
//! each record at its time: what the vehicle saw, also while the ground link was lost.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use marea::protocol::ItemKind;
use marea::Node;
use serde_json::{json, Value};
use tokio::time::Instant;

use super::flightlog::{unhex, FlightLogReadError, LogReader, Record};

/// Prints a line on stdout; a closed stdout (`usal replay LOG | head`) is not an error worth
/// a panic: the replay goes on publishing for the stations.
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout().lock(), $($arg)*);
    }};
}

/// `usal replay` arguments.
#[derive(clap::Args)]
pub struct ReplayArgs {
    /// The flight log written by `usal run` (logs/<mission>-<UTC>.jsonl.gz).
    pub log: PathBuf,
    /// Playback speed: 2 plays twice as fast as recorded.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Start this many seconds into the flight (earlier records are skipped).
    #[arg(long, default_value_t = 0.0)]
    pub from_s: f64,
    /// Replay the readable part of a truncated or corrupt log (a run that was killed) instead
    /// of refusing it.
    #[arg(long)]
    pub partial: bool,
}

/// What a first pass over the log found.
struct Scan {
    header: Value,
    /// Records to publish, by (name, item kind) with their type.
    items: BTreeMap<(String, bool), String>,
    records: u64,
    duration: f64,
    /// The error that ended the pass early, if any.
    broken: Option<FlightLogReadError>,
}

/// A record that went over the middleware: (name, is_event, type, raw bytes).
type Published = (String, bool, String, Vec<u8>);

fn published(r: &Record, reader: &LogReader) -> Result<Option<Published>, FlightLogReadError> {
    let f = &r.fields;
    let (Some(name), Some(raw)) = (f.get("name").and_then(Value::as_str), f.get("raw")) else {
        return Ok(None);
    };
    let event = match f.get("item").and_then(Value::as_str) {
        Some("variable") => false,
        Some("event") => true,
        _ => return Err(reader.bad("\"item\" must be \"variable\" or \"event\"".into())),
    };
    let ty = f
        .get("type")
        .and_then(Value::as_str)
        .ok_or_else(|| reader.bad("no \"type\"".into()))?;
    let bytes = raw
        .as_str()
        .and_then(unhex)
        .ok_or_else(|| reader.bad("\"raw\" is not hex".into()))?;
    Ok(Some((name.to_owned(), event, ty.to_owned(), bytes)))
}

fn scan(path: &Path) -> Result<Scan, FlightLogReadError> {
    let (mut reader, header) = LogReader::open(path)?;
    let mut s = Scan {
        header,
        items: BTreeMap::new(),
        records: 0,
        duration: 0.0,
        broken: None,
    };
    loop {
        let r = match reader.next_record() {
            Ok(Some(r)) => r,
            Ok(None) => break,
            Err(e) => {
                s.broken = Some(e);
                break;
            }
        };
        match published(&r, &reader) {
            Ok(Some((name, event, ty, _))) => {
                s.items.entry((name, event)).or_insert(ty);
            }
            Ok(None) => {}
            Err(e) => {
                s.broken = Some(e);
                break;
            }
        }
        s.records += 1;
        s.duration = s.duration.max(r.t);
    }
    Ok(s)
}

/// One record of an air-side log: when (seconds from the ground log's start), which node,
/// and the record.
struct AirRecord {
    t: f64,
    node: String,
    record: Value,
}

/// The air-side records of the run whose log is `log` (none when it kept none), oldest first;
/// `started_unix_ms` is the ground log's start. Unreadable lines are counted.
fn air_records(log: &Path, started_unix_ms: Option<u64>) -> (Vec<AirRecord>, usize) {
    let (mut out, mut bad) = (Vec::new(), 0);
    let Some(start) = started_unix_ms else {
        return (out, bad);
    };
    let Ok(nodes) = std::fs::read_dir(super::flightlog::air_dir(log)) else {
        return (out, bad);
    };
    for entry in nodes.flatten() {
        let node = entry.file_name().to_string_lossy().into_owned();
        // The rotated file first: it holds the older records.
        let texts: Vec<String> = ["vas-air.1.jsonl", "vas-air.jsonl"]
            .iter()
            .filter_map(|file| std::fs::read_to_string(entry.path().join(file)).ok())
            .collect();
        for line in texts.iter().flat_map(|t| t.lines()) {
            if line.trim().is_empty() {
                continue;
            }
            let v: Value = serde_json::from_str(line).unwrap_or(Value::Null);
            if v["format"].is_string() {
                continue; // a file's header
            }
            match (v["unix_ms"].as_u64(), v["kind"].is_string()) {
                (Some(ms), true) => out.push(AirRecord {
                    t: (ms as f64 - start as f64) / 1000.0,
                    node: node.clone(),
                    record: v,
                }),
                _ => bad += 1,
            }
        }
    }
    out.sort_by(|a, b| a.t.total_cmp(&b.t));
    (out, bad)
}

/// A `CommandRecord` (as JSON) as words: `from gcs/station change_state(WaypointNavigation)
/// -> ok: ...`.
fn command_record_text(v: &Value) -> String {
    let s = |k: &str| v[k].as_str().unwrap_or("?").to_owned();
    format!(
        "from {} {}({}) -> {}: {}",
        s("from"),
        s("command"),
        s("args"),
        if v["ok"] == true { "ok" } else { "refused" },
        s("answer")
    )
}

/// An air-side record as a line: `air air: command ground/gs change_state(...) -> ok: ...`.
fn show_air(a: &AirRecord, json_out: bool) {
    let r = &a.record;
    let s = |k: &str| r[k].as_str().unwrap_or("?").to_owned();
    let text = match r["kind"].as_str().unwrap_or("?") {
        "command" => format!("command {}", command_record_text(r)),
        "state" => format!("state {} -> {} ({})", s("from"), s("to"), s("cause")),
        "failsafe" => format!(
            "failsafe {} ({}): {}",
            s("failsafe"),
            s("action"),
            s("text")
        ),
        "alarm" => format!("alarm {}: {}", s("severity"), s("text")),
        kind => format!("{kind} {}", r),
    };
    if json_out {
        say!(
            "{}",
            json!({"event": "air_record", "t": a.t, "node": a.node, "kind": r["kind"], "text": text})
        );
    } else {
        say!("[{:>7.1} s] air {}: {text}", a.t, a.node);
    }
}

/// Runs `usal replay` on `node` (already joined); `wait` is the discovery time given to
/// stations before the first record.
///
/// # Errors
/// Declaring the publishers failed; a bad log is reported and returned as an exit status.
pub async fn run(
    node: &Node,
    args: &ReplayArgs,
    wait: Duration,
    json_out: bool,
) -> anyhow::Result<ExitCode> {
    if !(args.speed.is_finite() && args.speed >= 0.01) {
        eprintln!("usal replay: --speed must be at least 0.01");
        return Ok(ExitCode::from(2));
    }
    if !(args.from_s.is_finite() && args.from_s >= 0.0) {
        eprintln!("usal replay: --from-s must be a number of seconds, 0 or more");
        return Ok(ExitCode::from(2));
    }
    let path = &args.log;
    let scan = match tokio::task::block_in_place(|| scan(path)) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("usal replay: {e}");
            return Ok(ExitCode::FAILURE);
        }
    };
    if let Some(e) = &scan.broken {
        if !args.partial {
            eprintln!("usal replay: {e} (--partial replays what comes before)");
            return Ok(ExitCode::FAILURE);
        }
        eprintln!(
            "usal replay: {e}; replaying the {} records before it",
            scan.records
        );
    }
    // One publisher per recorded item, declared before playing so stations discover them
    // all during `wait` and no early event goes unheard.
    let mut services: BTreeMap<String, marea::Service> = BTreeMap::new();
    let mut publishers: BTreeMap<(String, bool), usal_json::Replayer> = BTreeMap::new();
    let mut skipped: Vec<String> = Vec::new();
    for ((name, event), ty) in &scan.items {
        let Some((prefix, item)) = name.rsplit_once('/') else {
            skipped.push(format!("{name} (no service in the name)"));
            continue;
        };
        let svc = match services.get(prefix) {
            Some(s) => s.clone(),
            None => {
                let s = node
                    .service(prefix)
                    .with_context(|| format!("declaring service {prefix}"))?;
                services.insert(prefix.to_owned(), s.clone());
                s
            }
        };
        let kind = if *event {
            ItemKind::Event
        } else {
            ItemKind::Variable
        };
        match usal_json::replayer(ty, &svc, kind, item) {
            Ok(p) => {
                publishers.insert((name.clone(), *event), p);
            }
            Err(e) => skipped.push(format!("{name}: {e}")),
        }
    }
    let mission = scan.header["mission"].as_str().unwrap_or("?").to_owned();
    let started = scan.header["started_utc"]
        .as_str()
        .unwrap_or("?")
        .to_owned();
    if json_out {
        say!(
            "{}",
            json!({"event": "replaying", "log": path.display().to_string(), "mission": mission,
                "flown_utc": started, "records": scan.records, "duration_s": scan.duration,
                "items": publishers.len(), "speed": args.speed, "skipped": skipped})
        );
    } else {
        say!(
            "replaying {} (mission {mission}, flown {started}): {} records over {:.1} s, {} items, at {}x",
            path.display(),
            scan.records,
            scan.duration,
            publishers.len(),
            args.speed,
        );
        for s in &skipped {
            say!("  not replayed: {s}");
        }
    }
    let (air, air_bad) = air_records(path, scan.header["started_unix_ms"].as_u64());
    if !air.is_empty() || air_bad > 0 {
        let nodes: std::collections::BTreeSet<&str> = air.iter().map(|a| a.node.as_str()).collect();
        if json_out {
            say!(
                "{}",
                json!({"event": "air_logs", "records": air.len(), "nodes": nodes, "unreadable": air_bad})
            );
        } else {
            say!(
                "with the air-side logs of {}: {} records{}",
                nodes.into_iter().collect::<Vec<_>>().join(", "),
                air.len(),
                if air_bad > 0 {
                    format!(" ({air_bad} unreadable lines skipped)")
                } else {
                    String::new()
                }
            );
        }
    }
    let mut air = std::collections::VecDeque::from(air);
    // The stations say REPLAY while this is fresh (twice a second, the discovery wait included).
    let status = usal_types::ReplayStatus {
        log: path.display().to_string(),
        mission: mission.clone(),
        flown_utc: started.clone(),
        at_s: args.from_s,
        duration_s: scan.duration,
        speed: args.speed,
        ended: false,
    };
    let (at_tx, status_task) = announce_replay(node, status)?;
    tokio::time::sleep(wait).await;

    let (mut reader, _) = match tokio::task::block_in_place(|| LogReader::open(path)) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("usal replay: {e}");
            return Ok(ExitCode::FAILURE);
        }
    };
    let start = Instant::now();
    let (mut sent, mut errors) = (0u64, 0u64);
    let mut last_state = String::new();
    for _ in 0..scan.records {
        // The first pass read these records whole.
        let Ok(Some(r)) = tokio::task::block_in_place(|| reader.next_record()) else {
            break;
        };
        if r.t < args.from_s {
            continue;
        }
        while air.front().is_some_and(|a| a.t <= r.t) {
            if let Some(a) = air.pop_front().filter(|a| a.t >= args.from_s) {
                show_air(&a, json_out);
            }
        }
        let at = start + Duration::from_secs_f64((r.t - args.from_s) / args.speed);
        tokio::time::sleep_until(at).await;
        at_tx.send_replace((r.t, false));
        if let Ok(Some((name, event, _, bytes))) = published(&r, &reader) {
            if let Some(p) = publishers.get(&(name.clone(), event)) {
                match p(&bytes) {
                    Ok(()) => sent += 1,
                    Err(e) => {
                        errors += 1;
                        eprintln!("usal replay: line {}: {name}: {e}", r.line);
                    }
                }
            }
        }
        show(&r, &mut last_state, json_out);
    }
    for a in air.iter().filter(|a| a.t >= args.from_s) {
        show_air(a, json_out);
    }
    at_tx.send_replace((scan.duration, true));
    // Let the last values (the replay's end among them) leave before the node goes.
    tokio::time::sleep(Duration::from_millis(600)).await;
    status_task.abort();
    if json_out {
        say!(
            "{}",
            json!({"event": "replayed", "published": sent, "errors": errors,
                "elapsed_s": start.elapsed().as_secs_f64()})
        );
    } else {
        say!(
            "replayed {sent} values and events of {} in {:.1} s{}",
            path.display(),
            start.elapsed().as_secs_f64(),
            if errors > 0 {
                format!(" ({errors} could not be published)")
            } else {
                String::new()
            }
        );
    }
    Ok(if errors > 0 || scan.broken.is_some() {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// Where the playback is: seconds into the recorded flight, and whether it has ended.
type PlaybackAt = tokio::sync::watch::Sender<(f64, bool)>;

/// Publishes `replay/status` twice a second from `status`, its time and end as the returned
/// sender gives them, until the returned task is aborted.
fn announce_replay(
    node: &Node,
    mut status: usal_types::ReplayStatus,
) -> anyhow::Result<(PlaybackAt, tokio::task::JoinHandle<()>)> {
    let svc = node.service("replay").context("declaring service replay")?;
    let var = usal_types::items::replay::STATUS
        .publish(&svc)
        .context("declaring replay/status")?;
    let (tx, rx) = tokio::sync::watch::channel((status.at_s, false));
    let task = tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(500));
        loop {
            tick.tick().await;
            (status.at_s, status.ended) = *rx.borrow();
            let _ = var.set(&status);
        }
    });
    Ok((tx, task))
}

/// Shows the records a reviewer follows: state changes, plan events, commands and the
/// launcher's waypoint lines.
fn show(r: &Record, last_state: &mut String, json_out: bool) {
    let f = &r.fields;
    let text = match r.kind.as_str() {
        "state" => {
            // The state_changed events say it all (from, to, why); the flight_state variable
            // only for the state before the first change.
            let v = &f["value"];
            match (v.as_str(), v.get("to").and_then(Value::as_str)) {
                (Some(state), _) if last_state.is_empty() => {
                    state.clone_into(last_state);
                    format!("state {state}")
                }
                (_, Some(to)) => {
                    let from = v["from"].as_str().unwrap_or("?");
                    to.clone_into(last_state);
                    format!(
                        "state {from} -> {to} ({})",
                        v["cause"].as_str().unwrap_or("-")
                    )
                }
                _ => return,
            }
        }
        "plan" if f["item"] == "event" => plan_event(f),
        "alarm" => format!("alarm {}", f["value"]),
        // A command a service received (`commands`): who sent it and the answer.
        "command" if f["value"]["from"].is_string() => format!(
            "command to {} {}",
            f["name"]
                .as_str()
                .unwrap_or("?")
                .trim_end_matches("/commands"),
            command_record_text(&f["value"])
        ),
        "command" if f["item"].is_null() => {
            let answer = f
                .get("answer")
                .or_else(|| f.get("error"))
                .unwrap_or(&Value::Null);
            format!(
                "command {} {} -> {answer}",
                f["name"].as_str().unwrap_or("?"),
                f["args"]
            )
        }
        _ => return,
    };
    if json_out {
        say!(
            "{}",
            json!({"event": "record", "t": r.t, "kind": r.kind, "text": text})
        );
    } else {
        say!("[{:>7.1} s] {text}", r.t);
    }
}

/// A plan event as a line: `plan_event WaypointReached leg=area seq=2` (the raw JSON for an
/// unexpected shape).
fn plan_event(f: &Value) -> String {
    let name = f["name"].as_str().unwrap_or("?");
    let item = name.rsplit('/').next().unwrap_or(name);
    let kind = &f["value"]["kind"];
    let text = match kind {
        Value::String(k) => k.clone(),
        Value::Object(o) if o.len() == 1 => {
            let (k, v) = o.iter().next().expect("one entry");
            let args: Vec<String> = match v {
                Value::Object(a) => a
                    .iter()
                    .map(|(n, x)| match x {
                        Value::String(t) => format!("{n}={t}"),
                        other => format!("{n}={other}"),
                    })
                    .collect(),
                Value::Null => Vec::new(),
                other => vec![other.to_string()],
            };
            format!("{k} {}", args.join(" ")).trim_end().to_owned()
        }
        _ => f["value"].to_string(),
    };
    format!("{item} {text}")
}

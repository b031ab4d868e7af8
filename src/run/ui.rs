//! What `usal run` prints: children's log lines prefixed with their node and service, the
//! launcher's own notes, and the live progress of the flight plan (a bar redrawn in place when
//! stderr is a terminal, plain lines otherwise, JSON lines on stdout with `--json`).

use std::io::{IsTerminal, Write};
use std::sync::Mutex;

use serde_json::Value;

/// The launcher's output, shared by the supervisor's and the station's tasks.
pub struct Ui {
    json: bool,
    /// Children's routine lines shown too ([`routine`]).
    verbose: bool,
    tty: bool,
    /// The progress bar now on screen (tty only), redrawn under every log line.
    bar: Mutex<Option<String>>,
    /// In a mission of several vehicles: each vehicle's part of the bar, in first-seen order.
    parts: Mutex<Vec<(String, String)>>,
    /// The run's flight log, which gets every note and progress record as a `note`.
    log: std::sync::OnceLock<std::sync::Arc<super::flightlog::FlightLog>>,
}

/// A child's line a pilot does not need, shown only with `--verbose`: a gateway's table of what
/// it forwards (`{"forwarded": N, "added": [..], "removed": [..]}`), rewritten at every change of
/// the routes, which made most of a radio mission's output.
fn routine(line: &str) -> bool {
    // Parsed only when it may be one: every child line passes here.
    line.starts_with('{')
        && line.contains("\"forwarded\":")
        && serde_json::from_str::<Value>(line).is_ok_and(|v| v.get("forwarded").is_some())
}

impl Ui {
    /// Output for this process: a bar only when stderr is a terminal and JSON is off.
    pub fn new(json: bool) -> Ui {
        Ui {
            json,
            verbose: false,
            tty: !json && std::io::stderr().is_terminal(),
            bar: Mutex::new(None),
            parts: Mutex::new(Vec::new()),
            log: std::sync::OnceLock::new(),
        }
    }

    /// Shows the children's routine lines too (`usal run --verbose`).
    pub fn verbose(mut self, on: bool) -> Ui {
        self.verbose = on;
        self
    }

    /// Copies every note, progress record and result into `log` from now on.
    pub fn set_log(&self, log: std::sync::Arc<super::flightlog::FlightLog>) {
        let _ = self.log.set(log);
    }

    fn tee(&self, json: &Value) {
        if let Some(l) = self.log.get() {
            l.record("note", serde_json::json!({ "record": json }));
        }
    }

    /// Whether a progress bar is drawn (else progress comes as lines).
    pub fn is_tty(&self) -> bool {
        self.tty
    }

    /// Writes `text` as whole lines on stderr, keeping the bar below them.
    fn stderr_lines(&self, text: &str) {
        let bar = marea::sync::lock(&self.bar);
        let mut err = std::io::stderr().lock();
        if bar.is_some() {
            let _ = write!(err, "\r\x1b[2K");
        }
        let _ = writeln!(err, "{text}");
        if let Some(b) = bar.as_deref() {
            let _ = write!(err, "{b}");
        }
        let _ = err.flush();
    }

    /// One log line of a child, as `[node/service] line`.
    pub fn child_line(&self, label: &str, line: &str) {
        if !self.verbose && routine(line) {
            return;
        }
        self.stderr_lines(&format!("[{label}] {line}"));
    }

    /// A note of the launcher: `[usal] text` on stderr, or `json` on stdout with `--json`.
    pub fn note(&self, text: &str, json: Value) {
        self.tee(&json);
        if self.json {
            println!("{json}");
        } else {
            self.stderr_lines(&format!("[usal] {text}"));
        }
    }

    /// A progress update: the bar on a terminal; otherwise a line when `line` is given (the
    /// caller decides which updates are worth a line) and the JSON record with `--json`.
    pub fn progress(&self, bar: &str, line: Option<&str>, json: Option<Value>) {
        if let Some(j) = &json {
            self.tee(j);
        }
        if self.tty {
            let mut b = marea::sync::lock(&self.bar);
            let mut err = std::io::stderr().lock();
            let _ = write!(err, "\r\x1b[2K{bar}");
            let _ = err.flush();
            *b = Some(bar.to_owned());
        } else if self.json {
            if let Some(j) = json {
                println!("{j}");
            }
        } else if let Some(l) = line {
            self.stderr_lines(&format!("[usal] {l}"));
        }
    }

    /// A progress update of one vehicle of several (`vehicle` set): the bar shows every
    /// vehicle's part side by side, the line is prefixed with the vehicle and the JSON record
    /// names it. Without a vehicle, [`Ui::progress`].
    pub fn progress_of(
        &self,
        vehicle: Option<&str>,
        bar: &str,
        line: Option<&str>,
        json: Option<Value>,
    ) {
        let Some(v) = vehicle else {
            return self.progress(bar, line, json);
        };
        let joined = {
            let mut parts = marea::sync::lock(&self.parts);
            match parts.iter_mut().find(|(k, _)| k == v) {
                Some(p) => bar.clone_into(&mut p.1),
                None => parts.push((v.to_owned(), bar.to_owned())),
            }
            join_parts(&parts)
        };
        let line = line.map(|l| format!("{v}: {l}"));
        let json = json.map(|mut j| {
            if let Some(o) = j.as_object_mut() {
                o.insert("vehicle".into(), v.into());
            }
            j
        });
        self.progress(&joined, line.as_deref(), json);
    }

    /// Removes the bar (before the summary and at exit).
    pub fn clear_bar(&self) {
        let mut b = marea::sync::lock(&self.bar);
        if b.take().is_some() {
            let mut err = std::io::stderr().lock();
            let _ = write!(err, "\r\x1b[2K");
            let _ = err.flush();
        }
    }

    /// The result of the run on stdout: `text` lines, or `json` with `--json`.
    pub fn result(&self, text: &str, json: Value) {
        self.tee(&json);
        self.clear_bar();
        if self.json {
            println!("{json}");
        } else {
            println!("{text}");
        }
    }
}

/// Vehicles' bars on one line: `rover1 [###-] 30% ... | rover2 ...`.
fn join_parts(parts: &[(String, String)]) -> String {
    parts
        .iter()
        .map(|(k, b)| format!("{k} {b}"))
        .collect::<Vec<_>>()
        .join(" | ")
}

/// A text progress bar of `width` cells for `fraction` in [0, 1].
pub fn bar(fraction: f64, width: usize) -> String {
    let f = if fraction.is_finite() {
        fraction.clamp(0.0, 1.0)
    } else {
        0.0
    };
    // Rounded down so a bar is full only at completion.
    let full = ((f * width as f64) as usize).min(width);
    format!("[{}{}]", "#".repeat(full), "-".repeat(width - full))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_gateway_tables_are_routine() {
        assert!(routine(
            r#"{"forwarded":3,"added":["variable rover1/vas/position from air"],"removed":[]}"#
        ));
        assert!(!routine(r#"{"ready":"air-gw","gateway":true,"links":[]}"#));
        assert!(!routine(
            "... INFO vas::val: flight state CONFIGURE_CHECK -> PARKING"
        ));
    }

    #[test]
    fn bars_are_full_only_at_one() {
        assert_eq!(bar(0.0, 4), "[----]");
        assert_eq!(bar(0.99, 4), "[###-]");
        assert_eq!(bar(1.0, 4), "[####]");
        assert_eq!(bar(f64::NAN, 2), "[--]");
        assert_eq!(bar(7.0, 2), "[##]");
    }

    #[test]
    fn a_fleet_bar_shows_every_vehicle_in_first_seen_order() {
        let ui = Ui::new(false);
        ui.progress_of(Some("rover1"), "[#-] 50%", None, None);
        ui.progress_of(Some("rover2"), "[--] 0%", None, None);
        ui.progress_of(Some("rover1"), "[##] 100%", None, None);
        let parts = marea::sync::lock(&ui.parts);
        assert_eq!(join_parts(&parts), "rover1 [##] 100% | rover2 [--] 0%");
    }
}

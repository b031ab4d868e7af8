//! The VAS's air-side log: what the vehicle's side saw of the flight (its flight states, every
//! command it received with who sent it and its answer, the MAVLink mission traffic it drove,
//! failsafes and alarms), written where the VAS runs, so a flight whose ground link was lost
//! can still be reviewed. `usal replay` reads it next to the ground's flight log.
//!
//! # Format
//!
//! JSON lines in `DIR/vas-air.jsonl`, one record per line:
//! `{"unix_ms":1795472573000,"kind":"state"|"command"|"mission"|"failsafe"|"alarm", ...}`
//! (`unix_ms`: the wall clock, which the ground log's header relates to its own times). The
//! first line of each file is the header `{"format":"usal-air-log","version":1,...}`.
//!
//! Bounded: when the file passes its size limit it becomes `vas-air.1.jsonl` (replacing the
//! one before) and a new file starts, so the log holds at most about twice the limit, the
//! newest records always kept. Written line by line and flushed, so a killed VAS leaves every
//! record it made.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};

/// The header's `format`.
pub const FORMAT: &str = "usal-air-log";
/// The name of the current file in the log's directory.
pub const FILE: &str = "vas-air.jsonl";
/// The name of the previous (rotated) file.
pub const ROTATED: &str = "vas-air.1.jsonl";

/// An open air-side log.
pub struct AirLog {
    dir: PathBuf,
    max_bytes: u64,
    out: Mutex<Out>,
}

struct Out {
    file: File,
    bytes: u64,
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

impl AirLog {
    /// Opens (appends to) the log in `dir`, created if needed, rotated past `max_bytes`.
    ///
    /// # Errors
    /// The directory or the file cannot be created.
    pub fn open(dir: &Path, max_bytes: u64) -> std::io::Result<AirLog> {
        std::fs::create_dir_all(dir)?;
        let out = Self::open_file(dir)?;
        let log = AirLog {
            dir: dir.to_owned(),
            max_bytes: max_bytes.max(4096),
            out: Mutex::new(out),
        };
        Ok(log)
    }

    fn open_file(dir: &Path) -> std::io::Result<Out> {
        let path = dir.join(FILE);
        let mut file = OpenOptions::new().create(true).append(true).open(&path)?;
        let mut bytes = file.metadata()?.len();
        if bytes == 0 {
            let header = json!({"format": FORMAT, "version": 1, "unix_ms": unix_ms()});
            let line = format!("{header}\n");
            file.write_all(line.as_bytes())?;
            bytes = line.len() as u64;
        }
        Ok(Out { file, bytes })
    }

    /// Appends a record of `kind` with `fields` (an object); a write error is logged, never
    /// raised: the log must not stop the vehicle.
    pub fn record(&self, kind: &str, fields: Value) {
        let mut rec = json!({"unix_ms": unix_ms(), "kind": kind});
        if let (Some(r), Value::Object(f)) = (rec.as_object_mut(), fields) {
            r.extend(f);
        }
        let line = format!("{rec}\n");
        let mut out = marea::sync::lock(&self.out);
        if out.bytes + line.len() as u64 > self.max_bytes {
            if let Err(e) = self.rotate(&mut out) {
                tracing::warn!("air log {}: rotating: {e}", self.dir.display());
            }
        }
        match out.file.write_all(line.as_bytes()) {
            Ok(()) => out.bytes += line.len() as u64,
            Err(e) => tracing::warn!("air log {}: {e}", self.dir.display()),
        }
    }

    fn rotate(&self, out: &mut Out) -> std::io::Result<()> {
        out.file.flush()?;
        std::fs::rename(self.dir.join(FILE), self.dir.join(ROTATED))?;
        *out = Self::open_file(&self.dir)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // What `usal replay` does with the files (it reads them itself: `usal` does not depend on
    // the VAS), for the tests here.
    /// Reads the records of the air log in `dir`, oldest first (the rotated file, then the
    /// current one); lines that do not read are skipped and counted.
    ///
    /// # Errors
    /// Neither file can be read.
    fn read(dir: &Path) -> std::io::Result<(Vec<Value>, usize)> {
        let mut records = Vec::new();
        let mut bad = 0;
        let mut found = false;
        for name in [ROTATED, FILE] {
            let text = match std::fs::read_to_string(dir.join(name)) {
                Ok(t) => t,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(e),
            };
            found = true;
            for line in text.lines().filter(|l| !l.trim().is_empty()) {
                match serde_json::from_str::<Value>(line) {
                    Ok(v) if v["format"] == FORMAT => {}
                    Ok(v) if v["kind"].is_string() => records.push(v),
                    _ => bad += 1,
                }
            }
        }
        if !found {
            return Err(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("no {FILE} in {}", dir.display()),
            ));
        }
        Ok((records, bad))
    }

    #[test]
    fn records_append_rotate_past_the_limit_and_read_back_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let log = AirLog::open(dir.path(), 4096).unwrap();
        for i in 0..200 {
            log.record("command", json!({"n": i, "pad": "x".repeat(40)}));
        }
        let size = |n| std::fs::metadata(dir.path().join(n)).map_or(0, |m| m.len());
        assert!(size(FILE) <= 4096 && size(ROTATED) <= 4096, "bounded");
        let (records, bad) = read(dir.path()).unwrap();
        assert_eq!(bad, 0);
        let n: Vec<u64> = records.iter().filter_map(|r| r["n"].as_u64()).collect();
        assert!(n.windows(2).all(|w| w[1] == w[0] + 1), "in order: {n:?}");
        assert_eq!(n.last(), Some(&199), "the newest kept");
        assert!(n.len() < 200, "the oldest dropped");
        // Reopened (a restarted VAS): appends.
        drop(log);
        AirLog::open(dir.path(), 4096)
            .unwrap()
            .record("state", json!({"to": "PARKING"}));
        let (records, _) = read(dir.path()).unwrap();
        assert_eq!(records.last().unwrap()["to"], "PARKING");
        assert!(read(&dir.path().join("none")).is_err());
    }
}

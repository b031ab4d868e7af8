//! The `--log` file: one JSON object per line for every event a test may check.
//!
//! Each line is `{"t_sim": seconds, "event": "...", ...fields}`, for example
//! `{"t_sim":12.34,"event":"item_reached","seq":3,"lat":41.27,"lon":1.98}`.
//!
//! A record is on file before any message the event caused leaves the simulator, so a test that
//! reads the log when it sees an effect (a reach, the mode after a mission) finds its cause.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

/// Something that happened in the simulator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum LogEvent {
    /// The simulator started.
    Started {
        /// `rover`, `copter` or `plane`.
        vehicle: String,
        /// MAVLink system id.
        sysid: u8,
        /// Home latitude, degrees.
        home_lat: f64,
        /// Home longitude, degrees.
        home_lon: f64,
    },
    /// A full upload was committed.
    MissionUploaded {
        /// Items on board, home included.
        count: u16,
    },
    /// A partial write was committed.
    MissionPartialWrite {
        /// First replaced index.
        start: u16,
        /// Last replaced index (inclusive).
        end: u16,
    },
    /// MISSION_CLEAR_ALL.
    MissionCleared,
    /// The current mission index changed.
    CurrentChanged {
        /// New current index.
        seq: u16,
        /// `set_current`, `advance` or `auto_start`.
        cause: String,
    },
    /// A mission item was reached.
    ItemReached {
        /// Its index.
        seq: u16,
        /// The item's latitude, degrees.
        lat: f64,
        /// The item's longitude, degrees.
        lon: f64,
    },
    /// The mission passed a DO_ command (executed at once, never "reached").
    DoCommand {
        /// Its index.
        seq: u16,
        /// Its MAV_CMD number (189: DO_LAND_START).
        command: u32,
    },
    /// The last item was reached (or the mission ended) and nothing follows.
    MissionComplete {
        /// Index of the last item reached.
        seq: u16,
    },
    /// The flight mode changed.
    ModeChanged {
        /// Previous custom mode number.
        from: u32,
        /// New custom mode number.
        to: u32,
        /// ArduPilot name of the new mode.
        name: String,
    },
    /// Armed or disarmed.
    Armed {
        /// New state.
        armed: bool,
    },
    /// The speed changed (DO_CHANGE_SPEED, or back to the default on a mode change).
    SpeedChanged {
        /// New speed, m/s; 0 for the vehicle's default.
        speed: f64,
    },
    /// A GUIDED take-off reached its altitude.
    TakeoffComplete {
        /// Metres above home.
        alt: f64,
    },
    /// A fence transfer was committed, or the fence cleared.
    FenceUploaded {
        /// Its polygon's vertices (0: none, or cleared).
        vertices: usize,
        /// Its inclusion circle item's radius, metres, if it has one (`null` in JSON if not).
        circle_m: Option<f64>,
    },
    /// The vehicle left the fence.
    FenceBreached {
        /// Which part: `circle (..)` (FENCE_RADIUS or GF_MAX_HOR_DIST), `ceiling (..)`
        /// (FENCE_ALT_MAX or GF_MAX_VER_DIST), `polygon`, `circle item (..)`.
        fence: String,
        /// What was done: `report` or (PX4) `warning`; else the lower-case name of the mode
        /// entered (`rtl`, `hold`, `loiter`, `land`...); PX4's terminate is
        /// `terminate as <mode>`.
        action: String,
        /// Where, latitude.
        lat: f64,
        /// Where, longitude.
        lon: f64,
    },
    /// A target of MAV_CMD_DO_REPOSITION was accepted (ArduPilot: in GUIDED; PX4 profile:
    /// into its hold mode): the vehicle goes there and holds.
    Repositioned {
        /// Target latitude, degrees.
        lat: f64,
        /// Target longitude, degrees.
        lon: f64,
        /// Target altitude above home, metres.
        alt: f64,
    },
    /// A LAND reached the ground.
    Landed,
    /// The reposition target was reached; the vehicle holds there.
    RepositionReached {
        /// Its latitude, degrees.
        lat: f64,
        /// Its longitude, degrees.
        lon: f64,
    },
}

/// A log line: simulated time plus the event.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LogRecord {
    /// Simulated seconds since start.
    pub t_sim: f64,
    /// What happened.
    #[serde(flatten)]
    pub event: LogEvent,
}

/// Appends records to a file, flushing each line so readers see it at once.
pub struct LogWriter {
    out: BufWriter<File>,
}

impl LogWriter {
    /// Creates (truncates) `path`.
    ///
    /// # Errors
    /// When the file cannot be created.
    pub fn create(path: &Path) -> std::io::Result<Self> {
        Ok(Self {
            out: BufWriter::new(File::create(path)?),
        })
    }

    /// Writes one record as a JSON line.
    ///
    /// # Errors
    /// When the write fails.
    pub fn write(&mut self, record: &LogRecord) -> std::io::Result<()> {
        serde_json::to_writer(&mut self.out, record)?;
        self.out.write_all(b"\n")?;
        self.out.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_are_flat_json_lines() {
        let rec = LogRecord {
            t_sim: 1.5,
            event: LogEvent::ItemReached {
                seq: 3,
                lat: 41.0,
                lon: 2.0,
            },
        };
        let line = serde_json::to_string(&rec).unwrap();
        assert_eq!(
            line,
            r#"{"t_sim":1.5,"event":"item_reached","seq":3,"lat":41.0,"lon":2.0}"#
        );
        let back: LogRecord = serde_json::from_str(&line).unwrap();
        assert_eq!(back, rec);
    }

    #[test]
    fn fence_uploaded_keeps_vertices_and_gains_circle_m() {
        let line = |event| serde_json::to_string(&LogRecord { t_sim: 2.0, event }).unwrap();
        assert_eq!(
            line(LogEvent::FenceUploaded {
                vertices: 4,
                circle_m: None
            }),
            r#"{"t_sim":2.0,"event":"fence_uploaded","vertices":4,"circle_m":null}"#
        );
        assert_eq!(
            line(LogEvent::FenceUploaded {
                vertices: 0,
                circle_m: Some(200.0)
            }),
            r#"{"t_sim":2.0,"event":"fence_uploaded","vertices":0,"circle_m":200.0}"#
        );
    }
}

//! A simple on-board detector (the Broz search): points of interest placed by the mission
//! (`--poi-file`), each detected once when the vehicle comes within the sensor footprint radius
//! (`--sensor-radius`) of it, horizontally.
//!
//! A detection goes to the ground as a STATUSTEXT of severity WARNING,
//! `POI <id> <lat> <lon> <confidence>` ([`usal_types::PoiDetection::to_text`], at most 50
//! characters, the field's size): no new MAVLink message. The VAS reads it back
//! ([`usal_types::PoiDetection::parse`]) and raises its typed `detection` event (position,
//! confidence, which vehicle), not an alarm. The confidence falls from 1 over the point to 0.5
//! at the footprint's edge.
//!
//! Pure: [`Detector::check`] takes the vehicle's local position and returns what it newly
//! sees; the driver in [`crate::sim`] calls it after each step.

use std::path::Path;

use crate::kinematics::{GeoPoint, LocalFrame, Ned};

/// Why a points-of-interest file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum PoiLoadError {
    /// The file could not be read.
    #[error("{path}: cannot read: {source}")]
    Read {
        /// The file.
        path: String,
        /// What the OS said.
        source: std::io::Error,
    },
    /// A line is not `LAT,LON` in range.
    #[error("{path}:{line}: `{text}` is not LAT,LON (degrees, in range)")]
    BadLine {
        /// The file.
        path: String,
        /// 1-based line number.
        line: usize,
        /// The line as written.
        text: String,
    },
    /// The sensor radius is not a positive number.
    #[error("the sensor radius must be a positive number of metres, not {0}")]
    BadRadius(f64),
}

/// A point of interest: its 1-based number in the file and where it is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Poi {
    /// 1-based, in file order (blank and `#` lines not counted).
    pub id: u32,
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
}

/// Reads a points-of-interest file: one `LAT,LON` a line; blank lines and `#` comments skipped.
///
/// # Errors
/// [`PoiLoadError`] naming the file and line.
pub fn load_pois(path: &Path) -> Result<Vec<Poi>, PoiLoadError> {
    let name = path.display().to_string();
    let src = std::fs::read_to_string(path).map_err(|source| PoiLoadError::Read {
        path: name.clone(),
        source,
    })?;
    parse_pois(&src, &name)
}

/// [`load_pois`] on text already read; `name` is used in errors.
///
/// # Errors
/// [`PoiLoadError::BadLine`].
pub fn parse_pois(src: &str, name: &str) -> Result<Vec<Poi>, PoiLoadError> {
    let mut out = Vec::new();
    for (i, raw) in src.lines().enumerate() {
        let text = raw.split('#').next().unwrap_or("").trim();
        if text.is_empty() {
            continue;
        }
        let bad = || PoiLoadError::BadLine {
            path: name.to_owned(),
            line: i + 1,
            text: raw.trim().to_owned(),
        };
        let mut parts = text.split(',').map(str::trim);
        let (Some(lat), Some(lon), None) = (parts.next(), parts.next(), parts.next()) else {
            return Err(bad());
        };
        let (Ok(lat), Ok(lon)) = (lat.parse::<f64>(), lon.parse::<f64>()) else {
            return Err(bad());
        };
        if !((-90.0..=90.0).contains(&lat) && (-180.0..=180.0).contains(&lon)) {
            return Err(bad());
        }
        let id = u32::try_from(out.len() + 1).map_err(|_| bad())?;
        out.push(Poi { id, lat, lon });
    }
    Ok(out)
}

/// The detector: points not yet seen, in the vehicle's local frame.
#[derive(Clone, Debug)]
pub struct Detector {
    radius_m: f64,
    /// (point, local position, seen).
    points: Vec<(Poi, Ned, bool)>,
}

impl Detector {
    /// A detector for `pois` around `home` (the vehicle's frame) seeing within `radius_m`.
    ///
    /// # Errors
    /// [`PoiLoadError::BadRadius`] for a radius that is not a positive finite number.
    pub fn new(home: GeoPoint, pois: &[Poi], radius_m: f64) -> Result<Self, PoiLoadError> {
        if !(radius_m.is_finite() && radius_m > 0.0) {
            return Err(PoiLoadError::BadRadius(radius_m));
        }
        let frame = LocalFrame::new(home);
        let points = pois
            .iter()
            .map(|p| {
                let local = frame.to_local(GeoPoint {
                    lat_deg: p.lat,
                    lon_deg: p.lon,
                    alt_m: home.alt_m,
                });
                (*p, local, false)
            })
            .collect();
        Ok(Self { radius_m, points })
    }

    /// The points within the footprint of `pos` not seen before, now marked seen, each with
    /// how sure the detector is (1 over it, 0.5 at the footprint's edge).
    pub fn check(&mut self, pos: Ned) -> Vec<(Poi, f32)> {
        let mut out = Vec::new();
        for (poi, local, seen) in &mut self.points {
            let d = pos.horizontal_distance(local);
            if !*seen && d <= self.radius_m {
                *seen = true;
                out.push((*poi, (1.0 - 0.5 * d / self.radius_m) as f32));
            }
        }
        out
    }

    /// Points seen so far.
    pub fn seen(&self) -> usize {
        self.points.iter().filter(|p| p.2).count()
    }
}

/// The STATUSTEXT of a detection seen with `confidence` (see the module doc).
pub fn detection_text(p: &Poi, confidence: f32) -> String {
    usal_types::PoiDetection {
        id: p.id,
        lat: p.lat,
        lon: p.lon,
        confidence,
        by: String::new(),
    }
    .to_text()
}

/// The STATUSTEXT message carrying `text` at severity WARNING (see the module doc).
pub fn statustext(text: &str) -> mavlink::dialects::ardupilotmega::MavMessage {
    use mavlink::dialects::ardupilotmega::{MavMessage, MavSeverity, STATUSTEXT_DATA};
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity: MavSeverity::MAV_SEVERITY_WARNING,
        text: text.into(),
        ..Default::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: GeoPoint = GeoPoint {
        lat_deg: 41.275,
        lon_deg: 1.987,
        alt_m: 0.0,
    };

    #[test]
    fn a_point_is_detected_once_within_the_footprint_only() {
        let pois = parse_pois(
            "# two points\n41.2751,1.987\n\n41.2760, 1.9880 # far\n",
            "p",
        )
        .unwrap();
        assert_eq!(pois.len(), 2);
        assert_eq!((pois[0].id, pois[1].id), (1, 2));
        let mut d = Detector::new(HOME, &pois, 12.0).unwrap();
        // The first point is ~11.1 m north of home.
        let seen = d.check(Ned::default());
        assert!(seen.iter().map(|p| p.0.id).eq([1]));
        // 11.1 m of a 12 m footprint: near its edge, not sure.
        assert!((0.5..0.6).contains(&seen[0].1), "{seen:?}");
        assert!(d.check(Ned::default()).is_empty(), "seen only once");
        assert!(d
            .check(Ned {
                north: 60.0,
                east: 0.0,
                up: 0.0
            })
            .is_empty());
        assert_eq!(d.seen(), 1);
    }

    #[test]
    fn bad_files_and_radii_are_errors_with_the_line() {
        let e = parse_pois("41,1\n91,1\n", "pois.txt").unwrap_err();
        assert_eq!(
            e.to_string(),
            "pois.txt:2: `91,1` is not LAT,LON (degrees, in range)"
        );
        assert!(parse_pois("41,1,3", "p").is_err());
        assert!(parse_pois("north,1", "p").is_err());
        assert!(Detector::new(HOME, &[], 0.0).is_err());
        assert!(Detector::new(HOME, &[], f64::NAN).is_err());
    }

    #[test]
    fn the_text_says_how_sure_and_reads_back() {
        let p = Poi {
            id: 7,
            lat: 41.275_123_4,
            lon: 1.987_123_4,
        };
        let d = usal_types::PoiDetection::parse(&detection_text(&p, 0.5)).unwrap();
        assert_eq!((d.id, d.confidence), (7, 0.5));
        assert!((d.lat - p.lat).abs() < 1e-7 && (d.lon - p.lon).abs() < 1e-7);
    }
}

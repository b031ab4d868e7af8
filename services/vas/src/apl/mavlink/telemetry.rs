//! What the autopilot reports, as the VAL reads it, pure: telemetry in USAL's units
//! (`AP_Reader`, 003 §3.3.3), status texts as alarms or detections, the heartbeat's status.

use usal_types::{Alarm, Attitude, AutopilotStatus, Battery, Position, Severity, Speeds};

use super::ApEvent;
use crate::mavlink_cm::dialect::MavSeverity;
use crate::mavlink_cm::{self as cm, VehicleState};

/// USAL's severity of a MAVLink one.
pub(super) fn severity(s: MavSeverity) -> Severity {
    match s {
        MavSeverity::MAV_SEVERITY_EMERGENCY => Severity::Emergency,
        MavSeverity::MAV_SEVERITY_ALERT => Severity::Alert,
        MavSeverity::MAV_SEVERITY_CRITICAL => Severity::Critical,
        MavSeverity::MAV_SEVERITY_ERROR => Severity::Error,
        MavSeverity::MAV_SEVERITY_WARNING => Severity::Warning,
        MavSeverity::MAV_SEVERITY_NOTICE => Severity::Notice,
        MavSeverity::MAV_SEVERITY_INFO => Severity::Info,
        MavSeverity::MAV_SEVERITY_DEBUG => Severity::Debug,
    }
}

/// A position report: the heading the autopilot gives, else the course from its velocity.
pub(super) fn position(p: &cm::Position) -> Position {
    let heading = p.heading_deg.unwrap_or_else(|| {
        p.vel_ned[1]
            .atan2(p.vel_ned[0])
            .to_degrees()
            .rem_euclid(360.0)
    });
    Position {
        lat: p.lat_deg,
        lon: p.lon_deg,
        alt: f64::from(p.alt_msl_m),
        heading,
        speed: p.vel_ned[0].hypot(p.vel_ned[1]),
        alt_rel: f64::from(p.alt_rel_m),
    }
}

/// Home's altitude above mean sea level a position report implies (MSL minus relative).
pub(super) fn home_alt_msl(p: &cm::Position) -> f64 {
    f64::from(p.alt_msl_m) - f64::from(p.alt_rel_m)
}

/// Attitude in degrees.
pub(super) fn attitude(a: &cm::Attitude) -> Attitude {
    Attitude {
        roll: a.roll.to_degrees(),
        pitch: a.pitch.to_degrees(),
        yaw: a.yaw.to_degrees(),
    }
}

/// Ground speed, airspeed and climb rate (VFR_HUD).
pub(super) fn speeds(v: &cm::VfrHud) -> Speeds {
    Speeds {
        ground: v.groundspeed,
        air: v.airspeed,
        climb: v.climb,
    }
}

/// The battery SYS_STATUS describes.
pub(super) fn battery_of_sys_status(s: &cm::SysStatus) -> Battery {
    Battery {
        voltage: s.voltage_v,
        current: s.current_a,
        remaining: s.battery_pct.map(f32::from),
    }
}

/// A BATTERY_STATUS report, when it is of the first battery (the one SYS_STATUS describes
/// too) and gives its voltage.
pub(super) fn battery_of_status(b: &cm::BatteryStatus) -> Option<Battery> {
    let voltage = b.voltage_v.filter(|_| b.id == 0)?;
    Some(Battery {
        voltage,
        current: b.current_a,
        remaining: b.battery_pct.map(f32::from),
    })
}

/// A STATUSTEXT: a detector's report is a detection, not an alarm; any other text the ground
/// hears as an alarm when it is a warning or worse (`None`: below that).
pub(super) fn status_text(s: MavSeverity, text: &str) -> Option<ApEvent> {
    if let Some(d) = usal_types::PoiDetection::parse(text) {
        return Some(ApEvent::Detection(d));
    }
    let severity = severity(s);
    (severity <= Severity::Warning).then(|| {
        ApEvent::Alarm(Alarm {
            severity,
            text: format!("autopilot: {text}"),
        })
    })
}

/// The status the VAL publishes, from the manager's view of the autopilot.
pub(super) fn status(s: &VehicleState) -> AutopilotStatus {
    AutopilotStatus {
        connected: s.link_up,
        armed: s.armed,
        mode: s.mode_name.unwrap_or_default().to_owned(),
        mode_number: s.mode.unwrap_or_default(),
        system_status: s
            .system_status
            .map(|st| {
                format!("{st:?}")
                    .trim_start_matches("MAV_STATE_")
                    .to_owned()
            })
            .unwrap_or_default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mavlink_cm::dialect::MavState;

    #[test]
    fn a_position_without_heading_takes_its_course_from_the_velocity() {
        let mut p = cm::Position {
            lat_deg: 41.0,
            lon_deg: 2.0,
            alt_msl_m: 130.0,
            alt_rel_m: 30.0,
            vel_ned: [0.0, -3.0, 0.0],
            heading_deg: None,
            time_boot_ms: 0,
        };
        let u = position(&p);
        assert_eq!((u.lat, u.lon, u.alt, u.alt_rel), (41.0, 2.0, 130.0, 30.0));
        assert!((u.heading - 270.0).abs() < 1e-3, "westward: {}", u.heading);
        assert!((u.speed - 3.0).abs() < 1e-6);
        assert_eq!(home_alt_msl(&p), 100.0);
        p.heading_deg = Some(12.0);
        assert_eq!(position(&p).heading, 12.0);
    }

    #[test]
    fn attitude_in_degrees_and_the_first_battery_only() {
        let a = attitude(&cm::Attitude {
            roll: std::f32::consts::FRAC_PI_2,
            pitch: 0.0,
            yaw: -std::f32::consts::PI,
            rates: [0.0; 3],
        });
        assert!((a.roll - 90.0).abs() < 1e-4 && (a.yaw + 180.0).abs() < 1e-4);
        let b = cm::BatteryStatus {
            id: 0,
            voltage_v: Some(12.1),
            current_a: Some(3.0),
            battery_pct: Some(80),
        };
        assert_eq!(
            battery_of_status(&b),
            Some(Battery {
                voltage: 12.1,
                current: Some(3.0),
                remaining: Some(80.0)
            })
        );
        assert_eq!(battery_of_status(&cm::BatteryStatus { id: 1, ..b }), None);
        assert_eq!(
            battery_of_status(&cm::BatteryStatus {
                voltage_v: None,
                ..b
            }),
            None
        );
    }

    #[test]
    fn a_detectors_text_is_a_detection_and_only_warnings_or_worse_are_alarms() {
        match status_text(MavSeverity::MAV_SEVERITY_INFO, "POI 7 41.1 2.2 0.9") {
            Some(ApEvent::Detection(d)) => assert_eq!((d.id, d.confidence), (7, 0.9)),
            other => panic!("not a detection: {other:?}"),
        }
        match status_text(MavSeverity::MAV_SEVERITY_WARNING, "Low battery") {
            Some(ApEvent::Alarm(a)) => {
                assert_eq!(a.severity, Severity::Warning);
                assert_eq!(a.text, "autopilot: Low battery");
            }
            other => panic!("not an alarm: {other:?}"),
        }
        assert_eq!(
            status_text(MavSeverity::MAV_SEVERITY_INFO, "Reached waypoint #3"),
            None
        );
    }

    #[test]
    fn the_status_names_the_mode_and_the_system_state_plainly() {
        let s = VehicleState {
            link_up: true,
            armed: true,
            mode_name: Some("AUTO"),
            mode: Some(10),
            system_status: Some(MavState::MAV_STATE_ACTIVE),
            ..VehicleState::default()
        };
        let st = status(&s);
        assert!(st.connected && st.armed);
        assert_eq!((st.mode.as_str(), st.mode_number), ("AUTO", 10));
        assert_eq!(st.system_status, "ACTIVE");
        assert_eq!(status(&VehicleState::default()).mode, "");
    }
}

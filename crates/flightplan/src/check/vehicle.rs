//! What depends on the vehicle: spacings, widths and lengths against its turn radius and
//! minimum waypoint distance, and pattern sizes against what the FPMa generates.

use crate::model::*;
use crate::parse::{PlanError, PlanErrorKind};
use crate::polygon::{auto_sweep, polygon_frame, width_across};
use crate::vehicle::VehicleParams;
use crate::xml::Pos;

type Result<T> = std::result::Result<T, PlanError>;

/// Most tracks one scan may have.
pub const MAX_SCAN_TRACKS: u64 = 10_000;

/// Checks what depends on the vehicle: spacings and widths against its turn radius and minimum
/// waypoint distance.
///
/// # Errors
/// The first node that the vehicle cannot fly, with its position.
pub fn check_vehicle(plan: &FlightPlan, vehicle: &VehicleParams) -> Result<()> {
    if let Some(kind) = plan.vehicle.filter(|k| *k != vehicle.kind) {
        let (line, col) = plan.vehicle_at;
        return Err(PlanError::at_line(
            line,
            col,
            PlanErrorKind::WrongVehicle {
                plan: kind,
                vehicle: vehicle.kind,
            },
        ));
    }
    fn walk(nodes: &[Node], v: &VehicleParams) -> Result<()> {
        for n in nodes {
            check_node(n, v)?;
            for b in n.kind.bodies() {
                walk(b, v)?;
            }
        }
        Ok(())
    }
    for s in Stage::ALL {
        walk(plan.stage(s), vehicle)?;
    }
    Ok(())
}

fn check_node(n: &Node, v: &VehicleParams) -> Result<()> {
    let pos = Pos {
        line: n.line,
        col: n.col,
    };
    let err = |kind| Err(PlanError::at(pos, kind));
    match &n.kind {
        NodeKind::Scan(s) => {
            let frame = polygon_frame(&s.polygon);
            let local: Vec<_> = s.polygon.iter().map(|p| frame.to_local(*p)).collect();
            let bearing = s.sweep_angle.unwrap_or_else(|| auto_sweep(&local));
            let tracks = (width_across(&local, bearing) / s.spacing).ceil();
            if tracks > MAX_SCAN_TRACKS as f64 {
                return err(PlanErrorKind::TooLarge {
                    what: "scan tracks (the area's width / spacing)",
                    value: tracks as u64,
                    max: MAX_SCAN_TRACKS,
                });
            }
            if s.spacing < 2.0 * v.turn_radius {
                return err(PlanErrorKind::SpacingBelowTurnLimit {
                    spacing: s.spacing,
                    min: 2.0 * v.turn_radius,
                });
            }
            if s.spacing < v.min_wp_distance {
                return err(PlanErrorKind::BelowMinWaypointDistance {
                    what: "scan spacing",
                    value: s.spacing,
                    min: v.min_wp_distance,
                });
            }
        }
        NodeKind::Perimeter(p) if p.spacing < v.min_wp_distance => {
            return err(PlanErrorKind::BelowMinWaypointDistance {
                what: "perimeter spacing",
                value: p.spacing,
                min: v.min_wp_distance,
            });
        }
        NodeKind::Hold(h) => {
            let width = h.flown_width(v);
            if h.shape == HoldShape::Racetrack && width < 2.0 * v.turn_radius - 1e-9 {
                return err(PlanErrorKind::HoldTooNarrow {
                    width,
                    min: 2.0 * v.turn_radius,
                });
            }
            if width < v.min_wp_distance {
                return err(PlanErrorKind::BelowMinWaypointDistance {
                    what: "hold width",
                    value: width,
                    min: v.min_wp_distance,
                });
            }
            if let Some(len) = h.length {
                if len < v.min_wp_distance {
                    return err(PlanErrorKind::BelowMinWaypointDistance {
                        what: "hold length",
                        value: len,
                        min: v.min_wp_distance,
                    });
                }
            }
        }
        _ => {}
    }
    Ok(())
}

//! What depends on the vehicle: spacings, widths and lengths against its turn radius and
//! minimum waypoint distance, and pattern sizes against what the FPMa generates.

use crate::model::*;
use crate::parse::{PlanError, PlanErrorKind};
use crate::polygon::{auto_sweep, polygon_frame, width_across};
use crate::vehicle::VehicleParams;
use crate::xml::Pos;

type Result<T> = std::result::Result<T, PlanError>;

/// Checks that no track between consecutive waypoints of the nominal stream `wps` is longer
/// than the vehicle flies in one leg ([`VehicleParams::longest_leg_m`]).
///
/// # Errors
/// The first leg too long, at its node (or the plan's start when it has no position).
pub fn check_leg_lengths(
    plan: &FlightPlan,
    wps: &[crate::expand::Waypoint],
    vehicle: &VehicleParams,
) -> Result<()> {
    let max = vehicle.longest_leg_m();
    for pair in wps.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        let d = crate::geo::distance(
            crate::geo::GeoPoint::new(a.lat, a.lon),
            crate::geo::GeoPoint::new(b.lat, b.lon),
        );
        if d > max {
            let (line, col) = plan
                .find(&b.leg)
                .filter(|n| n.line > 0)
                .map_or((1, 1), |n| (n.line, n.col));
            return Err(PlanError::at_line(
                line,
                col,
                PlanErrorKind::LegTooLong {
                    leg: b.leg.clone(),
                    km: d / 1000.0,
                    max_km: max / 1000.0,
                    vehicle: vehicle.kind,
                },
            ));
        }
    }
    Ok(())
}

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

#[cfg(test)]
mod tests {
    use crate::check::{load, CheckError};
    use crate::parse::PlanErrorKind;
    use crate::vehicle::VehicleParams;

    fn plan(lat_b: &str) -> String {
        format!(
            r#"<flightPlan name="p"><fixes><fix id="A" lat="41.275" lon="1.987"/>
      <fix id="B" lat="{lat_b}" lon="1.987"/></fixes>
      <mission><leg type="IF" fix="A"/><leg type="TF" fix="B"/></mission></flightPlan>"#
        )
    }

    /// A latitude negated by mistake (a 9,000 km leg for a rover) is refused at its leg, with
    /// what the vehicle flies in one; the same plan typed right flies.
    #[test]
    fn a_leg_longer_than_the_vehicle_flies_is_refused_at_its_node() {
        let rover = VehicleParams::rover();
        match load(&plan("-41.2754"), &rover) {
            Err(CheckError::Plan(e)) => {
                assert!(
                    matches!(&e.kind, PlanErrorKind::LegTooLong { km, max_km, .. }
                        if *km > 9000.0 && *max_km == 50.0),
                    "{e}"
                );
                assert_eq!((e.line, e.col), (3, 40), "{e}"); // the second <leg>
                assert!(
                    e.to_string().contains("is a coordinate typed wrong?"),
                    "{e}"
                );
            }
            other => panic!("expected the long leg refused, got {other:?}"),
        }
        assert!(load(&plan("41.2754"), &rover).is_ok());
        // An aircraft flies 100 km legs.
        let far = plan("42.2");
        assert!(load(&far, &VehicleParams::aircraft()).is_ok());
        assert!(load(&far, &rover).is_err());
    }
}

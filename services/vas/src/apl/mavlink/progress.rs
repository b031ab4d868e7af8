//! Waypoint progress the driver infers itself, pure: when a position counts as past a
//! waypoint, two samples in a row past it for an autopilot that reports no progress, when a
//! report of the vehicle's current item can show it driving back, and how soon it gets to its
//! target in wall-clock time.

use std::time::{Duration, Instant};

/// Metres per degree of latitude (and of longitude at the equator).
const M_PER_DEG: f64 = 111_319.49;

/// Metres between two points (flat earth: what separates waypoints and a vehicle).
pub(super) fn metres(a: (f64, f64), b: (f64, f64)) -> f64 {
    let north = (b.0 - a.0) * M_PER_DEG;
    let east = (b.1 - a.1) * M_PER_DEG * a.0.to_radians().cos();
    north.hypot(east)
}

/// The vehicle's speed over the ground in wall-clock time, from its position samples: what a
/// transfer to the autopilot races against, whatever a simulator's speed-up.
#[derive(Clone, Debug, Default)]
pub(super) struct WallSpeed {
    last: Option<(Instant, (f64, f64))>,
    mps: Option<f64>,
}

impl WallSpeed {
    /// Samples closer in time than this are not used (telemetry comes in bursts).
    const MIN_INTERVAL: Duration = Duration::from_millis(100);

    /// A position sample taken `now`.
    pub(super) fn sample(&mut self, now: Instant, pos: (f64, f64)) {
        if let Some((t, p)) = self.last {
            let dt = now.saturating_duration_since(t);
            if dt < Self::MIN_INTERVAL {
                return;
            }
            self.mps = Some(metres(p, pos) / dt.as_secs_f64());
        }
        self.last = Some((now, pos));
    }

    /// Wall-clock seconds to cover `d` metres at the latest speed; `None` when the speed is
    /// unknown or the vehicle stands still.
    pub(super) fn eta(&self, d: f64) -> Option<f64> {
        let v = self.mps?;
        (v > 0.05).then(|| d / v)
    }
}

/// Whether a vehicle at `pos` has reached `target` on the leg from `from`: within `radius`
/// of it, or past the line across the leg `radius` before it (the autopilot may switch there
/// without coming within the radius, and position samples arrive far apart at a speed-up).
pub(super) fn passed(from: (f64, f64), target: (f64, f64), pos: (f64, f64), radius: f64) -> bool {
    let cos_lat = target.0.to_radians().cos();
    let local = |p: (f64, f64)| {
        (
            (p.0 - target.0) * M_PER_DEG,
            (p.1 - target.1) * M_PER_DEG * cos_lat,
        )
    };
    let (pn, pe) = local(pos);
    if pn.hypot(pe) <= radius {
        return true;
    }
    let (an, ae) = local(from);
    let leg = an.hypot(ae);
    if leg < 0.1 {
        return false;
    }
    // Distance still to go along the leg (negative once past the target).
    let to_go = (an * pn + ae * pe) / leg;
    to_go <= radius
}

/// Infers a waypoint reached from position samples, for autopilots that report no progress
/// (neither MISSION_ITEM_REACHED, nor a "Reached" text, nor MISSION_CURRENT changes): the
/// target counts as reached once two samples in a row show it [`passed`].
#[derive(Clone, Debug, Default)]
pub(super) struct PassWatch {
    /// Where the leg to the target starts: the last waypoint reached, or where navigation
    /// started (`None`: at the next sample).
    leg_start: Option<(f64, f64)>,
    /// The slot whose waypoint the last sample showed passed (a second sample must agree).
    passing: Option<u16>,
}

impl PassWatch {
    /// A watch whose first leg starts at `from` (`None`: at the first sample).
    pub(super) fn starting_at(from: Option<(f64, f64)>) -> Self {
        Self {
            leg_start: from,
            passing: None,
        }
    }

    /// The next leg starts at `from` (a waypoint just reached).
    pub(super) fn leg_from(&mut self, from: (f64, f64)) {
        self.leg_start = Some(from);
    }

    /// Whether a vehicle at `pos` is past `target` on the current leg (a leg not started yet
    /// starts at `pos`: then only the radius counts).
    pub(super) fn is_past(&self, target: (f64, f64), pos: (f64, f64), radius: f64) -> bool {
        passed(self.leg_start.unwrap_or(pos), target, pos, radius)
    }

    /// Nothing to watch for (no target): a half-seen pass is forgotten.
    pub(super) fn no_target(&mut self) {
        self.passing = None;
    }

    /// A sample at `pos` on the way to `slot`'s `target`: whether it is the second in a row
    /// past it (then the target is reached and the watch starts over).
    pub(super) fn sample(
        &mut self,
        slot: u16,
        target: (f64, f64),
        pos: (f64, f64),
        radius: f64,
    ) -> bool {
        let from = *self.leg_start.get_or_insert(pos);
        if !passed(from, target, pos, radius) {
            self.passing = None;
            return false;
        }
        if self.passing.replace(slot) != Some(slot) {
            return false;
        }
        self.passing = None;
        true
    }
}

/// Whether a report of the vehicle's current item can show it driving back now: it flies a
/// mission of ours (AUTO, the queue running, no whole upload under way whose new items the
/// report may already name), over a live link, with every restart of the autopilot handled.
pub(super) fn backtracks_judged(
    mode: Option<&str>,
    queue_running: bool,
    uploading: bool,
    link_up: bool,
    restarts_handled: bool,
) -> bool {
    mode == Some("AUTO") && queue_running && !uploading && link_up && restarts_handled
}

#[cfg(test)]
mod tests {
    use super::*;

    const M: f64 = 1.0 / 111_319.49;

    /// `north`, `east` metres from (41, 2).
    fn at(north: f64, east: f64) -> (f64, f64) {
        (41.0 + north * M, 2.0 + east * M / 41f64.to_radians().cos())
    }

    #[test]
    fn a_waypoint_is_passed_inside_its_radius_or_past_its_finish_line() {
        let (from, target) = (at(0.0, 0.0), at(100.0, 0.0));
        assert!(!passed(from, target, at(50.0, 0.0), 2.0));
        assert!(!passed(from, target, at(97.0, 0.5), 2.0));
        assert!(
            passed(from, target, at(98.5, 0.5), 2.0),
            "inside the radius"
        );
        // Already turned away towards the next waypoint, 5 m aside, never within 2 m.
        assert!(
            passed(from, target, at(99.0, 5.0), 2.0),
            "past the finish line"
        );
        assert!(!passed(from, target, at(90.0, 5.0), 2.0));
        // No leg (navigation started on the waypoint): only the radius counts.
        assert!(!passed(target, target, at(103.0, 0.0), 2.0));
    }

    #[test]
    fn a_waypoint_counts_as_reached_at_the_second_sample_in_a_row_past_it() {
        let target = at(100.0, 0.0);
        let mut w = PassWatch::starting_at(Some(at(0.0, 0.0)));
        assert!(!w.sample(1, target, at(50.0, 0.0), 2.0));
        assert!(
            !w.sample(1, target, at(99.0, 0.0), 2.0),
            "one sample past it"
        );
        assert!(w.sample(1, target, at(101.0, 0.0), 2.0), "the second");
        // The watch starts over: one more sample is again only the first.
        assert!(!w.sample(1, target, at(101.0, 0.0), 2.0));
    }

    #[test]
    fn a_sample_short_of_the_waypoint_or_for_another_slot_starts_the_count_again() {
        let target = at(100.0, 0.0);
        let mut w = PassWatch::starting_at(Some(at(0.0, 0.0)));
        assert!(!w.sample(1, target, at(99.0, 0.0), 2.0));
        assert!(
            !w.sample(1, target, at(90.0, 0.0), 2.0),
            "short of it again"
        );
        assert!(!w.sample(1, target, at(99.0, 0.0), 2.0));
        assert!(!w.sample(2, target, at(99.0, 0.0), 2.0), "another slot");
        assert!(w.sample(2, target, at(99.5, 0.0), 2.0));
        assert!(!w.sample(3, target, at(99.0, 0.0), 2.0));
        w.no_target();
        assert!(!w.sample(3, target, at(99.0, 0.0), 2.0), "forgotten");
    }

    #[test]
    fn a_leg_not_started_starts_at_the_first_sample_and_a_reach_starts_the_next() {
        let target = at(100.0, 0.0);
        let mut w = PassWatch::default();
        // Navigation started 3 m past the waypoint: no leg to be past the end of, outside
        // the radius: not reached.
        assert!(!w.is_past(target, at(103.0, 0.0), 2.0));
        assert!(!w.sample(1, target, at(103.0, 0.0), 2.0));
        assert!(!w.sample(1, target, at(103.0, 0.0), 2.0));
        // From a waypoint reached behind it, the same position is past the finish line.
        w.leg_from(at(0.0, 0.0));
        assert!(w.is_past(target, at(103.0, 0.0), 2.0));
    }

    #[test]
    fn backtracks_are_judged_only_on_a_mission_of_ours_over_a_live_link() {
        assert!(backtracks_judged(Some("AUTO"), true, false, true, true));
        assert!(!backtracks_judged(Some("HOLD"), true, false, true, true));
        assert!(!backtracks_judged(None, true, false, true, true));
        assert!(!backtracks_judged(Some("AUTO"), false, false, true, true));
        assert!(
            !backtracks_judged(Some("AUTO"), true, true, true, true),
            "mid-upload"
        );
        assert!(!backtracks_judged(Some("AUTO"), true, false, false, true));
        assert!(
            !backtracks_judged(Some("AUTO"), true, false, true, false),
            "a restarted autopilot not handled yet"
        );
    }

    #[test]
    fn wall_speed_times_the_way_to_a_target() {
        let mut w = WallSpeed::default();
        let t0 = Instant::now();
        assert_eq!(w.eta(100.0), None);
        w.sample(t0, (41.0, 2.0));
        // 111 m north in half a second: 222 m/s; samples 50 ms apart are skipped.
        w.sample(t0 + Duration::from_millis(50), (41.0005, 2.0));
        w.sample(t0 + Duration::from_millis(500), (41.001, 2.0));
        let eta = w.eta(222.6).unwrap();
        assert!((eta - 1.0).abs() < 0.01, "{eta}");
        // Standing still: it never gets there.
        w.sample(t0 + Duration::from_millis(700), (41.001, 2.0));
        assert_eq!(w.eta(10.0), None);
        assert!((metres((41.0, 2.0), (41.001, 2.0)) - 111.3).abs() < 0.1);
    }
}

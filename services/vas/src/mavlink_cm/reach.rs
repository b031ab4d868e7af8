//! Waypoint-reached detection from three sources that may all report the same reach.
//!
//! APM:Rover in 003 sent no MISSION_ITEM_REACHED, only "Reached waypoint #N"
//! STATUSTEXTs (003 §3.2.2); newer ArduPilot sends both; PX4 and others may only
//! let you infer progress from MISSION_CURRENT. A reach of `seq` is reported
//! once per *visit*: a visit of `seq` starts when MISSION_CURRENT becomes `seq`,
//! so the rolling queue (003 §3.3.2), which reuses slots, still gets one report
//! per pass.

/// Which message revealed a reach.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReachSource {
    /// MISSION_ITEM_REACHED.
    ItemReached,
    /// MISSION_CURRENT advanced from `seq` to `seq + 1`.
    MissionCurrent,
    /// A "Reached waypoint #N" / "Reached command #N" STATUSTEXT.
    StatusText,
}

/// The deduplicating detector.
#[derive(Debug, Default)]
pub struct ReachDetector {
    current: Option<u16>,
    /// Reaches reported whose item has not been visited again since.
    reported: Vec<u16>,
    /// A MISSION_CURRENT change we caused (set-current), not a reach.
    expected_jump: Option<u16>,
}

/// Parses ArduPilot's "Reached waypoint #3", "Reached waypoint #3 dist 5m",
/// "Reached command #3".
pub fn parse_reached_text(text: &str) -> Option<u16> {
    let lower = text.to_ascii_lowercase();
    let rest = ["reached waypoint #", "reached command #"]
        .iter()
        .find_map(|p| lower.find(p).map(|i| &lower[i + p.len()..]))?;
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

impl ReachDetector {
    /// A detector with no history.
    pub fn new() -> Self {
        Self::default()
    }

    /// We are about to set the current item to `seq`: that change is not a reach, and it starts
    /// a new visit of `seq` even when `seq` is current already (a mission that ended at its
    /// last item keeps it current; the next upload reuses that slot and sets it again), so
    /// its next reach is a new one.
    pub fn expect_jump(&mut self, seq: u16) {
        self.reported.retain(|&s| s != seq);
        if self.current != Some(seq) {
            self.expected_jump = Some(seq);
        }
    }

    /// Forgets all history (after a reconnection or a new mission).
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    fn report(&mut self, seq: u16) -> Option<u16> {
        if self.reported.contains(&seq) {
            return None;
        }
        self.reported.push(seq);
        Some(seq)
    }

    /// MISSION_ITEM_REACHED.
    pub fn on_item_reached(&mut self, seq: u16) -> Option<u16> {
        self.report(seq)
    }

    /// STATUSTEXT.
    pub fn on_status_text(&mut self, text: &str) -> Option<u16> {
        parse_reached_text(text).and_then(|seq| self.report(seq))
    }

    /// MISSION_CURRENT.
    pub fn on_mission_current(&mut self, seq: u16) -> Option<u16> {
        let old = self.current.replace(seq);
        let old = match old {
            Some(old) if old != seq => old,
            _ => return None,
        };
        // A new visit of `seq` starts: its next reach is a new one.
        self.reported.retain(|&s| s != seq);
        if self.expected_jump.take() == Some(seq) {
            return None;
        }
        if old >= 1 && seq == old.wrapping_add(1) {
            return self.report(old);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_ardupilot_wordings() {
        assert_eq!(parse_reached_text("Reached waypoint #3"), Some(3));
        assert_eq!(parse_reached_text("Reached waypoint #12 dist 4m"), Some(12));
        assert_eq!(parse_reached_text("Reached command #7"), Some(7));
        assert_eq!(parse_reached_text("Reached Waypoint #2"), Some(2));
        assert_eq!(parse_reached_text("Mission Complete"), None);
        assert_eq!(parse_reached_text("Reached waypoint #"), None);
        assert_eq!(parse_reached_text("Reached waypoint #99999999"), None);
    }

    #[test]
    fn all_sources_report_one_reach() {
        let mut d = ReachDetector::new();
        assert_eq!(d.on_mission_current(1), None);
        assert_eq!(d.on_item_reached(1), Some(1));
        assert_eq!(d.on_status_text("Reached waypoint #1"), None);
        assert_eq!(d.on_mission_current(2), None);
        // MISSION_CURRENT first, then the others.
        assert_eq!(d.on_mission_current(3), Some(2));
        assert_eq!(d.on_item_reached(2), None);
        assert_eq!(d.on_status_text("Reached waypoint #2"), None);
    }

    #[test]
    fn status_text_alone_is_enough() {
        let mut d = ReachDetector::new();
        d.on_mission_current(1);
        assert_eq!(d.on_status_text("Reached waypoint #1"), Some(1));
        assert_eq!(d.on_mission_current(2), None);
    }

    #[test]
    fn set_current_is_not_a_reach() {
        let mut d = ReachDetector::new();
        d.on_mission_current(1);
        d.expect_jump(2);
        assert_eq!(d.on_mission_current(2), None);
        assert_eq!(d.on_mission_current(3), Some(2));
    }

    #[test]
    fn setting_the_item_already_current_starts_a_new_visit() {
        // One-item missions, each uploaded once the last ended: item 1 stays current.
        let mut d = ReachDetector::new();
        d.on_mission_current(1);
        for _mission in 0..3 {
            d.expect_jump(1);
            assert_eq!(d.on_mission_current(1), None);
            assert_eq!(d.on_item_reached(1), Some(1));
            assert_eq!(d.on_status_text("Reached command #1"), None);
        }
        // An advance after the last reach is that same reach, not a second one.
        assert_eq!(d.on_mission_current(2), None);
    }

    #[test]
    fn rolling_queue_slots_are_reported_every_pass() {
        let mut d = ReachDetector::new();
        let mut reports = Vec::new();
        d.on_mission_current(1);
        for _lap in 0..3 {
            for slot in 1..=4u16 {
                reports.extend(d.on_item_reached(slot));
                reports.extend(d.on_status_text(&format!("Reached waypoint #{slot}")));
                reports.extend(d.on_mission_current(slot + 1));
            }
            // Driving to slot 5 (= slot 1): jump back to 1.
            d.expect_jump(1);
            reports.extend(d.on_mission_current(1));
        }
        assert_eq!(reports, [1, 2, 3, 4, 1, 2, 3, 4, 1, 2, 3, 4]);
    }
}

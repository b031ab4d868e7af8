//! The autopilot's mission as the rolling queue's slots. A waypoint that begins the plan's
//! landing sequence ([`Waypoint::land_start`]) goes on board behind a DO_LAND_START, as
//! ArduPilot's missions mark their landing (where RTL_AUTOLAND and MAV_CMD_DO_LAND_START jump
//! to). The queue does not count that item: it holds one waypoint per slot, so a mission
//! sequence number and a slot differ by the markers before it. Pure.
//!
//! A marker never comes or goes at or before the slot the vehicle drives to while the
//! autopilot keeps its current item through an upload (ArduPilot): that would give the target
//! another sequence number under it, and an autopilot that reaches its remembered target in
//! between advances from the old number, skipping or repeating a waypoint. Such a slot keeps
//! the marker it has on board (behind the vehicle, or the one it drives to), and gets the one
//! its waypoint asks for once it lies ahead again, after the wrap to slot 1.

use super::*;

/// Which slots (1 first) a DO_LAND_START precedes on board.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct Layout {
    marked: Vec<bool>,
}

impl Layout {
    /// The layout a mission of `slots` (slot 1 first) should have, this one being on board:
    /// a marker before each waypoint that asks for one, except at slots up to `fixed_through`
    /// (the target's slot, where the autopilot keeps its current item through an upload),
    /// which keep theirs.
    pub(super) fn next(&self, slots: &[Waypoint], fixed_through: Option<u16>) -> Self {
        Self {
            marked: slots
                .iter()
                .enumerate()
                .map(|(k, w)| {
                    if fixed_through.is_some_and(|c| k < usize::from(c)) {
                        self.marked.get(k).copied().unwrap_or(false)
                    } else {
                        w.land_start
                    }
                })
                .collect(),
        }
    }

    /// The mission sequence number of `slot`'s waypoint (slot 0, item 0, is 0).
    pub(super) fn seq(&self, slot: u16) -> u16 {
        let before = self
            .marked
            .iter()
            .take(usize::from(slot))
            .filter(|m| **m)
            .count();
        slot.saturating_add(before as u16)
    }

    /// The slot of the mission item at `seq`; a DO_LAND_START counts as the slot it precedes
    /// (the autopilot passes it on its way there).
    pub(super) fn slot(&self, seq: u16) -> u16 {
        if seq == 0 {
            return 0;
        }
        let mut at = 0u16;
        for (k, marked) in self.marked.iter().enumerate() {
            at = at.saturating_add(1 + u16::from(*marked));
            if seq <= at {
                return k as u16 + 1;
            }
        }
        // Past the slots known: one item per slot.
        let markers = at - self.marked.len() as u16;
        seq - markers
    }

    /// The mission items of `slots` laid out this way (slot 1 first, item 0 excluded).
    pub(super) fn items(&self, slots: &[Waypoint]) -> Vec<MissionItem> {
        self.items_from(1, slots)
    }

    /// The partial write of `items` from slot `start` (this layout unchanged by it): the
    /// first sequence number it replaces (a marker of the first slot included) and its items.
    pub(super) fn partial(&self, start: u16, items: &[Waypoint]) -> (u16, Vec<MissionItem>) {
        let first_marked = self.marked(start);
        (
            self.seq(start) - u16::from(first_marked),
            self.items_from(start, items),
        )
    }

    fn marked(&self, slot: u16) -> bool {
        usize::from(slot)
            .checked_sub(1)
            .and_then(|k| self.marked.get(k))
            .copied()
            .unwrap_or(false)
    }

    fn items_from(&self, start: u16, slots: &[Waypoint]) -> Vec<MissionItem> {
        let mut items = Vec::with_capacity(slots.len() + 1);
        for (slot, w) in (start..).zip(slots) {
            if self.marked(slot) {
                items.push(land_start_item(w.lat, w.lon, frame_of(w.alt_ref)));
            }
            items.push(mission_item(w));
        }
        items
    }
}

/// A DO_LAND_START at `(lat, lon)`: ArduPilot picks the landing sequence whose marker is
/// nearest when it jumps to one.
pub(super) fn land_start_item(lat: f64, lon: f64, frame: MavFrame) -> MissionItem {
    let mut item = MissionItem::waypoint(lat, lon, 0.0);
    item.command = MavCmd::MAV_CMD_DO_LAND_START;
    item.frame = frame;
    item
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wp(seq: u64, land_start: bool) -> Waypoint {
        Waypoint {
            seq,
            lat: 41.0 + seq as f64 * 1e-3,
            lon: 2.0,
            land_start,
            ..Waypoint::default()
        }
    }

    #[test]
    fn a_marker_shifts_the_sequence_numbers_after_it() {
        // Slots 1..=4; slot 3 is marked: items 1, 2, [marker 3], 4, 5.
        let slots = [wp(1, false), wp(2, false), wp(3, true), wp(4, false)];
        let l = Layout::default().next(&slots, None);
        assert_eq!(
            (0..=4).map(|s| l.seq(s)).collect::<Vec<_>>(),
            [0, 1, 2, 4, 5]
        );
        // The marker (seq 3) counts as the slot it precedes.
        assert_eq!(
            (0..=6).map(|q| l.slot(q)).collect::<Vec<_>>(),
            [0, 1, 2, 3, 3, 4, 5]
        );
        let items = l.items(&slots);
        assert_eq!(items.len(), 5);
        assert_eq!(items[2].command, MavCmd::MAV_CMD_DO_LAND_START);
        assert_eq!(items[3].command, MavCmd::MAV_CMD_NAV_WAYPOINT);
        assert_eq!(
            (items[2].lat_deg(), items[2].lon_deg()),
            (items[3].lat_deg(), items[3].lon_deg())
        );
        // Without markers, slots are sequence numbers.
        let plain = Layout::default().next(&[wp(1, false), wp(2, false)], None);
        assert_eq!(plain.seq(2), 2);
        assert_eq!(plain.slot(7), 7);
        assert_eq!(Layout::default().slot(3), 3);
    }

    #[test]
    fn markers_at_or_before_the_target_stay_as_they_are_on_board() {
        let on_board = Layout::default().next(&[wp(1, true), wp(2, false), wp(3, false)], None);
        // Driving to slot 2: slot 1's marker stays though its new waypoint asks for none, and
        // slot 2 gets none though its waypoint asks for one; slot 3, ahead, gets its own.
        let next = [wp(4, false), wp(5, true), wp(6, true)];
        let l = on_board.next(&next, Some(2));
        assert_eq!(l.seq(2), on_board.seq(2), "the target keeps its number");
        assert_eq!(l.marked, [true, false, true]);
        // After the wrap to slot 1, slot 2 lies ahead and gets its marker.
        assert_eq!(l.next(&next, Some(1)).marked, [true, true, true]);
        // A partial write under an unchanged layout rewrites a slot's marker with it.
        let (seq, items) = l.partial(3, &[wp(7, true)]);
        assert_eq!((seq, items.len()), (4, 2));
        assert_eq!(l.partial(2, &[wp(8, false)]).0, 3);
    }
}

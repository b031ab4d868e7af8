//! The vehicle side of the MAVLink mission protocol, as a pure state machine.
//!
//! Uploads (full and partial) are staged and committed only when the last item
//! has arrived, so a transfer broken by a lossy link never leaves a half-written
//! mission on board. Requests are resent after [`REQUEST_TIMEOUT`] and the
//! transfer is cancelled after [`MAX_REQUEST_RETRIES`] resends without progress.
//! Item 0 is home, as in ArduPilot: whatever a client uploads there is replaced
//! by the vehicle's home position.

use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavFrame, MavMessage, MavMissionResult, MISSION_ACK_DATA, MISSION_COUNT_DATA,
    MISSION_ITEM_DATA, MISSION_ITEM_INT_DATA, MISSION_REQUEST_INT_DATA,
};

use crate::kinematics::GeoPoint;

/// How long the vehicle waits for the next item before asking again.
pub const REQUEST_TIMEOUT: Duration = Duration::from_millis(1000);
/// How many times a request is resent before the transfer is cancelled.
pub const MAX_REQUEST_RETRIES: u32 = 8;

/// A stored mission item (MISSION_ITEM_INT layout, `seq` equal to its index).
pub type Item = MISSION_ITEM_INT_DATA;

/// What a committed transfer changed, for the simulator's log.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Change {
    /// A full upload of `count` items (home included) replaced the mission.
    Uploaded {
        /// Items now on board, home included.
        count: u16,
    },
    /// A partial write replaced items `start..=end`.
    PartialWrite {
        /// First replaced index.
        start: u16,
        /// Last replaced index.
        end: u16,
    },
    /// MISSION_CLEAR_ALL left only home.
    Cleared,
}

#[derive(Debug)]
struct Receiving {
    partner: (u8, u8),
    start: u16,
    end: u16,
    next: u16,
    staged: Vec<Item>,
    partial: bool,
    last_request: Instant,
    retries: u32,
}

/// The on-board mission and the transfer in progress, if any.
#[derive(Debug)]
pub struct MissionStore {
    items: Vec<Item>,
    receiving: Option<Receiving>,
    /// Index and partner of the last committed transfer's final item, so a
    /// client that lost our MISSION_ACK and resends that item gets it again.
    last_commit: Option<(u16, (u8, u8))>,
    /// Item 0 is home (replaced by ours on upload).
    item0_is_home: bool,
}

fn is_global(frame: MavFrame) -> bool {
    !matches!(
        frame,
        MavFrame::MAV_FRAME_LOCAL_NED
            | MavFrame::MAV_FRAME_LOCAL_ENU
            | MavFrame::MAV_FRAME_LOCAL_OFFSET_NED
            | MavFrame::MAV_FRAME_BODY_NED
            | MavFrame::MAV_FRAME_BODY_OFFSET_NED
            | MavFrame::MAV_FRAME_MISSION
    )
}

/// Converts a legacy float MISSION_ITEM to the integer layout.
pub fn item_from_float(m: &MISSION_ITEM_DATA) -> Item {
    let scale = if is_global(m.frame) { 1e7 } else { 1e4 };
    Item {
        param1: m.param1,
        param2: m.param2,
        param3: m.param3,
        param4: m.param4,
        x: (f64::from(m.x) * scale).round() as i32,
        y: (f64::from(m.y) * scale).round() as i32,
        z: m.z,
        seq: m.seq,
        command: m.command,
        target_system: 0,
        target_component: 0,
        frame: m.frame,
        current: m.current,
        autocontinue: m.autocontinue,
        ..Default::default()
    }
}

/// Converts a stored item to the legacy float MISSION_ITEM.
pub fn item_to_float(m: &Item) -> MISSION_ITEM_DATA {
    let scale = if is_global(m.frame) { 1e7 } else { 1e4 };
    MISSION_ITEM_DATA {
        param1: m.param1,
        param2: m.param2,
        param3: m.param3,
        param4: m.param4,
        x: (f64::from(m.x) / scale) as f32,
        y: (f64::from(m.y) / scale) as f32,
        z: m.z,
        seq: m.seq,
        command: m.command,
        target_system: 0,
        target_component: 0,
        frame: m.frame,
        current: m.current,
        autocontinue: m.autocontinue,
        ..Default::default()
    }
}

/// The home item: a NAV_WAYPOINT at `home`, absolute altitude.
pub fn home_item(home: GeoPoint) -> Item {
    Item {
        x: (home.lat_deg * 1e7).round() as i32,
        y: (home.lon_deg * 1e7).round() as i32,
        z: home.alt_m as f32,
        command: MavCmd::MAV_CMD_NAV_WAYPOINT,
        frame: MavFrame::MAV_FRAME_GLOBAL,
        autocontinue: 1,
        ..Item::default()
    }
}

fn ack(partner: (u8, u8), result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: partner.0,
        target_component: partner.1,
        mavtype: result,
        ..Default::default()
    })
}

fn request(partner: (u8, u8), seq: u16) -> MavMessage {
    MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
        seq,
        target_system: partner.0,
        target_component: partner.1,
        ..Default::default()
    })
}

impl MissionStore {
    /// A mission holding only `home`.
    pub fn new(home: GeoPoint) -> Self {
        Self {
            items: vec![home_item(home)],
            receiving: None,
            last_commit: None,
            item0_is_home: true,
        }
    }

    /// Whether item 0 is home, replaced by ours on every upload (ArduPilot), or an ordinary
    /// item kept as uploaded (PX4, generic).
    pub fn set_item0_is_home(&mut self, home: bool) {
        self.item0_is_home = home;
    }

    /// The items on board, home first.
    pub fn items(&self) -> &[Item] {
        &self.items
    }

    /// Number of items on board, home included.
    pub fn count(&self) -> u16 {
        self.items.len() as u16
    }

    /// Whether an upload is in progress.
    pub fn is_receiving(&self) -> bool {
        self.receiving.is_some()
    }

    /// MISSION_COUNT: start a full upload.
    pub fn on_count(&mut self, partner: (u8, u8), count: u16, now: Instant) -> Vec<MavMessage> {
        if count == 0 {
            self.receiving = None;
            self.items.truncate(1);
            return vec![ack(partner, MavMissionResult::MAV_MISSION_ACCEPTED)];
        }
        self.receiving = Some(Receiving {
            partner,
            start: 0,
            end: count - 1,
            next: 0,
            staged: Vec::with_capacity(usize::from(count)),
            partial: false,
            last_request: now,
            retries: 0,
        });
        vec![request(partner, 0)]
    }

    /// MISSION_WRITE_PARTIAL_LIST: start replacing items `start..=end`
    /// (`end == -1` means "to the last item"). Only existing items can be
    /// replaced, as ArduPilot allows.
    pub fn on_partial(
        &mut self,
        partner: (u8, u8),
        start: i16,
        end: i16,
        now: Instant,
    ) -> Vec<MavMessage> {
        let count = i32::from(self.count());
        let start = i32::from(start);
        let end = if end == -1 { count - 1 } else { i32::from(end) };
        if start < 1 || start >= count || end < start || end >= count {
            return vec![ack(partner, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)];
        }
        let (start, end) = (start as u16, end as u16);
        self.receiving = Some(Receiving {
            partner,
            start,
            end,
            next: start,
            staged: self.items.clone(),
            partial: true,
            last_request: now,
            retries: 0,
        });
        vec![request(partner, start)]
    }

    /// MISSION_ITEM_INT (or a converted MISSION_ITEM). Returns the replies and,
    /// when the transfer completes, what changed.
    pub fn on_item(
        &mut self,
        partner: (u8, u8),
        item: Item,
        home: GeoPoint,
        now: Instant,
    ) -> (Vec<MavMessage>, Option<Change>) {
        let Some(rx) = self.receiving.as_mut() else {
            if self.last_commit == Some((item.seq, partner)) {
                // Our ACK was lost and the client resent its last item.
                return (
                    vec![ack(partner, MavMissionResult::MAV_MISSION_ACCEPTED)],
                    None,
                );
            }
            return (
                vec![ack(partner, MavMissionResult::MAV_MISSION_ERROR)],
                None,
            );
        };
        if rx.partner != partner {
            return (
                vec![ack(partner, MavMissionResult::MAV_MISSION_DENIED)],
                None,
            );
        }
        if item.seq != rx.next {
            // Duplicate or out of order: ask again for the one we need.
            rx.last_request = now;
            return (vec![request(partner, rx.next)], None);
        }
        let mut item = item;
        item.target_system = 0;
        item.target_component = 0;
        item.current = 0;
        if rx.partial {
            let index = usize::from(item.seq);
            rx.staged[index] = item;
        } else {
            rx.staged.push(item);
        }
        if rx.next < rx.end {
            rx.next += 1;
            rx.last_request = now;
            rx.retries = 0;
            return (vec![request(partner, rx.next)], None);
        }
        // Last item: commit atomically.
        let Some(rx) = self.receiving.take() else {
            return (Vec::new(), None);
        };
        let change = if rx.partial {
            Change::PartialWrite {
                start: rx.start,
                end: rx.end,
            }
        } else {
            Change::Uploaded {
                count: rx.staged.len() as u16,
            }
        };
        self.items = rx.staged;
        if self.item0_is_home {
            self.items[0] = home_item(home);
        }
        self.last_commit = Some((rx.end, partner));
        (
            vec![ack(partner, MavMissionResult::MAV_MISSION_ACCEPTED)],
            Some(change),
        )
    }

    /// MISSION_ACK from the client during an upload: a cancel.
    pub fn on_ack(&mut self, partner: (u8, u8)) {
        if self
            .receiving
            .as_ref()
            .is_some_and(|rx| rx.partner == partner)
        {
            self.receiving = None;
        }
    }

    /// MISSION_CLEAR_ALL: keep only home.
    pub fn on_clear(&mut self, partner: (u8, u8)) -> (Vec<MavMessage>, Change) {
        self.receiving = None;
        self.items.truncate(1);
        (
            vec![ack(partner, MavMissionResult::MAV_MISSION_ACCEPTED)],
            Change::Cleared,
        )
    }

    /// MISSION_REQUEST_LIST: announce the count.
    pub fn on_request_list(&self, partner: (u8, u8)) -> MavMessage {
        MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: self.count(),
            target_system: partner.0,
            target_component: partner.1,
            ..Default::default()
        })
    }

    /// MISSION_REQUEST_INT / MISSION_REQUEST during a download.
    pub fn on_request(&self, partner: (u8, u8), seq: u16, int: bool) -> MavMessage {
        match self.items.get(usize::from(seq)) {
            Some(item) => {
                let mut item = item.clone();
                item.seq = seq;
                item.target_system = partner.0;
                item.target_component = partner.1;
                if int {
                    MavMessage::MISSION_ITEM_INT(item)
                } else {
                    MavMessage::MISSION_ITEM(item_to_float(&item))
                }
            }
            None => ack(partner, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE),
        }
    }

    /// Resends the pending request after a timeout; cancels after too many.
    pub fn poll(&mut self, now: Instant) -> Vec<MavMessage> {
        let Some(rx) = self.receiving.as_mut() else {
            return Vec::new();
        };
        if now.duration_since(rx.last_request) < REQUEST_TIMEOUT {
            return Vec::new();
        }
        if rx.retries >= MAX_REQUEST_RETRIES {
            let partner = rx.partner;
            self.receiving = None;
            return vec![ack(
                partner,
                MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
            )];
        }
        rx.retries += 1;
        rx.last_request = now;
        vec![request(rx.partner, rx.next)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: GeoPoint = GeoPoint {
        lat_deg: 41.0,
        lon_deg: 2.0,
        alt_m: 5.0,
    };
    const GCS: (u8, u8) = (255, 190);

    fn wp(seq: u16, lat: f64) -> Item {
        Item {
            seq,
            x: (lat * 1e7) as i32,
            y: 20_000_000,
            z: 0.0,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            ..Item::default()
        }
    }

    fn requested(msgs: &[MavMessage]) -> Option<u16> {
        match msgs {
            [MavMessage::MISSION_REQUEST_INT(r)] => Some(r.seq),
            _ => None,
        }
    }

    fn acked(msgs: &[MavMessage]) -> Option<MavMissionResult> {
        match msgs {
            [MavMessage::MISSION_ACK(a)] => Some(a.mavtype),
            _ => None,
        }
    }

    fn upload(store: &mut MissionStore, n: u16) {
        let now = Instant::now();
        assert_eq!(requested(&store.on_count(GCS, n, now)), Some(0));
        for seq in 0..n {
            let (out, change) =
                store.on_item(GCS, wp(seq, 41.0 + f64::from(seq) * 1e-4), HOME, now);
            if seq + 1 < n {
                assert_eq!(requested(&out), Some(seq + 1));
                assert_eq!(change, None);
            } else {
                assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
                assert_eq!(change, Some(Change::Uploaded { count: n }));
            }
        }
    }

    #[test]
    fn full_upload_commits_and_replaces_home() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 4);
        assert_eq!(store.count(), 4);
        assert_eq!(store.items()[0], home_item(HOME));
        assert_eq!(store.items()[3].x, wp(3, 41.0 + 3e-4).x);
    }

    #[test]
    fn interrupted_upload_leaves_old_mission() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 3);
        let before = store.items().to_vec();
        let t0 = Instant::now();
        store.on_count(GCS, 5, t0);
        store.on_item(GCS, wp(0, 0.0), HOME, t0);
        store.on_item(GCS, wp(1, 40.0), HOME, t0);
        // No more items: the vehicle asks again, then gives up.
        let mut t = t0;
        for _ in 0..MAX_REQUEST_RETRIES {
            t += REQUEST_TIMEOUT;
            assert_eq!(requested(&store.poll(t)), Some(2));
        }
        t += REQUEST_TIMEOUT;
        assert_eq!(
            acked(&store.poll(t)),
            Some(MavMissionResult::MAV_MISSION_OPERATION_CANCELLED)
        );
        assert!(!store.is_receiving());
        assert_eq!(store.items(), &before[..]);
    }

    #[test]
    fn duplicate_item_is_rerequested_not_stored_twice() {
        let mut store = MissionStore::new(HOME);
        let now = Instant::now();
        store.on_count(GCS, 3, now);
        store.on_item(GCS, wp(0, 0.0), HOME, now);
        let (out, _) = store.on_item(GCS, wp(0, 0.0), HOME, now);
        assert_eq!(requested(&out), Some(1));
        store.on_item(GCS, wp(1, 41.1), HOME, now);
        let (out, change) = store.on_item(GCS, wp(2, 41.2), HOME, now);
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!(change, Some(Change::Uploaded { count: 3 }));
        // A resent last item after our ACK was lost is acknowledged again.
        let (out, change) = store.on_item(GCS, wp(2, 41.2), HOME, now);
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!(change, None);
    }

    #[test]
    fn partial_write_replaces_only_the_range() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 5);
        let now = Instant::now();
        assert_eq!(requested(&store.on_partial(GCS, 2, 3, now)), Some(2));
        store.on_item(GCS, wp(2, 50.0), HOME, now);
        let (out, change) = store.on_item(GCS, wp(3, 51.0), HOME, now);
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!(change, Some(Change::PartialWrite { start: 2, end: 3 }));
        assert_eq!(store.count(), 5);
        assert_eq!(store.items()[2].x, wp(2, 50.0).x);
        assert_eq!(store.items()[3].x, wp(3, 51.0).x);
        assert_eq!(store.items()[4].x, wp(4, 41.0 + 4e-4).x);
    }

    #[test]
    fn partial_write_cannot_grow_the_mission() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 3);
        let now = Instant::now();
        for (s, e) in [(2, 3), (3, 3), (0, 1), (2, 1)] {
            assert_eq!(
                acked(&store.on_partial(GCS, s, e, now)),
                Some(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE),
                "{s}..={e}"
            );
        }
        assert_eq!(requested(&store.on_partial(GCS, 1, -1, now)), Some(1));
    }

    #[test]
    fn download_serves_int_and_float_items() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 2);
        match store.on_request_list(GCS) {
            MavMessage::MISSION_COUNT(c) => assert_eq!(c.count, 2),
            other => panic!("{other:?}"),
        }
        match store.on_request(GCS, 1, false) {
            MavMessage::MISSION_ITEM(i) => assert!((i.x - 41.0001).abs() < 1e-5),
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            store.on_request(GCS, 9, true),
            MavMessage::MISSION_ACK(_)
        ));
    }

    #[test]
    fn clear_keeps_home() {
        let mut store = MissionStore::new(HOME);
        upload(&mut store, 4);
        let (_, change) = store.on_clear(GCS);
        assert_eq!(change, Change::Cleared);
        assert_eq!(store.count(), 1);
    }
}

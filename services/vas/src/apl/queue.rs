//! The rolling waypoint queue of 003 §3.3.2 as a pure state machine (no I/O, no clock).
//!
//! The autopilot holds a mission of `n` slots after home (slot 0). Slots `1..n-1` hold
//! distinct upcoming waypoints; slot `n` is the *mirror* of slot 1: when the vehicle has
//! reached slot `n-1` and drives to slot `n`, the driver sets the current item back to 1,
//! which holds the same point, so the path is not affected and the mission never ends.
//! Each slot the vehicle passes is free and is rewritten with the next waypoint of the plan
//! (a one-item MISSION_WRITE_PARTIAL_LIST), so a plan may hold any number of waypoints.
//!
//! The machine is declarative: from the waypoints ahead and the slot the vehicle drives to it
//! computes the mission the autopilot *should* hold, compares it with what it is known to
//! hold, and [`RollingQueue::poll`] returns the one action that brings them closer (a partial
//! write, a full upload, a set-current). The driver performs it and reports the outcome with
//! [`RollingQueue::done`]; a failure leaves the knowledge unchanged, so the next poll retries.
//! Hence the fallbacks: an autopilot that ignores partial writes gets the whole window
//! uploaded instead ([`RollingQueue::partial_unsupported`]); a link that comes back with an
//! unknown mission gets it re-uploaded ([`RollingQueue::forget_onboard`]); a missed reached
//! message is made up from MISSION_CURRENT ([`RollingQueue::on_current`]).
//!
//! Many autopilots (PX4, MAVSDK's server) reset the current item to 0 when a whole mission
//! is uploaded: after every whole upload while navigating, a set-current to the slot being
//! driven to is owed ([`RollingQueue::current_kept`] waives it where the autopilot is known to
//! have kept it), so the vehicle never turns back toward an item it has passed.
//!
//! A set-current must not race the autopilot's own advance: when it reports a waypoint
//! reached, many autopilots (MAVSDK's server among them) move their current item on a moment
//! later, and a set-current landing in between is advanced from, skipping the waypoint it
//! named. So after a reach no set-current is issued (the wrap's included) until the
//! autopilot reports it drives to the next slot ([`RollingQueue::on_current`]), or the driver
//! knows no such report will come ([`RollingQueue::assume_advanced`]).
//!
//! When fewer waypoints are known than the window holds, the mission is truncated after the
//! last one (a full upload, which ArduPilot does without changing the current target), so
//! the vehicle stops there instead of driving back to a stale slot.

use std::collections::VecDeque;

/// What the driver must do to the autopilot next.
#[derive(Clone, Debug, PartialEq)]
pub enum QueueAction<W> {
    /// Upload the whole mission: home, then these items in slots `1..=items.len()`.
    Upload(Vec<W>),
    /// Replace slots `start .. start + items.len()` (MISSION_WRITE_PARTIAL_LIST).
    WritePartial {
        /// First slot (≥ 1).
        start: u16,
        /// New contents.
        items: Vec<W>,
    },
    /// Make `seq` the current mission item (MISSION_SET_CURRENT).
    SetCurrent(u16),
}

/// Errors building a queue.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QueueCreateError {
    /// Fewer than 3 slots cannot mirror slot 1 and still hold two distinct waypoints.
    #[error("a rolling queue needs at least 3 slots, not {0}")]
    TooFewSlots(u16),
}

/// The rolling waypoint queue. `W` is the waypoint (the VAS uses `usal_types::Waypoint`).
#[derive(Clone, Debug)]
pub struct RollingQueue<W> {
    /// Slots after home (the seed's 5).
    n: u16,
    /// Waypoints from the one being driven to (`ahead[0]`) onwards.
    ahead: VecDeque<W>,
    /// Slot the vehicle drives to; `None` when not navigating.
    cur: Option<u16>,
    /// What the autopilot holds in slots `1..=have.len()`, `None` where unknown;
    /// `have_known` false when even the length is unknown.
    have: Vec<Option<W>>,
    have_known: bool,
    /// A set-current to `1` is owed after (re)starting.
    owe_start: bool,
    /// A set-current to the slot driven to is owed after a whole upload while navigating.
    owe_restore: bool,
    /// MISSION_WRITE_PARTIAL_LIST works on this autopilot (until shown otherwise).
    partial_ok: bool,
    /// `clear` was called: the next push replaces everything after the target.
    replacing: bool,
    /// The autopilot has moved to `cur` by itself since the last reach, or no advance of its
    /// own is pending (after a set-current or an upload of ours): a set-current cannot race it.
    advanced: bool,
    /// The last reach was of the last item on board while waypoints remain: the autopilot
    /// ended its mission early (a wrap or a growing write came too late).
    ended_early: bool,
    /// The last whole upload moved the target to another slot: an autopilot that kept its
    /// current item now points at the wrong one, so the restoring set-current is owed anyway.
    target_moved: bool,
}

impl<W: Clone + PartialEq> RollingQueue<W> {
    /// An empty queue of `slots` autopilot slots (after home).
    ///
    /// # Errors
    /// [`QueueCreateError::TooFewSlots`] below 3.
    pub fn new(slots: u16) -> Result<Self, QueueCreateError> {
        if slots < 3 {
            return Err(QueueCreateError::TooFewSlots(slots));
        }
        Ok(Self {
            n: slots,
            ahead: VecDeque::new(),
            cur: None,
            have: Vec::new(),
            have_known: false,
            owe_start: false,
            owe_restore: false,
            partial_ok: true,
            replacing: false,
            advanced: true,
            ended_early: false,
            target_moved: false,
        })
    }

    /// Slots after home.
    pub fn slots(&self) -> u16 {
        self.n
    }

    /// Waypoints queued, the target included.
    pub fn len(&self) -> usize {
        self.ahead.len()
    }

    /// No waypoint queued.
    pub fn is_empty(&self) -> bool {
        self.ahead.is_empty()
    }

    /// The waypoint being driven to (or next to drive to when not navigating).
    pub fn target(&self) -> Option<&W> {
        self.ahead.front()
    }

    /// The waypoints queued, target first.
    pub fn queued(&self) -> impl Iterator<Item = &W> {
        self.ahead.iter()
    }

    /// The slot the vehicle drives to, when navigating.
    pub fn current_slot(&self) -> Option<u16> {
        self.cur
    }

    /// Navigating through the queue.
    pub fn is_running(&self) -> bool {
        self.cur.is_some()
    }

    /// `clear` was called and no push has followed.
    pub fn is_replacing(&self) -> bool {
        self.replacing
    }

    /// Partial writes are still believed to work.
    pub fn partial_supported(&self) -> bool {
        self.partial_ok
    }

    /// Appends waypoints. After [`Self::clear`], they replace everything queued after the
    /// target instead (the target stays: the vehicle is already on its way to it; a first
    /// pushed waypoint equal to the target is not repeated).
    pub fn push(&mut self, wps: impl IntoIterator<Item = W>) {
        let mut wps = wps.into_iter().peekable();
        if self.replacing {
            self.replacing = false;
            let keep = usize::from(self.is_running());
            self.ahead.truncate(keep);
            if wps.peek().is_some() && wps.peek() == self.ahead.front() {
                wps.next();
            }
        }
        self.ahead.extend(wps);
    }

    /// "A new queue follows" (003 §6.2.2): nothing changes on the autopilot now; the next
    /// [`Self::push`] replaces what follows the target.
    pub fn clear(&mut self) {
        self.replacing = true;
    }

    /// Drops every waypoint at once (when leaving navigation for good, not on `clear`).
    pub fn discard(&mut self) {
        self.ahead.clear();
        self.replacing = false;
    }

    /// Starts (or restarts) navigation: the window is laid out from slot 1 and the current
    /// item set to 1 before the driver switches the autopilot to AUTO.
    pub fn start(&mut self) {
        self.cur = Some(1);
        self.owe_start = true;
        self.advanced = true;
    }

    /// Stops navigating (the autopilot left AUTO). The waypoints stay queued.
    pub fn stop(&mut self) {
        self.cur = None;
        self.owe_start = false;
        self.owe_restore = false;
    }

    /// The autopilot is known to have kept its current item through the last whole upload
    /// (it reported it since): the restoring set-current is not needed, unless that upload
    /// moved the target to another slot.
    pub fn current_kept(&mut self) {
        if !self.target_moved {
            self.owe_restore = false;
        }
    }

    /// The autopilot was seen driving somewhere it should not (back toward a passed waypoint
    /// or home): the current item is set to the target's slot next, without waiting for an
    /// advance of the autopilot's own.
    pub fn restore_current(&mut self) {
        if self.cur.is_some() {
            self.owe_restore = true;
            self.advanced = true;
        }
    }

    /// A set-current is owed to restore the current item after a whole upload.
    pub fn owes_restore(&self) -> bool {
        self.owe_restore
    }

    /// The slot of the restoring set-current, when it is owed and may go out now (no advance
    /// of the autopilot's own pending), for a driver that must send it before anything else
    /// [`Self::poll`] would do first.
    pub fn restore_due(&self) -> Option<u16> {
        (self.owe_restore && self.advanced).then_some(self.cur?)
    }

    /// An action is due but waits for the autopilot to report its own advance past the
    /// waypoint last reached (a set-current, or a window laid out afresh, which one follows).
    pub fn awaits_advance(&self) -> bool {
        !self.advanced && self.cur.is_some() && self.waits_for_advance()
    }

    /// Whether the last reach ended the autopilot's mission with waypoints still queued (its
    /// last item on board was reached before the wrap or a growing write): navigation must be
    /// restarted ([`Self::start`]) to go on. Reading it clears it.
    pub fn take_ended_early(&mut self) -> bool {
        std::mem::take(&mut self.ended_early)
    }

    /// The autopilot will not report its advance (it reports no progress, or not in time):
    /// take it as done.
    pub fn assume_advanced(&mut self) {
        self.advanced = true;
    }

    /// Whether the autopilot's advance changes the next action (it waits for it).
    fn waits_for_advance(&self) -> bool {
        let mut advanced = self.clone();
        advanced.advanced = true;
        advanced.poll() != self.poll()
    }

    /// The autopilot reports it drives to mission item `slot`: is that back toward a waypoint
    /// already passed? Item 0 holds `item0` (what the last whole upload put there where item 0
    /// is flown) or, when `None`, home. A slot holding a waypoint no longer queued (passed) or
    /// home is a backtrack; an unknown slot, or any report when not navigating, is not.
    pub fn heads_back(&self, slot: u16, item0: Option<&W>) -> bool {
        if self.cur.is_none() || self.ahead.is_empty() {
            return false;
        }
        let held = if slot == 0 {
            match item0 {
                Some(w) => w,
                None => return true,
            }
        } else {
            match self.onboard_slot(slot) {
                Some(w) => w,
                None => return false,
            }
        };
        !self.ahead.contains(held)
    }

    /// What the autopilot is believed to hold in `slot` (≥ 1), when known.
    pub fn onboard_slot(&self, slot: u16) -> Option<&W> {
        let k = usize::from(slot).checked_sub(1)?;
        self.have.get(k)?.as_ref()
    }

    /// The autopilot ignores MISSION_WRITE_PARTIAL_LIST: upload whole windows from now on.
    pub fn partial_unsupported(&mut self) {
        self.partial_ok = false;
    }

    /// The autopilot answers partial writes again (another autopilot, or the same updated,
    /// after the link came back).
    pub fn partial_supported_again(&mut self) {
        self.partial_ok = true;
    }

    /// What the autopilot holds is no longer known (link restored, autopilot restarted).
    pub fn forget_onboard(&mut self) {
        self.have.clear();
        self.have_known = false;
    }

    /// What the autopilot holds, as downloaded (slot 1 first, home excluded).
    pub fn set_onboard(&mut self, items: Vec<W>) {
        self.have = items.into_iter().map(Some).collect();
        self.have_known = true;
    }

    /// What the autopilot is believed to hold (slot 1 first), when fully known.
    pub fn onboard(&self) -> Option<Vec<W>> {
        if !self.have_known {
            return None;
        }
        self.have.iter().cloned().collect()
    }

    /// Everything the autopilot reported is consistent with the plan and nothing is owed.
    pub fn is_synced(&self) -> bool {
        self.poll().is_none()
    }

    /// Slot of `ahead[i]` for a vehicle driving to slot `c` (≤ n-1), and whether slot 1
    /// mirrors it; `None` past the window.
    fn slot_of(&self, c: u16, i: usize) -> Option<(u16, bool)> {
        let n = usize::from(self.n);
        let m = n - 1;
        let lin = usize::from(c) + i;
        if lin < n {
            Some((lin as u16, false))
        } else if lin == n {
            Some((self.n, c >= 2))
        } else {
            let slot = lin - m;
            (slot < usize::from(c)).then_some((slot as u16, false))
        }
    }

    /// The mission the autopilot should hold (slot 1 first), `None` entries meaning
    /// "whatever is there", for a vehicle driving to `c` (1..=n-1).
    fn wanted(&self, c: u16) -> Vec<Option<W>> {
        let n = usize::from(self.n);
        let last_lin = usize::from(c) + self.ahead.len().saturating_sub(1);
        let count = if last_lin < n { last_lin } else { n };
        let mut want: Vec<Option<W>> = (0..count)
            .map(|k| self.have.get(k).cloned().flatten())
            .collect();
        let mut assigned = vec![false; count];
        for (i, w) in self.ahead.iter().enumerate() {
            let Some((slot, mirror)) = self.slot_of(c, i) else {
                break;
            };
            let k = usize::from(slot) - 1;
            if k >= count || assigned[k] {
                break;
            }
            assigned[k] = true;
            want[k] = Some(w.clone());
            if mirror {
                assigned[0] = true;
                want[0] = Some(w.clone());
            }
        }
        want
    }

    /// The next action needed, or `None` when the autopilot holds what it should.
    ///
    /// Where partial writes do not work, every whole upload while navigating lays the window
    /// out afresh with the target in slot 1 (and item 0, where item 0 is flown: the driver's
    /// part), followed by a set-current to it: an autopilot that resets its current item on
    /// an upload, whatever its family says, then lands on the target, never on a waypoint it
    /// has passed.
    pub fn poll(&self) -> Option<QueueAction<W>> {
        let action = self.poll_in_place()?;
        let c = self.cur?;
        if self.partial_ok || c == 1 || !matches!(action, QueueAction::Upload(_)) {
            return Some(action);
        }
        // The window laid out afresh is followed by a set-current to slot 1: like one, it
        // waits for the autopilot's own advance after a reach, or that late advance would
        // move the vehicle from slot 1 to 2, past the target.
        if !self.advanced {
            return None;
        }
        let a0 = self.ahead.front()?.clone();
        let window: Vec<W> = self
            .wanted(1)
            .into_iter()
            .map(|w| w.unwrap_or_else(|| a0.clone()))
            .collect();
        Some(QueueAction::Upload(window))
    }

    /// [`Self::poll`] with the window where it is (the target's slot kept).
    fn poll_in_place(&self) -> Option<QueueAction<W>> {
        let c = self.cur?;
        let a0 = self.ahead.front()?.clone();
        if c == self.n {
            // Driving to the mirror slot: wrap to slot 1 unless this is the last waypoint.
            if self.ahead.len() < 2 {
                return (self.owe_restore && self.advanced).then_some(QueueAction::SetCurrent(c));
            }
            if self.have.first() != Some(&Some(a0.clone())) {
                return Some(self.write(1, vec![a0]));
            }
            // Once the autopilot is seen driving to the mirror: a set-current before its
            // own advance would be advanced from, skipping slot 1's waypoint.
            return self.advanced.then_some(QueueAction::SetCurrent(1));
        }
        let want = self.wanted(c);
        let filler = || a0.clone();
        let known = self.have_known && self.have.iter().all(Option::is_some);
        let differs = |k: usize| want[k].is_some() && want[k] != self.have[k];
        // The partial write of the first run of differing slots.
        let first_run = || {
            let first = (0..want.len()).find(|&k| differs(k))?;
            let items = (first..want.len())
                .take_while(|&k| differs(k))
                .map(|k| want[k].clone().unwrap_or_else(filler))
                .collect();
            Some(self.write(first as u16 + 1, items))
        };
        // Cutting the mission short takes a full upload, a long transfer on a lossy link:
        // slots the vehicle will drive to first get their waypoints by partial writes before
        // it, so they are not waiting on it.
        let shrinking = known && self.partial_ok && self.have.len() > want.len();
        if shrinking {
            if let Some(write) = first_run() {
                return Some(write);
            }
        }
        if !known || self.have.len() != want.len() {
            let items = want
                .iter()
                .map(|w| w.clone().unwrap_or_else(filler))
                .collect();
            return Some(QueueAction::Upload(items));
        }
        if let Some(write) = first_run() {
            return Some(write);
        }
        if self.owe_start || (self.owe_restore && self.advanced) {
            return Some(QueueAction::SetCurrent(c));
        }
        None
    }

    fn write(&self, start: u16, items: Vec<W>) -> QueueAction<W> {
        if self.partial_ok && self.have_known {
            QueueAction::WritePartial { start, items }
        } else {
            QueueAction::Upload(self.mission_after(start, &items))
        }
    }

    /// The whole mission a write of `items` from slot `start` leaves on board, for a driver
    /// that must upload it whole instead (and where partial writes do not work).
    pub fn mission_after(&self, start: u16, items: &[W]) -> Vec<W> {
        let mut all: Vec<W> = self
            .have
            .iter()
            .map(|w| w.clone().or_else(|| items.first().cloned()))
            .collect::<Option<Vec<W>>>()
            .unwrap_or_default();
        let s = usize::from(start) - 1;
        if all.len() < s + items.len() {
            // Unknown contents: fall back to the computed window.
            return items.to_vec();
        }
        all[s..s + items.len()].clone_from_slice(items);
        all
    }

    /// The driver performed `action` successfully.
    pub fn done(&mut self, action: &QueueAction<W>) {
        match action {
            QueueAction::Upload(items) => {
                self.have = items.iter().cloned().map(Some).collect();
                self.have_known = true;
                // The autopilot may have reset its current item: it is restored next (once
                // its own advance, if one is pending, is done).
                self.owe_restore = self.cur.is_some();
                self.target_moved = false;
                if !self.partial_ok && self.cur.is_some() {
                    // Whole windows are laid out from the target (see `poll`): the target's
                    // slot is where the upload put it (the next one if it was reached while
                    // the upload went on).
                    let at = self
                        .ahead
                        .front()
                        .and_then(|t| items.iter().position(|w| w == t));
                    if let Some(k) = at {
                        let slot = k as u16 + 1;
                        self.target_moved = self.cur != Some(slot);
                        self.cur = Some(slot);
                        // Set at once: whatever the autopilot did with its current item, it
                        // no longer names our target's slot.
                        self.advanced = true;
                    }
                }
            }
            QueueAction::WritePartial { start, items } => {
                let s = usize::from(*start) - 1;
                for (k, w) in items.iter().enumerate() {
                    if let Some(slot) = self.have.get_mut(s + k) {
                        *slot = Some(w.clone());
                    }
                }
            }
            QueueAction::SetCurrent(seq) => {
                if self.cur.is_some() {
                    self.cur = Some(*seq);
                }
                self.owe_start = false;
                self.owe_restore = false;
                self.advanced = true;
            }
        }
    }

    /// The autopilot reports it reached mission item `slot`. Returns the waypoint reached,
    /// if it is the target (duplicates and stale reports of passed slots return `None`).
    pub fn on_reached(&mut self, slot: u16) -> Option<W> {
        let c = self.cur?;
        let is_target = slot == c || (c == self.n && slot == 1);
        if !is_target || self.owe_start {
            return None;
        }
        let w = self.ahead.pop_front()?;
        let last_on_board = self.have_known && usize::from(slot) == self.have.len();
        if self.ahead.is_empty() || slot == self.n || last_on_board {
            // Last waypoint, or the last item on board (the wrap, or the write growing the
            // mission, came too late) and the mission ended: the autopilot holds; navigation
            // must be restarted.
            self.cur = None;
            self.ended_early = !self.ahead.is_empty();
        } else {
            self.cur = Some(slot + 1);
            self.advanced = false;
        }
        Some(w)
    }

    /// MISSION_CURRENT says the autopilot drives to `slot`. When that is the slot of the
    /// waypoint after the target, the target's reached message was missed: it is returned
    /// as reached. When it is the target's slot, the autopilot's own advance is done.
    pub fn on_current(&mut self, slot: u16) -> Option<W> {
        let c = self.cur?;
        let reached = if self.owe_start || c == self.n || self.ahead.len() < 2 {
            None
        } else {
            match self.slot_of(c, 1) {
                Some((s, _)) if s == slot => self.on_reached(c),
                _ => None,
            }
        };
        if self.cur == Some(slot) {
            self.advanced = true;
        }
        reached
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A simulated autopilot mission as 003 §2.5.4 describes APM:Rover: a target index that
    /// uploads do not change, set-current does, HOLD after the last item.
    struct Autopilot {
        mission: Vec<u32>,
        current: u16,
        holding: bool,
        reached: Vec<u32>,
        partial_works: bool,
        /// Resets its current item to 0 (an ordinary item: here `HOME`) on every upload, as
        /// PX4 and MAVSDK do.
        resets_current: bool,
        /// Times it drove toward item 0 after an upload.
        backtracks: u32,
    }

    const HOME: u32 = u32::MAX;

    impl Autopilot {
        fn new(partial_works: bool) -> Self {
            Self {
                mission: Vec::new(),
                current: 1,
                holding: false,
                reached: Vec::new(),
                partial_works,
                resets_current: false,
                backtracks: 0,
            }
        }
        fn apply(&mut self, a: &QueueAction<u32>) -> bool {
            match a {
                QueueAction::Upload(items) => {
                    self.mission = items.clone();
                    if self.resets_current {
                        self.current = 0;
                        self.holding = false;
                    }
                }
                QueueAction::WritePartial { start, items } => {
                    if !self.partial_works {
                        return false;
                    }
                    let s = usize::from(*start) - 1;
                    assert!(s + items.len() <= self.mission.len(), "partial cannot grow");
                    self.mission[s..s + items.len()].copy_from_slice(items);
                }
                QueueAction::SetCurrent(seq) => self.current = *seq,
            }
            true
        }
        /// Reaches the current item without advancing (the report goes out first).
        fn reach_only(&mut self) -> Option<u16> {
            if self.holding {
                return None;
            }
            let slot = self.current;
            assert_ne!(slot, 0, "never sent back to item 0 here");
            let wp = *self.mission.get(usize::from(slot) - 1)?;
            self.reached.push(wp);
            Some(slot)
        }
        /// The advance after [`Self::reach_only`], from whatever is current by then.
        fn advance(&mut self) {
            if usize::from(self.current) == self.mission.len() {
                self.holding = true;
            } else {
                self.current += 1;
            }
        }
        /// Drives to the current item; returns the slot reached.
        fn drive(&mut self) -> Option<u16> {
            if self.holding {
                return None;
            }
            let slot = self.current;
            if slot == 0 {
                self.backtracks += 1;
                self.reached.push(HOME);
                self.current = 1;
                return Some(0);
            }
            let wp = *self.mission.get(usize::from(slot) - 1)?;
            self.reached.push(wp);
            if usize::from(slot) == self.mission.len() {
                self.holding = true;
            } else {
                self.current += 1;
            }
            Some(slot)
        }
    }

    fn settle(q: &mut RollingQueue<u32>, ap: &mut Autopilot) {
        for _ in 0..20 {
            let Some(a) = q.poll() else { return };
            if ap.apply(&a) {
                q.done(&a);
            } else {
                q.partial_unsupported();
            }
        }
        panic!("queue did not settle");
    }

    /// A queue of `slots` slots navigating ten waypoints `0..10` on an autopilot whose partial writes
    /// work (`partial_works`; else the queue knows they do not), settled.
    fn flying_ten(slots: u16, partial_works: bool) -> (RollingQueue<u32>, Autopilot) {
        let mut q = RollingQueue::new(slots).unwrap();
        q.push(0..10);
        q.start();
        let mut ap = Autopilot::new(partial_works);
        if !partial_works {
            q.partial_unsupported();
        }
        settle(&mut q, &mut ap);
        (q, ap)
    }

    fn fly(slots: u16, plan: u32, partial_works: bool, feed_chunk: usize) -> Autopilot {
        let mut q = RollingQueue::new(slots).unwrap();
        let mut ap = Autopilot::new(partial_works);
        let mut next = 0u32;
        let mut feed = |q: &mut RollingQueue<u32>| {
            let end = (next + feed_chunk as u32).min(plan);
            q.push(next..end);
            next = end;
        };
        feed(&mut q);
        q.start();
        settle(&mut q, &mut ap);
        while let Some(slot) = ap.drive() {
            if q.len() < 2 * usize::from(slots) {
                feed(&mut q);
            }
            let w = q.on_reached(slot);
            assert_eq!(w, ap.reached.last().copied(), "queue and autopilot agree");
            q.on_current(ap.current);
            settle(&mut q, &mut ap);
        }
        ap
    }

    #[test]
    fn unlimited_waypoints_in_order_without_holding_early() {
        for slots in [3u16, 4, 5, 8] {
            for plan in [1u32, 2, 3, 4, 5, 6, 7, 9, 200] {
                let ap = fly(slots, plan, true, 3);
                assert_eq!(
                    ap.reached,
                    (0..plan).collect::<Vec<_>>(),
                    "{slots} slots, {plan}"
                );
                assert!(ap.holding);
            }
        }
    }

    #[test]
    fn falls_back_to_full_uploads_without_partial_writes() {
        let ap = fly(5, 50, false, 7);
        assert_eq!(ap.reached, (0..50).collect::<Vec<_>>());
    }

    /// An autopilot whose "reached, advance" is two steps (MAVSDK's server): a set-current
    /// landing between them is advanced from.
    #[test]
    fn the_wrap_waits_for_the_autopilots_own_advance_so_it_cannot_be_advanced_from() {
        for racing in [false, true] {
            let mut q = RollingQueue::new(5).unwrap();
            let mut ap = Autopilot::new(true);
            q.push(0..30);
            q.start();
            settle(&mut q, &mut ap);
            let mut wraps = 0;
            // Reached: reported now, the advance a step later.
            while let Some(slot) = ap.reach_only() {
                let w = q.on_reached(slot);
                assert_eq!(w, ap.reached.last().copied());
                if racing {
                    // What the queue asks before the advance must not be a set-current.
                    while let Some(a) = q.poll() {
                        assert!(
                            !matches!(a, QueueAction::SetCurrent(_)),
                            "set-current before the advance: {a:?}"
                        );
                        assert!(ap.apply(&a));
                        q.done(&a);
                    }
                    if q.current_slot() == Some(5) {
                        assert!(q.awaits_advance(), "the wrap waits");
                        wraps += 1;
                    }
                }
                ap.advance();
                assert_eq!(q.on_current(ap.current), None, "the advance is no reach");
                assert!(!q.awaits_advance());
                settle(&mut q, &mut ap);
            }
            assert_eq!(ap.reached, (0..30).collect::<Vec<_>>(), "racing: {racing}");
            assert!(!racing || wraps >= 5, "{wraps} wraps");
        }
    }

    #[test]
    fn without_an_advance_report_the_set_current_goes_ahead_when_told() {
        let mut q = RollingQueue::new(3).unwrap();
        let mut ap = Autopilot::new(true);
        q.push(0..10);
        q.start();
        settle(&mut q, &mut ap);
        let s = ap.drive().unwrap();
        q.on_reached(s);
        settle(&mut q, &mut ap);
        let s = ap.drive().unwrap();
        q.on_reached(s);
        // Driving to the mirror slot 3; slot 1 holds its waypoint: only the wrap is left.
        assert_eq!(q.current_slot(), Some(3));
        assert_eq!(q.poll(), None);
        assert!(q.awaits_advance());
        q.assume_advanced();
        assert_eq!(q.poll(), Some(QueueAction::SetCurrent(1)));
        // A restart owes its set-current at once: no advance of the autopilot's is pending.
        q.stop();
        q.start();
        assert!(!q.awaits_advance());
    }

    #[test]
    fn a_mission_ended_at_its_last_item_with_waypoints_left_is_restarted_from_slot_1() {
        let mut q = RollingQueue::new(4).unwrap();
        let mut ap = Autopilot::new(true);
        q.push(0..12);
        q.start();
        settle(&mut q, &mut ap);
        // Reaches slots 1 and 2 while every write is lost (a stalled link).
        for _ in 0..2 {
            let s = ap.drive().unwrap();
            q.on_reached(s);
            q.on_current(ap.current);
        }
        let s = ap.drive().unwrap();
        assert_eq!(q.on_reached(s), Some(2));
        q.on_current(ap.current);
        assert!(!q.take_ended_early());
        // Driving to the mirror slot 4; slot 1 still holds waypoint 0: the wrap needs a
        // write first, which is lost too; the autopilot reaches slot 4 and ends its mission.
        assert_eq!(q.current_slot(), Some(4));
        assert!(matches!(
            q.poll(),
            Some(QueueAction::WritePartial { start: 1, .. })
        ));
        assert_eq!(ap.drive(), Some(4));
        assert!(ap.holding);
        assert_eq!(q.on_reached(4), Some(3));
        assert!(!q.is_running());
        assert!(q.take_ended_early());
        assert!(!q.take_ended_early(), "read once");
        // Restarted: the next waypoint from slot 1, and the rest in order.
        q.start();
        ap.holding = false;
        settle(&mut q, &mut ap);
        while let Some(slot) = ap.drive() {
            q.on_reached(slot);
            q.on_current(ap.current);
            settle(&mut q, &mut ap);
        }
        assert_eq!(ap.reached, (0..12).collect::<Vec<_>>());
        // The plan's own end is no early end.
        assert!(!q.take_ended_early());
    }

    #[test]
    fn seed_layout_five_slots() {
        let mut q = RollingQueue::new(5).unwrap();
        q.push(10..20);
        q.start();
        // Slots 1-4 distinct, slot 5 already holds the waypoint slot 1 will get.
        assert_eq!(
            q.poll(),
            Some(QueueAction::Upload(vec![10, 11, 12, 13, 14]))
        );
        q.done(&QueueAction::Upload(vec![10, 11, 12, 13, 14]));
        assert_eq!(q.poll(), Some(QueueAction::SetCurrent(1)));
        q.done(&QueueAction::SetCurrent(1));
        assert_eq!(q.poll(), None);
        // Reached slot 1: it is rewritten (with what slot 5 holds), nothing else.
        assert_eq!(q.on_reached(1), Some(10));
        let a = q.poll().unwrap();
        assert_eq!(
            a,
            QueueAction::WritePartial {
                start: 1,
                items: vec![14]
            }
        );
        q.done(&a);
        assert_eq!(q.poll(), None);
        for (slot, wp, write) in [(2, 11, (2, 15)), (3, 12, (3, 16))] {
            assert_eq!(q.on_reached(slot), Some(wp));
            let a = q.poll().unwrap();
            assert_eq!(
                a,
                QueueAction::WritePartial {
                    start: write.0,
                    items: vec![write.1]
                }
            );
            q.done(&a);
        }
        // Reached slot 4: driving to 5, the mirror: wrap to 1 first (once the autopilot
        // reports it drives to 5), then refill 4.
        assert_eq!(q.on_reached(4), Some(13));
        assert_eq!(q.poll(), None);
        assert_eq!(q.on_current(5), None);
        assert_eq!(q.poll(), Some(QueueAction::SetCurrent(1)));
        q.done(&QueueAction::SetCurrent(1));
        let a = q.poll().unwrap();
        // Slot 5 gets its next waypoint in the same write: it is free again.
        assert_eq!(
            a,
            QueueAction::WritePartial {
                start: 4,
                items: vec![17, 18]
            }
        );
        q.done(&a);
        assert_eq!(q.poll(), None);
        assert_eq!(q.current_slot(), Some(1));
        assert_eq!(q.target(), Some(&14));
    }

    #[test]
    fn cutting_the_mission_short_writes_the_next_slot_first() {
        let mut q = RollingQueue::new(5).unwrap();
        let mut ap = Autopilot::new(true);
        q.push(0..20);
        q.start();
        settle(&mut q, &mut ap);
        let slot = ap.drive().unwrap();
        q.on_reached(slot);
        q.on_current(ap.current);
        settle(&mut q, &mut ap);
        // A new, short queue: the target (1) stays, 100 follows, and the mission must end.
        q.clear();
        q.push([1, 100]);
        let mut actions = Vec::new();
        while let Some(a) = q.poll() {
            assert!(ap.apply(&a));
            q.done(&a);
            actions.push(a);
            assert!(actions.len() < 10, "{actions:?}");
        }
        // The slot after the target first, by a partial write; then the cut, a full upload.
        assert_eq!(
            actions[0],
            QueueAction::WritePartial {
                start: 3,
                items: vec![100]
            }
        );
        // ... and the current item restored after it (an autopilot may have reset it).
        let n = actions.len();
        assert!(matches!(&actions[n - 2], QueueAction::Upload(items) if items.len() == 3));
        assert_eq!(actions[n - 1], QueueAction::SetCurrent(2));
        while let Some(slot) = ap.drive() {
            q.on_reached(slot);
            q.on_current(ap.current);
            settle(&mut q, &mut ap);
        }
        assert_eq!(ap.reached, [0, 1, 100]);
    }

    #[test]
    fn short_plan_truncates_and_grows_back() {
        let mut q = RollingQueue::new(5).unwrap();
        q.push([1, 2]);
        q.start();
        assert_eq!(q.poll(), Some(QueueAction::Upload(vec![1, 2])));
        q.done(&QueueAction::Upload(vec![1, 2]));
        q.done(&QueueAction::SetCurrent(1));
        assert_eq!(q.on_reached(1), Some(1));
        // More arrive while driving to slot 2: the mission grows by a full upload (slot 1,
        // behind the vehicle, already mirrors slot 5).
        q.push([3, 4, 5, 6]);
        assert_eq!(q.poll(), Some(QueueAction::Upload(vec![5, 2, 3, 4, 5])));
    }

    #[test]
    fn clear_keeps_the_target_and_replaces_the_rest() {
        let (mut q, mut ap) = flying_ten(5, true);
        let slot = ap.drive().unwrap();
        q.on_reached(slot);
        settle(&mut q, &mut ap);
        q.clear();
        assert!(q.is_replacing());
        // Nothing changes on the autopilot until the new queue arrives.
        assert_eq!(q.poll(), None);
        q.push([1, 100, 101, 102, 103, 104]);
        settle(&mut q, &mut ap);
        while let Some(slot) = ap.drive() {
            q.on_reached(slot);
            q.on_current(ap.current);
            settle(&mut q, &mut ap);
        }
        assert_eq!(ap.reached, [0, 1, 100, 101, 102, 103, 104]);
    }

    #[test]
    fn missed_reach_is_inferred_from_mission_current() {
        let (mut q, mut ap) = flying_ten(5, true);
        ap.drive();
        // No reached message: MISSION_CURRENT = 2 reveals it.
        assert_eq!(q.on_current(2), Some(0));
        assert_eq!(q.on_current(2), None);
        assert_eq!(q.on_reached(1), None, "a late duplicate is ignored");
        settle(&mut q, &mut ap);
        assert_eq!(q.current_slot(), Some(2));
    }

    #[test]
    fn restart_after_the_autopilot_forgot_everything() {
        let mut q = RollingQueue::new(5).unwrap();
        q.push(0..20);
        q.start();
        let mut ap = Autopilot::new(true);
        settle(&mut q, &mut ap);
        for _ in 0..6 {
            let s = ap.drive().unwrap();
            q.on_reached(s);
            q.on_current(ap.current);
            settle(&mut q, &mut ap);
        }
        // Autopilot reboots: empty mission, current 1.
        let mut ap2 = Autopilot::new(true);
        q.forget_onboard();
        q.stop();
        q.start();
        settle(&mut q, &mut ap2);
        while let Some(s) = ap2.drive() {
            q.on_reached(s);
            q.on_current(ap2.current);
            settle(&mut q, &mut ap2);
        }
        assert_eq!(ap2.reached, (6..20).collect::<Vec<_>>());
    }

    #[test]
    fn too_few_slots() {
        assert_eq!(
            RollingQueue::<u32>::new(2).unwrap_err(),
            QueueCreateError::TooFewSlots(2)
        );
    }

    #[test]
    fn the_current_item_is_restored_after_every_whole_upload() {
        // No partial writes and a current item reset by every upload: without restoring,
        // the vehicle would turn back to item 0 after each one.
        for slots in [3u16, 5] {
            let mut q = RollingQueue::new(slots).unwrap();
            let mut ap = Autopilot::new(false);
            ap.resets_current = true;
            q.push(0..50);
            q.start();
            settle(&mut q, &mut ap);
            let mut uploads = 0;
            while let Some(slot) = ap.drive() {
                let w = q.on_reached(slot);
                assert_eq!(w, ap.reached.last().copied());
                q.on_current(ap.current);
                while let Some(a) = q.poll() {
                    if let QueueAction::Upload(_) = a {
                        uploads += 1;
                        assert!(ap.apply(&a));
                        q.done(&a);
                        assert!(q.owes_restore());
                        assert_eq!(
                            q.poll(),
                            Some(QueueAction::SetCurrent(q.current_slot().unwrap()))
                        );
                        continue;
                    }
                    if ap.apply(&a) {
                        q.done(&a);
                    } else {
                        q.partial_unsupported();
                    }
                }
            }
            assert!(uploads > 10, "{uploads} uploads");
            assert_eq!(ap.backtracks, 0);
            assert_eq!(ap.reached, (0..50).collect::<Vec<_>>(), "{slots} slots");
        }
    }

    #[test]
    fn a_kept_current_item_needs_no_restoring_unless_the_upload_moved_the_target() {
        // Partial writes work: the upload that cuts the mission short after the last
        // waypoint leaves the target in its slot, and an autopilot that kept its current item
        // needs no set-current.
        let (mut q, mut ap) = flying_ten(5, true);
        let s = ap.drive().unwrap();
        q.on_reached(s);
        settle(&mut q, &mut ap);
        let slot = q.current_slot();
        q.clear();
        q.push([1, 2]);
        let upload = loop {
            let a = q.poll().expect("an upload cutting the mission short");
            assert!(ap.apply(&a));
            q.done(&a);
            if matches!(a, QueueAction::Upload(_)) {
                break a;
            }
        };
        assert_eq!(q.current_slot(), slot, "{upload:?}");
        assert!(q.owes_restore());
        q.current_kept();
        assert!(!q.owes_restore());
        assert_eq!(q.poll(), None);

        // Whole windows: the upload lays the window out from the target, in slot 1; a kept
        // current item names another slot, so the set-current is owed all the same.
        let (mut q, mut ap) = flying_ten(5, false);
        let s = ap.drive().unwrap();
        q.on_reached(s);
        // Laid out afresh only once the autopilot moved on by itself: its late advance would
        // otherwise follow the set-current to slot 1 and skip the target.
        assert_eq!(q.poll(), None);
        assert!(q.awaits_advance());
        q.on_current(ap.current);
        assert!(!q.awaits_advance());
        let a = q.poll().unwrap();
        assert_eq!(
            a,
            QueueAction::Upload(vec![1, 2, 3, 4, 5]),
            "from the target on"
        );
        ap.apply(&a);
        q.done(&a);
        assert_eq!(q.current_slot(), Some(1));
        q.current_kept();
        assert_eq!(q.poll(), Some(QueueAction::SetCurrent(1)));
        // Not navigating: nothing to restore.
        q.stop();
        q.done(&QueueAction::Upload(vec![1, 2, 3]));
        assert!(!q.owes_restore());
    }

    /// An autopilot that says nothing of resetting its current item on an upload but does
    /// (to item 0, home, so in effect to slot 1): with whole windows laid out from the target,
    /// the reset lands on the target, never on a passed waypoint.
    #[test]
    fn a_reset_after_a_whole_upload_lands_on_the_target() {
        let mut q = RollingQueue::new(5).unwrap();
        q.push(0..30);
        q.start();
        let mut ap = Autopilot::new(false);
        q.partial_unsupported();
        settle(&mut q, &mut ap);
        let mut reached = Vec::new();
        while let Some(s) = ap.drive() {
            reached.extend(q.on_reached(s));
            // Its MISSION_CURRENT after moving on.
            q.on_current(ap.current);
            let Some(a) = q.poll() else { continue };
            assert!(ap.apply(&a));
            if matches!(a, QueueAction::Upload(_)) {
                // The reset, before any set-current of ours: slot 1 must hold the target.
                assert_eq!(
                    ap.mission.first(),
                    q.target(),
                    "a reset would drive to {:?}",
                    ap.mission.first()
                );
            }
            q.done(&a);
            settle(&mut q, &mut ap);
        }
        assert_eq!(reached, (0..30).collect::<Vec<_>>());
    }

    #[test]
    fn heading_back_is_toward_a_passed_waypoint_or_home() {
        let mut q = RollingQueue::new(5).unwrap();
        q.push(0..10);
        // Not navigating: nothing counts.
        assert!(!q.heads_back(0, None));
        q.start();
        let mut ap = Autopilot::new(true);
        settle(&mut q, &mut ap);
        let s = ap.drive().unwrap();
        q.on_reached(s);
        settle(&mut q, &mut ap);
        // The second reach, before its slot is rewritten.
        let s = ap.drive().unwrap();
        q.on_reached(s);
        // Driving to slot 3 (waypoint 2); slot 1 was rewritten with waypoint 4 (ahead), slot
        // 2 still holds waypoint 1 (passed).
        assert_eq!(q.current_slot(), Some(3));
        assert!(!q.heads_back(3, None), "the target");
        assert!(!q.heads_back(4, None), "further ahead");
        assert!(q.heads_back(2, None), "waypoint 1, passed");
        assert!(!q.heads_back(1, None), "rewritten with a waypoint ahead");
        // Item 0: home where it is home; the target's copy where it is flown.
        assert!(q.heads_back(0, None));
        assert!(!q.heads_back(0, Some(&2)));
        assert!(q.heads_back(0, Some(&0)));
        // Unknown contents are not counted.
        q.forget_onboard();
        assert!(!q.heads_back(2, None));
    }
}

//! The ground-station side of a mission upload, as a pure state machine (no I/O, no tokio).
//!
//! After the start message (MISSION_COUNT for a whole mission, MISSION_WRITE_PARTIAL_LIST for a
//! range) the autopilot asks for each item with MISSION_REQUEST_INT (or the legacy
//! MISSION_REQUEST, answered with a float MISSION_ITEM) and ends with a MISSION_ACK. The
//! machine takes `now` and each incoming message, pushes what to send, and says when it next
//! needs [`MissionUpload::poll`] ([`MissionUpload::poll_at`]), like smoltcp's `poll`/`poll_at`.
//! The async driver in [`super::mission`] only moves messages and sleeps.
//!
//! Retries: every attempt waits `timeout`; silence resends the last message (after resync
//! bytes on a byte stream), a repeated request for the same item counts as another attempt,
//! and past `retries` attempts the transfer is cancelled with a MISSION_ACK. The deadline is
//! per attempt, not per message received, so stale requests and acknowledgements of earlier
//! transfers cannot postpone a resend. The start may have fewer attempts of its own
//! ([`UploadConfig::start_retries`]): a partial-write probe is one short attempt.
//!
//! Every MISSION_ACK result has its meaning ([`ack_meaning`]): ACCEPTED ends the transfer once
//! the last item went out (earlier, it belongs to an earlier transfer); INVALID_SEQUENCE once
//! items flow says the autopilot got an item it did not ask for and still waits for the one it
//! wants (an attempt, not an end), before any item that the start was refused (a partial write
//! past the end); every other result ends it with that result
//! ([`MissionError::Rejected`]), and at the start of a partial write UNSUPPORTED or DENIED
//! mean the autopilot has no partial writes ([`MissionError::PartialUnsupported`]).

use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    MavMessage, MavMissionResult, MavMissionType, MISSION_ACK_DATA,
};

use super::outbound::Outbound;
use super::types::{MissionError, MissionItem, MissionStage};

/// Who we are and how patient to be.
#[derive(Clone, Copy, Debug)]
pub(crate) struct UploadConfig {
    /// Our system id: requests addressed elsewhere are not for us.
    pub me: u8,
    /// The autopilot's (system, component).
    pub target: (u8, u8),
    /// Attempts per stage before giving up.
    pub retries: u32,
    /// How long one attempt waits.
    pub timeout: Duration,
    /// Attempts at the start message before giving up (a probe: 1).
    pub start_retries: u32,
}

/// What a MISSION_ACK result means to the transfer in progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum AckMeaning {
    /// MAV_MISSION_ACCEPTED: done (when the last item went out).
    Accepted,
    /// MAV_MISSION_INVALID_SEQUENCE: the autopilot still waits for the item it asked for.
    KeepGoing,
    /// Every other result: the autopilot ended the transfer.
    Ended,
}

/// The meaning of each MISSION_ACK result to an upload.
pub(crate) fn ack_meaning(result: MavMissionResult) -> AckMeaning {
    use MavMissionResult::*;
    match result {
        MAV_MISSION_ACCEPTED => AckMeaning::Accepted,
        MAV_MISSION_INVALID_SEQUENCE => AckMeaning::KeepGoing,
        MAV_MISSION_ERROR
        | MAV_MISSION_UNSUPPORTED_FRAME
        | MAV_MISSION_UNSUPPORTED
        | MAV_MISSION_NO_SPACE
        | MAV_MISSION_INVALID
        | MAV_MISSION_INVALID_PARAM1
        | MAV_MISSION_INVALID_PARAM2
        | MAV_MISSION_INVALID_PARAM3
        | MAV_MISSION_INVALID_PARAM4
        | MAV_MISSION_INVALID_PARAM5_X
        | MAV_MISSION_INVALID_PARAM6_Y
        | MAV_MISSION_INVALID_PARAM7
        | MAV_MISSION_DENIED
        | MAV_MISSION_OPERATION_CANCELLED => AckMeaning::Ended,
    }
}

/// One upload in progress: `items` numbered from `first`.
pub(crate) struct MissionUpload<'a> {
    cfg: UploadConfig,
    items: &'a [MissionItem],
    first: u16,
    last: u16,
    stage: MissionStage,
    attempts: u32,
    last_sent: MavMessage,
    deadline: Instant,
    /// The start message is MISSION_WRITE_PARTIAL_LIST.
    partial: bool,
    /// What is transferred (the start message's `mission_type`): the mission, or the fence;
    /// requests and acknowledgements of other types are someone else's.
    mission_type: MavMissionType,
}

/// What an incoming message means to the upload.
enum Step {
    /// The autopilot wants item `seq`, as MISSION_ITEM_INT (`true`) or MISSION_ITEM.
    Request(u16, bool),
    /// The transfer's MISSION_ACK.
    Ack(MavMissionResult),
}

/// The MISSION_ACK we send to `target`.
pub(crate) fn mission_ack(target: (u8, u8), result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: target.0,
        target_component: target.1,
        mavtype: result,
        ..Default::default()
    })
}

impl<'a> MissionUpload<'a> {
    /// Starts an upload at `now`: pushes `start` (MISSION_COUNT or MISSION_WRITE_PARTIAL_LIST)
    /// onto `out`.
    ///
    /// # Errors
    /// [`MissionError::Invalid`] when `items` is empty or does not fit after `first`.
    pub(crate) fn start(
        cfg: UploadConfig,
        start: MavMessage,
        items: &'a [MissionItem],
        first: u16,
        now: Instant,
        out: &mut Vec<Outbound>,
    ) -> Result<Self, MissionError> {
        let last = items
            .len()
            .checked_sub(1)
            .and_then(|n| u16::try_from(n).ok())
            .and_then(|n| first.checked_add(n))
            .ok_or_else(|| {
                MissionError::Invalid(format!("upload of {} items at {first}", items.len()))
            })?;
        let partial = matches!(start, MavMessage::MISSION_WRITE_PARTIAL_LIST(_));
        let mission_type = match &start {
            MavMessage::MISSION_COUNT(c) => c.mission_type,
            MavMessage::MISSION_WRITE_PARTIAL_LIST(p) => p.mission_type,
            _ => MavMissionType::MAV_MISSION_TYPE_MISSION,
        };
        out.push(Outbound::Message(start.clone()));
        Ok(Self {
            partial,
            cfg,
            items,
            first,
            last,
            stage: MissionStage::Start,
            attempts: 1,
            last_sent: start,
            deadline: now + cfg.timeout,
            mission_type,
        })
    }

    /// When [`Self::poll`] must run next if no message arrives.
    pub(crate) fn poll_at(&self) -> Instant {
        self.deadline
    }

    /// Handles the passing of time: at the deadline, resends or gives up.
    /// Returns the outcome once the transfer is over.
    pub(crate) fn poll(
        &mut self,
        now: Instant,
        out: &mut Vec<Outbound>,
    ) -> Option<Result<(), MissionError>> {
        if now < self.deadline {
            return None;
        }
        // Silence: our last message or the autopilot's request was lost.
        let limit = if self.stage == MissionStage::Start {
            self.cfg.start_retries.min(self.cfg.retries).max(1)
        } else {
            self.cfg.retries
        };
        if self.attempts >= limit {
            return Some(self.give_up(out));
        }
        self.attempts += 1;
        tracing::debug!(
            "mission transfer: silence at {:?}, attempt {}",
            self.stage,
            self.attempts
        );
        out.push(Outbound::Resync);
        out.push(Outbound::Message(self.last_sent.clone()));
        self.deadline = now + self.cfg.timeout;
        None
    }

    /// Handles one incoming message (anything not about this upload is ignored).
    /// Returns the outcome once the transfer is over.
    pub(crate) fn handle(
        &mut self,
        msg: &MavMessage,
        now: Instant,
        out: &mut Vec<Outbound>,
    ) -> Option<Result<(), MissionError>> {
        match self.classify(msg)? {
            Step::Request(seq, int) => self.on_request(seq, int, now, out),
            Step::Ack(result) => match ack_meaning(result) {
                // An ACK before the last item was sent belongs to an earlier transfer.
                AckMeaning::Accepted => {
                    (self.stage == MissionStage::Item(self.last)).then_some(Ok(()))
                }
                // Before any item: the start itself was refused (a range past the end).
                AckMeaning::KeepGoing if self.stage == MissionStage::Start => {
                    Some(Err(MissionError::Rejected(result)))
                }
                AckMeaning::KeepGoing => {
                    // It got an item it did not ask for (a stale resend): its next request
                    // or our resend at the deadline carries on; a loop of these still ends.
                    self.attempts += 1;
                    (self.attempts > self.cfg.retries).then(|| self.give_up(out))
                }
                AckMeaning::Ended
                    if self.partial
                        && self.stage == MissionStage::Start
                        && matches!(
                            result,
                            MavMissionResult::MAV_MISSION_UNSUPPORTED
                                | MavMissionResult::MAV_MISSION_DENIED
                        ) =>
                {
                    Some(Err(MissionError::PartialUnsupported))
                }
                AckMeaning::Ended => Some(Err(MissionError::Rejected(result))),
            },
        }
    }

    #[allow(deprecated)] // Legacy autopilots request MISSION_ITEM with MISSION_REQUEST.
    fn classify(&self, msg: &MavMessage) -> Option<Step> {
        let me = self.cfg.me;
        // Only our type (the mission itself, or the fence being uploaded): other transfers
        // are someone else's.
        let mission = self.mission_type;
        match msg {
            MavMessage::MISSION_REQUEST_INT(r)
                if r.target_system == me && r.mission_type == mission =>
            {
                Some(Step::Request(r.seq, true))
            }
            MavMessage::MISSION_REQUEST(r)
                if r.target_system == me && r.mission_type == mission =>
            {
                Some(Step::Request(r.seq, false))
            }
            MavMessage::MISSION_ACK(a)
                if (a.target_system == me || a.target_system == 0) && a.mission_type == mission =>
            {
                Some(Step::Ack(a.mavtype))
            }
            _ => None,
        }
    }

    fn on_request(
        &mut self,
        seq: u16,
        int: bool,
        now: Instant,
        out: &mut Vec<Outbound>,
    ) -> Option<Result<(), MissionError>> {
        if seq < self.first || seq > self.last {
            // A stale request from an earlier transfer.
            return None;
        }
        if self.stage == MissionStage::Item(seq) {
            // Asked again: our answer was lost.
            self.attempts += 1;
            if self.attempts > self.cfg.retries {
                return Some(self.give_up(out));
            }
        } else {
            self.stage = MissionStage::Item(seq);
            self.attempts = 1;
        }
        let item = &self.items[usize::from(seq - self.first)];
        #[allow(deprecated)]
        let msg = if int {
            let mut m = item.to_int(seq, self.cfg.target);
            m.mission_type = self.mission_type;
            MavMessage::MISSION_ITEM_INT(m)
        } else {
            let mut m = item.to_float(seq, self.cfg.target);
            m.mission_type = self.mission_type;
            MavMessage::MISSION_ITEM(m)
        };
        self.last_sent = msg.clone();
        out.push(Outbound::Message(msg));
        self.deadline = now + self.cfg.timeout;
        None
    }

    /// Cancels the transfer on the autopilot so it does not wait for the rest.
    fn give_up(&self, out: &mut Vec<Outbound>) -> Result<(), MissionError> {
        let mut ack = mission_ack(
            self.cfg.target,
            MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
        );
        if let MavMessage::MISSION_ACK(a) = &mut ack {
            a.mission_type = self.mission_type;
        }
        out.push(Outbound::Message(ack));
        Err(MissionError::RetriesExhausted {
            stage: self.stage,
            attempts: self.attempts,
        })
    }
}

#[cfg(test)]
#[allow(deprecated)]
mod tests {
    use mavlink::dialects::ardupilotmega::{
        MISSION_COUNT_DATA, MISSION_REQUEST_DATA, MISSION_REQUEST_INT_DATA,
        MISSION_WRITE_PARTIAL_LIST_DATA,
    };

    use super::*;

    const ME: u8 = 255;
    const TARGET: (u8, u8) = (1, 1);
    const TIMEOUT: Duration = Duration::from_millis(1000);

    fn cfg(retries: u32) -> UploadConfig {
        UploadConfig {
            me: ME,
            target: TARGET,
            retries,
            timeout: TIMEOUT,
            start_retries: retries,
        }
    }

    fn items(n: usize) -> Vec<MissionItem> {
        (0..n)
            .map(|i| MissionItem::waypoint(41.0 + i as f64 * 0.001, 2.0, 10.0))
            .collect()
    }

    fn count(n: u16) -> MavMessage {
        MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: n,
            target_system: TARGET.0,
            target_component: TARGET.1,
            ..Default::default()
        })
    }

    fn request_int(seq: u16) -> MavMessage {
        MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: ME,
            target_component: 190,
            ..Default::default()
        })
    }

    fn request_float(seq: u16) -> MavMessage {
        MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
            seq,
            target_system: ME,
            target_component: 190,
            ..Default::default()
        })
    }

    fn ack(result: MavMissionResult) -> MavMessage {
        mission_ack((ME, 190), result)
    }

    /// The seq of the item message in `out`, which must hold exactly that one message.
    fn sent_item(out: &mut Vec<Outbound>) -> u16 {
        let sent = std::mem::take(out);
        match sent.as_slice() {
            [Outbound::Message(MavMessage::MISSION_ITEM_INT(i))] => i.seq,
            [Outbound::Message(MavMessage::MISSION_ITEM(i))] => i.seq,
            other => panic!("expected one mission item, got {other:?}"),
        }
    }

    fn is_cancel(o: &Outbound) -> bool {
        matches!(o, Outbound::Message(MavMessage::MISSION_ACK(a))
            if a.mavtype == MavMissionResult::MAV_MISSION_OPERATION_CANCELLED
                && (a.target_system, a.target_component) == TARGET)
    }

    /// A whole-mission upload of `list` started at `t0`, its MISSION_COUNT already taken out.
    fn begin(
        retries: u32,
        list: &[MissionItem],
        t0: Instant,
    ) -> (MissionUpload<'_>, Vec<Outbound>) {
        let mut out = Vec::new();
        let n = u16::try_from(list.len()).expect("test lists are short");
        let up = MissionUpload::start(cfg(retries), count(n), list, 0, t0, &mut out)
            .expect("a valid upload");
        assert!(
            matches!(out.as_slice(), [Outbound::Message(MavMessage::MISSION_COUNT(c))] if c.count == n)
        );
        out.clear();
        (up, out)
    }

    /// The upload gave up at `stage` after `attempts`, cancelling it on the autopilot.
    fn assert_gave_up(
        done: Option<Result<(), MissionError>>,
        out: &[Outbound],
        stage: MissionStage,
        attempts: u32,
    ) {
        assert_eq!(
            done,
            Some(Err(MissionError::RetriesExhausted { stage, attempts }))
        );
        assert!(
            matches!(out, [o] if is_cancel(o)),
            "expected one cancel, got {out:?}"
        );
    }

    #[test]
    fn normal_upload_answers_each_request_and_ends_on_accept() {
        let t0 = Instant::now();
        let list = items(3);
        let (mut up, mut out) = begin(5, &list, t0);
        assert_eq!(up.poll_at(), t0 + TIMEOUT);
        for seq in 0..3 {
            let now = t0 + Duration::from_millis(100 * u64::from(seq + 1));
            assert_eq!(up.handle(&request_int(seq), now, &mut out), None);
            assert_eq!(sent_item(&mut out), seq);
            assert_eq!(
                up.poll_at(),
                now + TIMEOUT,
                "each answer restarts the attempt"
            );
        }
        let done = up.handle(&ack(MavMissionResult::MAV_MISSION_ACCEPTED), t0, &mut out);
        assert_eq!(done, Some(Ok(())));
        assert!(out.is_empty());
    }

    #[test]
    fn the_item_sent_carries_its_coordinates_and_target() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(5, &list, t0);
        up.handle(&request_int(1), t0, &mut out);
        match out.as_slice() {
            [Outbound::Message(MavMessage::MISSION_ITEM_INT(i))] => {
                assert_eq!(i, &list[1].to_int(1, TARGET));
            }
            other => panic!("expected MISSION_ITEM_INT, got {other:?}"),
        }
        out.clear();
        // The legacy request gets the legacy float item.
        up.handle(&request_float(0), t0, &mut out);
        match out.as_slice() {
            [Outbound::Message(MavMessage::MISSION_ITEM(i))] => {
                assert_eq!(i, &list[0].to_float(0, TARGET));
            }
            other => panic!("expected MISSION_ITEM, got {other:?}"),
        }
    }

    #[test]
    fn a_lost_request_is_answered_by_a_resend_at_the_deadline() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(5, &list, t0);
        // Before the deadline nothing happens.
        assert_eq!(
            up.poll(t0 + TIMEOUT - Duration::from_millis(1), &mut out),
            None
        );
        assert!(out.is_empty());
        // At the deadline: resync bytes, then MISSION_COUNT again.
        let t1 = t0 + TIMEOUT;
        assert_eq!(up.poll(t1, &mut out), None);
        assert!(matches!(
            out.as_slice(),
            [Outbound::Resync, Outbound::Message(MavMessage::MISSION_COUNT(c))] if c.count == 2
        ));
        assert_eq!(up.poll_at(), t1 + TIMEOUT);
        out.clear();
        // Item 0's answer is lost: the resend is the item, not the count.
        up.handle(&request_int(0), t1, &mut out);
        assert_eq!(sent_item(&mut out), 0);
        let t2 = t1 + TIMEOUT;
        up.poll(t2, &mut out);
        match out.as_slice() {
            [Outbound::Resync, Outbound::Message(MavMessage::MISSION_ITEM_INT(i))] => {
                assert_eq!(i.seq, 0);
            }
            other => panic!("expected resync and item 0, got {other:?}"),
        }
        out.clear();
        up.handle(&request_int(1), t2, &mut out);
        assert_eq!(sent_item(&mut out), 1);
        let done = up.handle(&ack(MavMissionResult::MAV_MISSION_ACCEPTED), t2, &mut out);
        assert_eq!(done, Some(Ok(())));
    }

    #[test]
    fn silence_through_every_attempt_cancels_and_fails() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(3, &list, t0);
        for _ in 0..2 {
            let now = up.poll_at();
            assert_eq!(up.poll(now, &mut out), None);
            assert_eq!(out.len(), 2, "resync and resend");
            out.clear();
        }
        let now = up.poll_at();
        assert_eq!(now, t0 + TIMEOUT * 3);
        let done = up.poll(now, &mut out);
        assert_gave_up(done, &out, MissionStage::Start, 3);
    }

    #[test]
    fn silence_after_an_item_fails_at_that_item() {
        let t0 = Instant::now();
        let list = items(3);
        let (mut up, mut out) = begin(2, &list, t0);
        up.handle(&request_int(0), t0, &mut out);
        up.handle(&request_int(1), t0, &mut out);
        out.clear();
        assert_eq!(up.poll(up.poll_at(), &mut out), None);
        out.clear();
        let done = up.poll(up.poll_at(), &mut out);
        assert_gave_up(done, &out, MissionStage::Item(1), 2);
    }

    #[test]
    fn a_nack_ends_the_transfer_with_its_result() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(5, &list, t0);
        up.handle(&request_int(0), t0, &mut out);
        out.clear();
        let done = up.handle(&ack(MavMissionResult::MAV_MISSION_NO_SPACE), t0, &mut out);
        assert_eq!(
            done,
            Some(Err(MissionError::Rejected(
                MavMissionResult::MAV_MISSION_NO_SPACE
            )))
        );
        assert!(out.is_empty(), "the autopilot ended it: no cancel to send");
    }

    #[test]
    fn duplicate_requests_resend_until_the_retries_run_out() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(3, &list, t0);
        for _ in 0..3 {
            assert_eq!(up.handle(&request_int(0), t0, &mut out), None);
            assert_eq!(sent_item(&mut out), 0);
        }
        let done = up.handle(&request_int(0), t0, &mut out);
        assert_gave_up(done, &out, MissionStage::Item(0), 4);
    }

    #[test]
    fn out_of_order_and_stale_messages_are_handled_as_before() {
        let t0 = Instant::now();
        let list = items(3);
        let (mut up, mut out) = begin(5, &list, t0);
        // An ACCEPTED before the last item belongs to an earlier transfer.
        assert_eq!(
            up.handle(&ack(MavMissionResult::MAV_MISSION_ACCEPTED), t0, &mut out),
            None
        );
        // A request past the end is stale: ignored, deadline unchanged.
        let later = t0 + Duration::from_millis(500);
        assert_eq!(up.handle(&request_int(7), later, &mut out), None);
        assert!(out.is_empty());
        assert_eq!(up.poll_at(), t0 + TIMEOUT);
        // Requests addressed to another ground station are not ours.
        let other = MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq: 0,
            target_system: 42,
            target_component: 190,
            ..Default::default()
        });
        assert_eq!(up.handle(&other, later, &mut out), None);
        assert!(out.is_empty());
        // Out of order: each request gets the item it names.
        up.handle(&request_int(2), later, &mut out);
        assert_eq!(sent_item(&mut out), 2);
        up.handle(&request_int(0), later, &mut out);
        assert_eq!(sent_item(&mut out), 0);
        up.handle(&request_int(1), later, &mut out);
        assert_eq!(sent_item(&mut out), 1);
        // The last item requested was 1, not the last one: an ACCEPTED is still stale.
        assert_eq!(
            up.handle(
                &ack(MavMissionResult::MAV_MISSION_ACCEPTED),
                later,
                &mut out
            ),
            None
        );
        up.handle(&request_int(2), later, &mut out);
        assert_eq!(sent_item(&mut out), 2);
        assert_eq!(
            up.handle(
                &ack(MavMissionResult::MAV_MISSION_ACCEPTED),
                later,
                &mut out
            ),
            Some(Ok(()))
        );
    }

    #[test]
    fn partial_write_numbers_items_from_the_start_index() {
        let t0 = Instant::now();
        let list = items(2);
        let start = MavMessage::MISSION_WRITE_PARTIAL_LIST(MISSION_WRITE_PARTIAL_LIST_DATA {
            start_index: 3,
            end_index: 4,
            target_system: TARGET.0,
            target_component: TARGET.1,
            ..Default::default()
        });
        let mut out = Vec::new();
        let mut up = MissionUpload::start(cfg(5), start, &list, 3, t0, &mut out).unwrap();
        assert!(matches!(
            out.as_slice(),
            [Outbound::Message(MavMessage::MISSION_WRITE_PARTIAL_LIST(p))] if p.start_index == 3
        ));
        out.clear();
        // Items outside 3..=4 are not part of this write.
        assert_eq!(up.handle(&request_int(2), t0, &mut out), None);
        assert_eq!(up.handle(&request_int(5), t0, &mut out), None);
        assert!(out.is_empty());
        up.handle(&request_int(3), t0, &mut out);
        match out.as_slice() {
            [Outbound::Message(MavMessage::MISSION_ITEM_INT(i))] => {
                assert_eq!(i, &list[0].to_int(3, TARGET));
            }
            other => panic!("expected item 3, got {other:?}"),
        }
        out.clear();
        up.handle(&request_int(4), t0, &mut out);
        assert_eq!(sent_item(&mut out), 4);
        assert_eq!(
            up.handle(&ack(MavMissionResult::MAV_MISSION_ACCEPTED), t0, &mut out),
            Some(Ok(()))
        );
    }

    #[test]
    fn an_empty_or_overflowing_upload_is_refused() {
        let mut out = Vec::new();
        let none: Vec<MissionItem> = Vec::new();
        assert!(matches!(
            MissionUpload::start(cfg(5), count(0), &none, 0, Instant::now(), &mut out),
            Err(MissionError::Invalid(_))
        ));
        let two = items(2);
        assert!(matches!(
            MissionUpload::start(cfg(5), count(2), &two, u16::MAX, Instant::now(), &mut out),
            Err(MissionError::Invalid(_))
        ));
        assert!(out.is_empty());
    }

    fn partial_start(start: u16, end: u16) -> MavMessage {
        MavMessage::MISSION_WRITE_PARTIAL_LIST(MISSION_WRITE_PARTIAL_LIST_DATA {
            start_index: start as i16,
            end_index: end as i16,
            target_system: TARGET.0,
            target_component: TARGET.1,
            ..Default::default()
        })
    }

    #[test]
    fn a_probe_is_one_short_attempt_at_the_start_then_normal_retries() {
        let t0 = Instant::now();
        let list = items(2);
        let probe = UploadConfig {
            start_retries: 1,
            ..cfg(5)
        };
        let mut out = Vec::new();
        let mut up =
            MissionUpload::start(probe, partial_start(2, 3), &list, 2, t0, &mut out).unwrap();
        out.clear();
        // Unanswered: one attempt only, then the cancel, within one timeout.
        let done = up.poll(t0 + TIMEOUT, &mut out);
        assert_gave_up(done, &out, MissionStage::Start, 1);

        // Answered: the items get the full retries.
        let mut out = Vec::new();
        let mut up =
            MissionUpload::start(probe, partial_start(2, 3), &list, 2, t0, &mut out).unwrap();
        out.clear();
        up.handle(&request_int(2), t0, &mut out);
        assert_eq!(sent_item(&mut out), 2);
        for k in 1..5 {
            let now = up.poll_at();
            assert_eq!(up.poll(now, &mut out), None, "item resend {k}");
            out.clear();
        }
        let done = up.poll(up.poll_at(), &mut out);
        assert_gave_up(done, &out, MissionStage::Item(2), 5);
    }

    #[test]
    fn every_mission_ack_result_has_its_meaning() {
        use MavMissionResult::*;
        assert_eq!(ack_meaning(MAV_MISSION_ACCEPTED), AckMeaning::Accepted);
        assert_eq!(
            ack_meaning(MAV_MISSION_INVALID_SEQUENCE),
            AckMeaning::KeepGoing
        );
        for r in [
            MAV_MISSION_ERROR,
            MAV_MISSION_UNSUPPORTED_FRAME,
            MAV_MISSION_UNSUPPORTED,
            MAV_MISSION_NO_SPACE,
            MAV_MISSION_INVALID,
            MAV_MISSION_INVALID_PARAM1,
            MAV_MISSION_INVALID_PARAM7,
            MAV_MISSION_DENIED,
            MAV_MISSION_OPERATION_CANCELLED,
        ] {
            assert_eq!(ack_meaning(r), AckMeaning::Ended, "{r:?}");
            // Each ends a whole upload with that very result, without a cancel of ours.
            let t0 = Instant::now();
            let list = items(2);
            let (mut up, mut out) = begin(5, &list, t0);
            up.handle(&request_int(0), t0, &mut out);
            out.clear();
            assert_eq!(
                up.handle(&ack(r), t0, &mut out),
                Some(Err(MissionError::Rejected(r)))
            );
            assert!(out.is_empty());
        }
    }

    #[test]
    fn invalid_sequence_is_an_attempt_not_an_end() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(2, &list, t0);
        up.handle(&request_int(0), t0, &mut out);
        out.clear();
        let nak = ack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE);
        assert_eq!(up.handle(&nak, t0, &mut out), None);
        // The autopilot asks again for what it wants: the transfer carries on.
        up.handle(&request_int(1), t0, &mut out);
        assert_eq!(sent_item(&mut out), 1);
        assert_eq!(
            up.handle(&ack(MavMissionResult::MAV_MISSION_ACCEPTED), t0, &mut out),
            Some(Ok(()))
        );
        // Before any item it refuses the start (a partial write past the end).
        let (mut up, mut out) = begin(2, &list, t0);
        assert_eq!(
            up.handle(&nak, t0, &mut out),
            Some(Err(MissionError::Rejected(
                MavMissionResult::MAV_MISSION_INVALID_SEQUENCE
            )))
        );
        // A loop of them ends at the retries.
        let (mut up, mut out) = begin(2, &list, t0);
        up.handle(&request_int(0), t0, &mut out);
        out.clear();
        assert_eq!(up.handle(&nak, t0, &mut out), None);
        let done = up.handle(&nak, t0, &mut out);
        assert_gave_up(done, &out, MissionStage::Item(0), 3);
    }

    #[test]
    fn a_partial_write_refused_at_the_start_means_no_partial_writes() {
        let t0 = Instant::now();
        let list = items(1);
        for r in [
            MavMissionResult::MAV_MISSION_UNSUPPORTED,
            MavMissionResult::MAV_MISSION_DENIED,
        ] {
            let mut out = Vec::new();
            let mut up =
                MissionUpload::start(cfg(5), partial_start(1, 1), &list, 1, t0, &mut out).unwrap();
            out.clear();
            assert_eq!(
                up.handle(&ack(r), t0, &mut out),
                Some(Err(MissionError::PartialUnsupported))
            );
        }
        // The same refusal of a whole upload is just a refusal.
        let (mut up, mut out) = begin(5, &list, t0);
        assert_eq!(
            up.handle(&ack(MavMissionResult::MAV_MISSION_DENIED), t0, &mut out),
            Some(Err(MissionError::Rejected(
                MavMissionResult::MAV_MISSION_DENIED
            )))
        );
    }

    #[test]
    fn requests_and_acks_of_another_mission_type_are_not_ours() {
        let t0 = Instant::now();
        let list = items(2);
        let (mut up, mut out) = begin(5, &list, t0);
        let fence = MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq: 0,
            target_system: ME,
            target_component: 190,
            mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
        });
        assert_eq!(up.handle(&fence, t0, &mut out), None);
        assert!(
            out.is_empty(),
            "a fence request is not answered with a mission item"
        );
        let rally_nak = MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: ME,
            target_component: 190,
            mavtype: MavMissionResult::MAV_MISSION_DENIED,
            mission_type: MavMissionType::MAV_MISSION_TYPE_RALLY,
            ..Default::default()
        });
        assert_eq!(up.handle(&rally_nak, t0, &mut out), None);
        up.handle(&request_int(0), t0, &mut out);
        assert_eq!(sent_item(&mut out), 0);
    }
}

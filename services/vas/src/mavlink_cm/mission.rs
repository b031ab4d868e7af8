//! The mission protocol on [`MavlinkManager`]: upload (full or partial, through the pure
//! [`MissionUpload`] machine), download, clear and set-current.

use marea::sync::lock;
use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavMissionResult, MavMissionType, MavProtocolCapability,
    MISSION_CLEAR_ALL_DATA, MISSION_COUNT_DATA, MISSION_REQUEST_DATA, MISSION_REQUEST_INT_DATA,
    MISSION_REQUEST_LIST_DATA, MISSION_SET_CURRENT_DATA, MISSION_WRITE_PARTIAL_LIST_DATA,
};
use std::time::Duration;

use tokio::sync::broadcast;
use tokio::time::{timeout_at, Instant};

use super::driver::Inner;
use super::manager::MavlinkManager;
use super::mission_upload::{mission_ack, MissionUpload, UploadConfig};
use super::types::*;

/// Whether the autopilot has partial mission writes, as its identity advertises it: an
/// autopilot that answered AUTOPILOT_VERSION and whose heartbeat names ArduPilot (which has
/// them) or PX4 (which has not). `None`: unknown (anything else, or no AUTOPILOT_VERSION):
/// it must be probed.
pub(crate) fn partial_writes_by_identity(s: &super::manager::VehicleState) -> Option<bool> {
    use mavlink::dialects::ardupilotmega::MavAutopilot;
    s.capabilities?;
    match s.autopilot? {
        MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Some(true),
        MavAutopilot::MAV_AUTOPILOT_PX4 => Some(false),
        _ => None,
    }
}

impl MavlinkManager {
    pub fn mission_cached(&self) -> Vec<MissionItem> {
        lock(&self.inner.mission).clone()
    }

    /// Uploads a whole mission. `items[0]` is the home slot on ArduPilot (the
    /// autopilot keeps its own home there). The autopilot stages or overwrites
    /// as it sees fit; on any failure the transfer is cancelled with a
    /// MISSION_ACK so it does not wait for the rest.
    ///
    /// # Errors
    /// Empty list, refusal, or retries exhausted at some item.
    pub async fn mission_upload(&self, items: &[MissionItem]) -> Result<(), MissionError> {
        if items.is_empty() || items.len() > usize::from(u16::MAX) {
            return Err(MissionError::Invalid(format!("{} items", items.len())));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let start = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: items.len() as u16,
            target_system: target.0,
            target_component: target.1,
            ..Default::default()
        });
        self.inner.upload(target, start, items, 0).await?;
        *lock(&self.inner.mission) = items.to_vec();
        Ok(())
    }

    /// Uploads the fence (`mission_type` FENCE): polygon vertices and circles as
    /// MAV_CMD_NAV_FENCE_* items, numbered from 0 (no home slot). An empty list clears it.
    ///
    /// # Errors
    /// Refusal (an autopilot without fences answers UNSUPPORTED), or retries exhausted.
    pub async fn fence_upload(&self, items: &[MissionItem]) -> Result<(), MissionError> {
        if items.len() > usize::from(u16::MAX) {
            return Err(MissionError::Invalid(format!(
                "{} fence items",
                items.len()
            )));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        if items.is_empty() {
            let mut rx = self.inner.raw_tx.subscribe();
            let clear = MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
                target_system: target.0,
                target_component: target.1,
                mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
            });
            self.inner
                .put(super::outbound::Outbound::Message(clear))
                .await?;
            // Best effort: the ack is awaited briefly, a missing one is not an error.
            let until = Instant::now() + self.inner.cfg.request_timeout;
            while let Ok(Ok(m)) = timeout_at(until, rx.recv()).await {
                if let MavMessage::MISSION_ACK(a) = &*m {
                    if a.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE {
                        break;
                    }
                }
            }
            return Ok(());
        }
        let start = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: items.len() as u16,
            target_system: target.0,
            target_component: target.1,
            mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
            ..Default::default()
        });
        self.inner.upload(target, start, items, 0).await
    }

    /// Replaces items `start .. start + items.len()` with MISSION_WRITE_PARTIAL_LIST
    /// (ArduPilot only replaces existing items; it cannot grow the mission).
    ///
    /// Whether the autopilot has partial writes is remembered per connection
    /// ([`MavlinkManager::partial_writes`]; the VAS finds out on the ground with
    /// [`Self::probe_partial_writes`]): once known to lack them, this fails at once. Not yet
    /// known, a write whose start goes unanswered through every retry records the lack.
    ///
    /// # Errors
    /// [`MissionError::PartialUnsupported`] when the probe went unanswered or was refused (or
    /// an earlier one on this connection did); otherwise empty list, refusal, or retries
    /// exhausted.
    pub async fn mission_write_partial(
        &self,
        start: u16,
        items: &[MissionItem],
    ) -> Result<(), MissionError> {
        let end = usize::from(start) + items.len();
        if items.is_empty() || start == 0 || end > i16::MAX as usize {
            return Err(MissionError::Invalid(format!(
                "partial write of {} items at {start}",
                items.len()
            )));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let known = *lock(&self.inner.partial);
        if known == Some(false) {
            return Err(MissionError::PartialUnsupported);
        }
        let msg = MavMessage::MISSION_WRITE_PARTIAL_LIST(MISSION_WRITE_PARTIAL_LIST_DATA {
            start_index: start as i16,
            end_index: (end - 1) as i16,
            target_system: target.0,
            target_component: target.1,
            ..Default::default()
        });
        let probing = known.is_none();
        let began = std::time::Instant::now();
        let result = self
            .inner
            .upload_with(target, msg, items, start, self.inner.cfg.retries)
            .await;
        let answered = match &result {
            Err(MissionError::PartialUnsupported) => Some(false),
            Err(MissionError::RetriesExhausted {
                stage: MissionStage::Start,
                ..
            }) if probing => Some(false),
            // Any request (or any other end) means it speaks the protocol.
            Err(MissionError::RetriesExhausted {
                stage: MissionStage::Start,
                ..
            })
            | Err(MissionError::Link(_)) => None,
            _ => Some(true),
        };
        if probing {
            if let Some(ok) = answered {
                *lock(&self.inner.partial) = Some(ok);
                tracing::info!(
                    "partial mission writes {} (probe took {} ms)",
                    if ok { "supported" } else { "not supported" },
                    began.elapsed().as_millis()
                );
            }
        }
        match result {
            Err(MissionError::RetriesExhausted {
                stage: MissionStage::Start,
                ..
            }) if probing => return Err(MissionError::PartialUnsupported),
            r => r?,
        }
        let mut cache = lock(&self.inner.mission);
        if cache.len() >= end {
            cache[usize::from(start)..end].clone_from_slice(items);
        }
        Ok(())
    }

    /// Finds out whether the autopilot answers MISSION_WRITE_PARTIAL_LIST, with one short
    /// attempt (one request timeout, at least a second; the start sent twice, so one lost frame on a lossy link
    /// does not decide it), and remembers it for this connection
    /// ([`Self::partial_writes`]). Done before flying (the VAS probes while configuring the
    /// autopilot), so an autopilot without partial writes costs one timeout on the ground,
    /// not a stall in flight. The probe writes item 1 onto itself and cancels at once: an
    /// autopilot commits a transfer only when complete, so nothing on board changes. Any
    /// answer but UNSUPPORTED or DENIED (a request, or an ACK such as INVALID_SEQUENCE for
    /// an empty mission) means the autopilot speaks it.
    ///
    /// Where the autopilot has identified itself with AUTOPILOT_VERSION (its capabilities
    /// are known, [`Self::request_capabilities`]), its heartbeat's `autopilot` field tells the
    /// answer without a probe: MAVLink has no capability bit for partial writes, but ArduPilot
    /// implements them and PX4 does not ([`partial_writes_by_identity`]).
    ///
    /// # Errors
    /// Not connected, or shut down.
    pub async fn probe_partial_writes(&self) -> Result<bool, LinkError> {
        if let Some(known) = *lock(&self.inner.partial) {
            return Ok(known);
        }
        if let Some(known) = partial_writes_by_identity(&self.state()) {
            *lock(&self.inner.partial) = Some(known);
            tracing::info!(
                "partial mission writes {} (the identified {} autopilot; no probe)",
                if known { "supported" } else { "not supported" },
                if known { "ArduPilot" } else { "PX4" }
            );
            return Ok(known);
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let me = self.inner.cfg.system_id;
        let mut rx = self.inner.raw_tx.subscribe();
        let began = Instant::now();
        for _ in 0..2 {
            self.inner
                .send(MavMessage::MISSION_WRITE_PARTIAL_LIST(
                    MISSION_WRITE_PARTIAL_LIST_DATA {
                        start_index: 1,
                        end_index: 1,
                        target_system: target.0,
                        target_component: target.1,
                        ..Default::default()
                    },
                ))
                .await?;
        }
        // At least a second: a request timeout tuned to a fast radio's round trip is too
        // short a verdict on a whole protocol feature.
        let wait = self.inner.cfg.request_timeout.max(Duration::from_secs(1));
        #[allow(deprecated)]
        let answer = super::driver::wait_for(&mut rx, began + wait, |m| match m {
            MavMessage::MISSION_REQUEST_INT(r) if r.target_system == me => Some(None),
            MavMessage::MISSION_REQUEST(r) if r.target_system == me => Some(None),
            MavMessage::MISSION_ACK(a) if a.target_system == me || a.target_system == 0 => {
                Some(Some(a.mavtype))
            }
            _ => None,
        })
        .await?;
        let supported = match answer {
            Some(None) => {
                // It asked for the item: cancel, nothing is committed.
                self.inner
                    .send(mission_ack(
                        target,
                        MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
                    ))
                    .await?;
                true
            }
            Some(Some(
                MavMissionResult::MAV_MISSION_UNSUPPORTED | MavMissionResult::MAV_MISSION_DENIED,
            ))
            | None => false,
            Some(Some(_)) => true,
        };
        *lock(&self.inner.partial) = Some(supported);
        tracing::info!(
            "partial mission writes {} (probe took {} ms)",
            if supported {
                "supported"
            } else {
                "not supported"
            },
            began.elapsed().as_millis()
        );
        Ok(supported)
    }

    /// Downloads the whole mission (home first).
    ///
    /// # Errors
    /// Retries exhausted at the count or at some item.
    pub async fn mission_download(&self) -> Result<Vec<MissionItem>, MissionError> {
        let items = self.mission_read(None).await?;
        *lock(&self.inner.mission) = items.clone();
        Ok(items)
    }

    /// Reads items `first..=last` only, a partial read (the seed's GetWaypointsPartialList):
    /// the item count, those items by index, then MISSION_ACK. Not with
    /// MISSION_REQUEST_PARTIAL_LIST, which ArduPilot and PX4 leave unanswered; every autopilot
    /// answers item requests by index. What was last downloaded whole is not changed.
    ///
    /// # Errors
    /// `first > last` or `last` past the mission's end (`Invalid`, naming the mission's
    /// length), refusal or no answer.
    pub async fn mission_download_range(
        &self,
        first: u16,
        last: u16,
    ) -> Result<Vec<MissionItem>, MissionError> {
        if first > last {
            return Err(MissionError::Invalid(format!(
                "items {first}..={last}: the first is after the last"
            )));
        }
        self.mission_read(Some((first, last))).await
    }

    /// The mission download: every item (`None`) or `first..=last`.
    async fn mission_read(
        &self,
        range: Option<(u16, u16)>,
    ) -> Result<Vec<MissionItem>, MissionError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system: target.0,
                target_component: target.1,
                ..Default::default()
            })
        };
        let count = self
            .inner
            .transact(make, |m| match m {
                MavMessage::MISSION_COUNT(c)
                    if c.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
                {
                    Some(c.count)
                }
                _ => None,
            })
            .await?
            .ok_or(MissionError::RetriesExhausted {
                stage: MissionStage::Count,
                attempts: self.inner.cfg.retries,
            })?;
        let seqs = match range {
            None => 0..count,
            Some((first, last)) if last < count => first..last + 1,
            Some((first, last)) => {
                // End the transfer the count began before saying why.
                self.inner
                    .send(mission_ack(target, MavMissionResult::MAV_MISSION_ACCEPTED))
                    .await?;
                return Err(MissionError::Invalid(format!(
                    "items {first}..={last} asked, the mission has {count} (0..={})",
                    count.saturating_sub(1)
                )));
            }
        };
        let mut items = Vec::with_capacity(seqs.len());
        // MISSION_REQUEST_INT unless AUTOPILOT_VERSION said the autopilot lacks MISSION_INT.
        let int = self.state().capabilities.is_none_or(|c| {
            c & MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_INT.bits() != 0
        });
        for seq in seqs {
            #[allow(deprecated)] // The float request, for autopilots without MISSION_INT.
            let make = |_| {
                if int {
                    MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                        seq,
                        target_system: target.0,
                        target_component: target.1,
                        ..Default::default()
                    })
                } else {
                    MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
                        seq,
                        target_system: target.0,
                        target_component: target.1,
                        ..Default::default()
                    })
                }
            };
            #[allow(deprecated)] // Legacy autopilots answer with MISSION_ITEM.
            let matcher = |m: &MavMessage| match m {
                MavMessage::MISSION_ITEM_INT(i)
                    if i.seq == seq
                        && i.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
                {
                    Some(MissionItem::from_int(i))
                }
                MavMessage::MISSION_ITEM(i)
                    if i.seq == seq
                        && i.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
                {
                    Some(MissionItem::from_float(i))
                }
                _ => None,
            };
            let item = self.inner.transact(make, matcher).await?.ok_or(
                MissionError::RetriesExhausted {
                    stage: MissionStage::Item(seq),
                    attempts: self.inner.cfg.retries,
                },
            )?;
            items.push(item);
        }
        self.inner
            .send(mission_ack(target, MavMissionResult::MAV_MISSION_ACCEPTED))
            .await?;
        Ok(items)
    }

    /// Clears the mission (ArduPilot keeps home). A rover in AUTO still drives
    /// to the item it had memorised, then holds (003 §2.5.4).
    ///
    /// # Errors
    /// Refusal or no answer.
    pub async fn mission_clear(&self) -> Result<(), MissionError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
                target_system: target.0,
                target_component: target.1,
                ..Default::default()
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::MISSION_ACK(a)
                if a.target_system == self.inner.cfg.system_id || a.target_system == 0 =>
            {
                Some(a.mavtype)
            }
            _ => None,
        };
        match self.inner.transact(make, matcher).await? {
            Some(MavMissionResult::MAV_MISSION_ACCEPTED) => {
                lock(&self.inner.mission).clear();
                Ok(())
            }
            Some(other) => Err(MissionError::Rejected(other)),
            None => Err(MissionError::RetriesExhausted {
                stage: MissionStage::Ack,
                attempts: self.inner.cfg.retries,
            }),
        }
    }

    /// Makes `seq` the current item (the vehicle turns to it at once in AUTO),
    /// confirmed by MISSION_CURRENT; falls back to MAV_CMD_DO_SET_MISSION_CURRENT.
    /// The jump is not reported as a waypoint reached.
    ///
    /// # Errors
    /// No confirmation by either method.
    pub async fn mission_set_current(&self, seq: u16) -> Result<(), MissionError> {
        let target = self.inner.target().await?;
        lock(&self.inner.reach).expect_jump(seq);
        #[allow(deprecated)] // MISSION_SET_CURRENT is what ArduPilot of every age understands.
        let make = |_| {
            MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
                seq,
                target_system: target.0,
                target_component: target.1,
            })
        };
        // The autopilot reporting `seq` current verifies it, and so does its reaching `seq`:
        // a vehicle already at that item reaches it and advances at once, and when its report
        // of `seq` is lost on the radio, another attempt would only send it back to an item
        // it has just passed (a backtrack: the waypoint reached twice).
        let matcher = |m: &MavMessage| match m {
            MavMessage::MISSION_CURRENT(c) if c.seq == seq => Some(()),
            MavMessage::MISSION_ITEM_REACHED(r) if r.seq == seq => Some(()),
            _ => None,
        };
        // Sent twice per attempt (the rolling queue's wrap has one leg of slack), the second
        // copy only when the first is unconfirmed half a request timeout later: sent at once,
        // it could reach a vehicle that took the first, reached `seq` and went on, and set it
        // back. An autopilot that sends MISSION_CURRENT only on change says nothing when `seq`
        // already was current: after a silent attempt, the last MISSION_CURRENT it reported
        // verifies it.
        let mut rx = self.inner.raw_tx.subscribe();
        for attempt in 0..self.inner.cfg.retries {
            if attempt > 0 {
                if self.inner.state_tx.borrow().mission_current == Some(seq) {
                    return Ok(());
                }
                self.inner.resync().await?;
            }
            let sent = Instant::now();
            let halfway = sent + self.inner.cfg.request_timeout / 2;
            let deadline = sent + self.inner.cfg.request_timeout;
            for until in [halfway, deadline] {
                self.inner.send(make(attempt)).await?;
                if super::driver::wait_for(&mut rx, until, matcher)
                    .await?
                    .is_some()
                {
                    return Ok(());
                }
            }
        }
        if self.inner.state_tx.borrow().mission_current == Some(seq) {
            return Ok(());
        }
        match self
            .command_long(
                MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
                [f32::from(seq), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            )
            .await
        {
            Ok(()) => Ok(()),
            Err(CommandError::Link(e)) => Err(e.into()),
            Err(_) => Err(MissionError::RetriesExhausted {
                stage: MissionStage::SetCurrent,
                attempts: self.inner.cfg.retries * 2,
            }),
        }
    }
}

impl Inner {
    /// Runs a [`MissionUpload`] of `items` (numbered from `first`) after `start`
    /// (MISSION_COUNT or MISSION_WRITE_PARTIAL_LIST): moves its messages to the wire and the
    /// autopilot's to it, and sleeps until its deadline.
    async fn upload(
        &self,
        target: (u8, u8),
        start: MavMessage,
        items: &[MissionItem],
        first: u16,
    ) -> Result<(), MissionError> {
        self.upload_with(target, start, items, first, self.cfg.retries)
            .await
    }

    /// [`Self::upload`] with `start_retries` attempts at the start message.
    async fn upload_with(
        &self,
        target: (u8, u8),
        start: MavMessage,
        items: &[MissionItem],
        first: u16,
        start_retries: u32,
    ) -> Result<(), MissionError> {
        // Subscribed before the start goes out, so no early answer is missed.
        let mut rx = self.raw_tx.subscribe();
        let cfg = UploadConfig {
            me: self.cfg.system_id,
            target,
            retries: self.cfg.retries,
            timeout: self.cfg.request_timeout,
            start_retries,
        };
        let mut out = Vec::new();
        let mut upload = MissionUpload::start(
            cfg,
            start,
            items,
            first,
            Instant::now().into_std(),
            &mut out,
        )?;
        loop {
            for o in out.drain(..) {
                self.put(o).await?;
            }
            let deadline = Instant::from_std(upload.poll_at());
            let done = match timeout_at(deadline, rx.recv()).await {
                // The timer fired, so the deadline has passed whatever the clock says.
                Err(_) => upload.poll(Instant::now().into_std().max(upload.poll_at()), &mut out),
                Ok(Ok(msg)) => upload.handle(&msg, Instant::now().into_std(), &mut out),
                Ok(Err(broadcast::error::RecvError::Lagged(_))) => None,
                Ok(Err(broadcast::error::RecvError::Closed)) => {
                    return Err(LinkError::Closed.into())
                }
            };
            if let Some(result) = done {
                for o in out.drain(..) {
                    self.put(o).await?;
                }
                return result;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mavlink_cm::VehicleState;
    use mavlink::dialects::ardupilotmega::MavAutopilot;

    #[test]
    fn an_identified_autopilot_needs_no_partial_write_probe() {
        let mut s = VehicleState {
            autopilot: Some(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA),
            ..VehicleState::default()
        };
        assert_eq!(
            partial_writes_by_identity(&s),
            None,
            "no AUTOPILOT_VERSION yet"
        );
        s.capabilities = Some(0x200d);
        assert_eq!(partial_writes_by_identity(&s), Some(true));
        s.autopilot = Some(MavAutopilot::MAV_AUTOPILOT_PX4);
        assert_eq!(partial_writes_by_identity(&s), Some(false));
        s.autopilot = Some(MavAutopilot::MAV_AUTOPILOT_GENERIC);
        assert_eq!(partial_writes_by_identity(&s), None, "probed");
    }
}

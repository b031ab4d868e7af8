//! Structure-aware fuzzing of the mission upload machine ([`super::mission_upload`], feature
//! `fuzzing`): MAVLink messages of the kinds it reads (MISSION_REQUEST_INT, legacy
//! MISSION_REQUEST, MISSION_ACK of every result, for us, for another system or broadcast, with
//! sequence numbers inside, around and far outside the upload) and unrelated traffic, in
//! random order, interleaved with the passing of time. Checks: never a panic; at most two
//! messages out per step; every item sent is one of the upload's, with the content it was
//! given; success only after the last item went out; a silent autopilot ends the upload within
//! its retry budget. Reached through [`crate::mavlink_cm::fuzz_mission_upload`].

use std::time::{Duration, Instant};

use arbitrary::{Result, Unstructured};
use mavlink::dialects::ardupilotmega::{
    MavMessage, MavMissionResult, HEARTBEAT_DATA, MISSION_COUNT_DATA, MISSION_REQUEST_DATA,
    MISSION_REQUEST_INT_DATA,
};

use super::mission_upload::{mission_ack, MissionUpload, UploadConfig};
use super::outbound::Outbound;
use super::types::MissionItem;

const ME: u8 = 255;
const TARGET: (u8, u8) = (1, 1);

const RESULTS: &[MavMissionResult] = &[
    MavMissionResult::MAV_MISSION_ACCEPTED,
    MavMissionResult::MAV_MISSION_ERROR,
    MavMissionResult::MAV_MISSION_NO_SPACE,
    MavMissionResult::MAV_MISSION_INVALID_SEQUENCE,
    MavMissionResult::MAV_MISSION_DENIED,
    MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
];

/// One case; panics when a property fails.
pub(crate) fn run(data: &[u8]) -> Result<()> {
    let mut u = Unstructured::new(data);
    let u = &mut u;
    let n = u.int_in_range(1usize..=40)?;
    let mut items = Vec::with_capacity(n);
    for i in 0..n {
        let lat = 41.0 + f64::from(u.int_in_range(0u16..=1000)?) * 1e-4;
        let lon = 2.0 + f64::from(u.int_in_range(0u16..=1000)?) * 1e-4 + i as f64 * 1e-6;
        items.push(MissionItem::waypoint(
            lat,
            lon,
            f32::from(u.int_in_range(0u8..=120)?),
        ));
    }
    let first: u16 = if u.ratio(1u8, 4)? { u.arbitrary()? } else { 0 };
    let retries = u.int_in_range(1u32..=5)?;
    let timeout = Duration::from_millis(u.int_in_range(10u64..=2000)?);
    let cfg = UploadConfig {
        me: ME,
        target: TARGET,
        retries,
        timeout,
        start_retries: retries,
    };
    let start = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: n as u16,
        target_system: TARGET.0,
        target_component: TARGET.1,
        ..Default::default()
    });
    let t0 = Instant::now();
    let mut now = t0;
    let mut out = Vec::new();
    let Ok(mut up) = MissionUpload::start(cfg, start, &items, first, now, &mut out) else {
        // Refused only when the items do not fit after `first`.
        assert!(usize::from(first) + n - 1 > usize::from(u16::MAX));
        return Ok(());
    };
    let last = first + (n as u16 - 1);
    let mut last_item_sent = false;
    let check_out = |out: &mut Vec<Outbound>, last_item_sent: &mut bool| {
        assert!(out.len() <= 2, "{} messages out in one step", out.len());
        for o in out.drain(..) {
            let Outbound::Message(m) = o else { continue };
            let (seq, x, y) = match &m {
                MavMessage::MISSION_ITEM_INT(i) => (i.seq, Some(i.x), Some(i.y)),
                MavMessage::MISSION_ITEM(i) => (i.seq, None, None),
                _ => continue,
            };
            assert!(
                (first..=last).contains(&seq),
                "item {seq} outside {first}..={last}"
            );
            let want = items[usize::from(seq - first)].to_int(seq, TARGET);
            if let (Some(x), Some(y)) = (x, y) {
                assert_eq!((x, y), (want.x, want.y), "item {seq} content");
            }
            *last_item_sent |= seq == last;
        }
    };
    check_out(&mut out, &mut last_item_sent);
    let mut outcome = None;
    u.arbitrary_loop(Some(0), Some(300), |u| {
        let target = *u.choose(&[ME, ME, ME, 0, 7])?;
        let seq = match u.int_in_range(0u8..=5)? {
            0..=3 => first.wrapping_add(u.int_in_range(0..=n as u16)?),
            4 => first.wrapping_sub(1),
            _ => u.arbitrary()?,
        };
        let step = match u.int_in_range(0u8..=9)? {
            0..=4 => up.handle(
                &MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                    seq,
                    target_system: target,
                    target_component: 190,
                    ..Default::default()
                }),
                now,
                &mut out,
            ),
            5 => up.handle(
                &MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
                    seq,
                    target_system: target,
                    target_component: 190,
                    ..Default::default()
                }),
                now,
                &mut out,
            ),
            6 => up.handle(
                &mission_ack((target, 190), *u.choose(RESULTS)?),
                now,
                &mut out,
            ),
            7 => up.handle(
                &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
                now,
                &mut out,
            ),
            _ => {
                now += Duration::from_millis(u.int_in_range(0u64..=3000)?);
                up.poll(now, &mut out)
            }
        };
        check_out(&mut out, &mut last_item_sent);
        if let Some(r) = step {
            outcome = Some(r);
            return Ok(std::ops::ControlFlow::Break(()));
        }
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    if let Some(Ok(())) = outcome {
        assert!(
            last_item_sent,
            "upload succeeded before its last item was sent"
        );
    }
    if outcome.is_none() {
        // The autopilot falls silent: the upload ends within its retry budget.
        for _ in 0..=retries {
            now = now.max(up.poll_at());
            if let Some(r) = up.poll(now, &mut out) {
                outcome = Some(r);
                break;
            }
            check_out(&mut out, &mut last_item_sent);
        }
        assert!(
            outcome.is_some(),
            "a silent autopilot never ended the upload"
        );
    }
    Ok(())
}

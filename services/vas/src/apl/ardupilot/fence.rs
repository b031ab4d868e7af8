//! The fence on an ArduPilot autopilot (issue 15), as ArduPilot keeps it: the circle and the
//! ceiling as parameters (`FENCE_RADIUS` around home, `FENCE_ALT_MAX`, which parts are on in
//! `FENCE_TYPE`: 1 ceiling, 2 circle, 4 polygon), the breach action as `FENCE_ACTION`, and
//! the polygon as a fence transfer (`mission_type` FENCE) of
//! MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION items (param1: the vertex count). `FENCE_ENABLE`
//! goes on last, once everything else is in place.

use usal_types::Fence;

use crate::mavlink_cm::dialect::{MavCmd, MavFrame};
use crate::mavlink_cm::{MavlinkManager, MissionItem};

use super::AutopilotError;

/// The fence transfer's items for `fence`'s polygon.
pub fn polygon_items(fence: &Fence) -> Vec<MissionItem> {
    let n = fence.polygon.len() as f32;
    fence
        .polygon
        .iter()
        .map(|&(lat, lon)| MissionItem {
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            params: [n, 0.0, 0.0, 0.0],
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            z: 0.0,
            autocontinue: false,
        })
        .collect()
}

/// `FENCE_TYPE` bits for `fence`.
pub fn fence_type(fence: &Fence) -> f32 {
    let mut t = 0;
    if fence.max_height_m.is_some() {
        t |= 1;
    }
    if fence.max_distance_m.is_some() {
        t |= 2;
    }
    if !fence.polygon.is_empty() {
        t |= 4;
    }
    t as f32
}

/// Uploads `fence` (or clears it) on the autopilot behind `mgr`.
///
/// # Errors
/// The first parameter or transfer the autopilot refused or did not answer.
pub async fn upload(mgr: &MavlinkManager, fence: Option<&Fence>) -> Result<(), AutopilotError> {
    let refused = |what: &str, e: String| AutopilotError::Refused(format!("{what}: {e}"));
    // Off while it changes, so a half-written fence is never enforced.
    mgr.param_set("FENCE_ENABLE", 0.0)
        .await
        .map_err(|e| refused("FENCE_ENABLE", e.to_string()))?;
    let Some(f) = fence else {
        mgr.fence_upload(&[])
            .await
            .map_err(|e| refused("clearing the fence", e.to_string()))?;
        return Ok(());
    };
    let mut params = vec![
        ("FENCE_TYPE", fence_type(f)),
        ("FENCE_ACTION", f.action.ardupilot_param()),
    ];
    if let Some(r) = f.max_distance_m {
        params.push(("FENCE_RADIUS", r as f32));
    }
    if let Some(h) = f.max_height_m {
        params.push(("FENCE_ALT_MAX", h as f32));
    }
    for (name, v) in params {
        mgr.param_set(name, v)
            .await
            .map_err(|e| refused(name, e.to_string()))?;
    }
    mgr.fence_upload(&polygon_items(f))
        .await
        .map_err(|e| refused("the fence transfer", e.to_string()))?;
    mgr.param_set("FENCE_ENABLE", 1.0)
        .await
        .map_err(|e| refused("FENCE_ENABLE", e.to_string()))?;
    Ok(())
}

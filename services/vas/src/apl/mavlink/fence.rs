//! The fence on the autopilot, as each family keeps it.
//!
//! ArduPilot: the circle and the ceiling as parameters (`FENCE_RADIUS` around home,
//! `FENCE_ALT_MAX`, which parts are on in `FENCE_TYPE`: 1 ceiling, 2 circle, 4 polygon), the
//! breach action as `FENCE_ACTION`, and the polygon as a fence transfer (`mission_type` FENCE)
//! of MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION items (param1: the vertex count).
//! `FENCE_ENABLE` goes on last, once everything else is in place.
//!
//! PX4: the whole area as the fence transfer (the polygon's vertices and the circle as a
//! MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION item around the fence's home, param1 its radius), the
//! ceiling as `GF_MAX_VER_DIST` and the breach action as `GF_ACTION`. PX4 has no switch: a
//! stored fence is in force, so the parameters go first and the transfer last.

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

/// The fence transfer's items for PX4: the polygon's vertices and the circle.
pub fn px4_items(fence: &Fence) -> Vec<MissionItem> {
    let mut items = polygon_items(fence);
    if let Some(r) = fence.max_distance_m {
        items.push(MissionItem {
            command: MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            params: [r as f32, 0.0, 0.0, 0.0],
            x: (fence.home.0 * 1e7).round() as i32,
            y: (fence.home.1 * 1e7).round() as i32,
            z: 0.0,
            autocontinue: false,
        });
    }
    items
}

/// PX4's `GF_ACTION` for `action` (1 warning, 2 hold, 3 return).
pub fn px4_action(action: usal_types::FenceAction) -> f32 {
    match action {
        usal_types::FenceAction::Report => 1.0,
        usal_types::FenceAction::Hold => 2.0,
        usal_types::FenceAction::ReturnToLaunch => 3.0,
    }
}

/// Uploads `fence` (or clears it) on a PX4 autopilot behind `mgr`.
///
/// # Errors
/// The first parameter or transfer the autopilot refused or did not answer.
pub async fn upload_px4(mgr: &MavlinkManager, fence: Option<&Fence>) -> Result<(), AutopilotError> {
    let refused = |what: &str, e: String| AutopilotError::Refused(format!("{what}: {e}"));
    let Some(f) = fence else {
        return mgr
            .fence_upload(&[])
            .await
            .map_err(|e| refused("clearing the fence", e.to_string()));
    };
    for (name, v) in [
        ("GF_ACTION", px4_action(f.action)),
        ("GF_MAX_VER_DIST", f.max_height_m.unwrap_or(0.0) as f32),
    ] {
        mgr.param_set(name, v)
            .await
            .map_err(|e| refused(name, e.to_string()))?;
    }
    mgr.fence_upload(&px4_items(f))
        .await
        .map_err(|e| refused("the fence transfer", e.to_string()))
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

//! Forwarding between the autopilot and extra endpoints, as mavlink-router does: a ground
//! station (QGroundControl, MAVProxy) beside the VAS sees everything the autopilot sends and
//! reaches the autopilot through the VAS's link, so it can watch and take over the vehicle
//! USAL flies.
//!
//! One task per endpoint owns its connection (reopened with backoff when it fails). Frames
//! keep their own header both ways (system, component and sequence of whoever sent them), so
//! the autopilot answers the other station, not us. What that station changes in the mission
//! shows in the autopilot's MISSION_ACK addressed to it, which the driver reports as
//! [`super::MavEvent::MissionChangedElsewhere`].

use std::sync::Arc;

use mavconn::{Connection, Endpoint, OpenOptions};
use tokio::sync::broadcast;
use tokio::time::sleep;
use tokio_util::sync::CancellationToken;

use super::driver::Inner;
use super::outbound::Outbound;

/// Forwards between the autopilot (through `inner`) and `endpoint` until `cancel` fires.
pub(crate) async fn forwarder(inner: Arc<Inner>, endpoint: Endpoint, cancel: CancellationToken) {
    let backoff = inner.cfg.reconnect_backoff;
    // Subscribed once, before the first opening, so nothing from the autopilot is missed
    // while the endpoint comes up.
    let mut from_autopilot = inner.frames_tx.subscribe();
    loop {
        let opened = tokio::select! {
            _ = cancel.cancelled() => return,
            c = Connection::open(&endpoint, OpenOptions::default()) => c,
        };
        let mut conn = match opened {
            Ok(c) => c,
            Err(e) => {
                tracing::debug!("forward {endpoint}: cannot open: {e}");
                tokio::select! {
                    _ = cancel.cancelled() => return,
                    _ = sleep(backoff) => continue,
                }
            }
        };
        tracing::info!("forwarding MAVLink to and from {endpoint}");
        let error = loop {
            tokio::select! {
                _ = cancel.cancelled() => return,
                frame = from_autopilot.recv() => match frame {
                    Ok(f) => {
                        let (header, msg) = &*f;
                        if let Err(e) = conn.send(*header, msg) {
                            break e.to_string();
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::debug!("forward {endpoint}: {n} autopilot frames dropped");
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                },
                frame = conn.recv() => match frame {
                    Some(Ok(f)) => {
                        if inner.put(Outbound::Raw(f.header, f.msg)).await.is_err() {
                            return;
                        }
                    }
                    Some(Err(e)) => break e.to_string(),
                    None => break "closed".to_owned(),
                },
            }
        };
        tracing::warn!("forward {endpoint} failed: {error}; reopening");
        conn.close().await;
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = sleep(backoff) => {}
        }
    }
}

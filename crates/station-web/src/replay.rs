//! A flight log played back (`usal replay`) is shown as one: every station follows
//! `**/replay/status` and puts a REPLAY banner on its page while it is fresh, so a recorded
//! flight is never taken for a live one, nor the replay's end for a lost link.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use usal_types::ReplayStatus;

use crate::Live;

/// A replay counts as going on this long after its last status (it is published twice a
/// second).
const FRESH: Duration = Duration::from_secs(3);

/// The latest replay status heard, and when.
#[derive(Clone, Default)]
pub struct ReplayWatch {
    latest: Arc<Mutex<Option<(ReplayStatus, Instant)>>>,
}

/// What a station's page shows of a replay.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ReplayView {
    /// The status as last published.
    #[serde(flatten)]
    pub status: ReplayStatus,
    /// Milliseconds since it was heard.
    pub age_ms: u64,
    /// Heard lately: the replay is going on (or just ended).
    pub live: bool,
}

impl ReplayWatch {
    /// Follows `**/replay/status` on `svc` for as long as the station runs (`live`).
    ///
    /// # Errors
    /// The subscription cannot be declared.
    pub fn follow(&self, svc: &marea::Service, live: &Live) -> Result<(), marea::DeclareError> {
        let sub = svc.subscribe_variable::<ReplayStatus>("**/replay/status")?;
        let latest = self.latest.clone();
        live.follow(sub, "replay status", move |s| {
            *marea::sync::lock(&latest) = Some((s.value, Instant::now()));
        });
        Ok(())
    }

    /// The replay heard, if any: `live` while its status is fresh.
    pub fn view(&self, now: Instant) -> Option<ReplayView> {
        let latest = marea::sync::lock(&self.latest).clone();
        latest.map(|(status, at)| {
            let age = now.saturating_duration_since(at);
            ReplayView {
                status,
                age_ms: u64::try_from(age.as_millis()).unwrap_or(u64::MAX),
                live: age <= FRESH,
            }
        })
    }
}

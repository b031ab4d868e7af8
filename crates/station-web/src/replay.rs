//! A flight log played back (`usal replay`) is shown as one: every station follows
//! `**/replay/status` and puts a REPLAY banner on its page while it is fresh, so a recorded
//! flight is never taken for a live one, nor the replay's end for a lost link.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use usal_types::items::replay;
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
    /// The banner both stations show while it is live.
    pub text: String,
}

/// `REPLAY of mission M (flown T): 1:23 of 4:56 at 4x — ...`.
fn banner(s: &ReplayStatus) -> String {
    let mmss = |secs: f64| {
        let secs = secs.max(0.0) as u64;
        format!("{}:{:02}", secs / 60, secs % 60)
    };
    format!(
        "REPLAY of mission {} (flown {}): {} of {} at {}× — {}",
        s.mission,
        s.flown_utc,
        mmss(s.at_s),
        mmss(s.duration_s),
        s.speed,
        if s.ended {
            "ended: the values shown are the recording's last"
        } else {
            "a recorded flight, not a live one; commands go nowhere"
        }
    )
}

impl ReplayWatch {
    /// Follows `**/replay/status` on `svc` for as long as the station runs (`live`).
    ///
    /// # Errors
    /// The subscription cannot be declared.
    pub fn follow(&self, svc: &marea::Service, live: &Live) -> Result<(), marea::DeclareError> {
        let sub = replay::STATUS.subscribe(svc, "**/replay")?;
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
                text: banner(&status),
                status,
                age_ms: u64::try_from(age.as_millis()).unwrap_or(u64::MAX),
                live: age <= FRESH,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_banner_says_which_flight_where_in_it_and_whether_it_ended() {
        let mut s = ReplayStatus {
            log: "logs/x.jsonl.gz".into(),
            mission: "rover-demo".into(),
            flown_utc: "2026-11-28T14:00:00Z".into(),
            at_s: 83.4,
            duration_s: 296.0,
            speed: 4.0,
            ended: false,
        };
        assert_eq!(
            banner(&s),
            "REPLAY of mission rover-demo (flown 2026-11-28T14:00:00Z): 1:23 of 4:56 at 4× — a recorded flight, not a live one; commands go nowhere"
        );
        s.ended = true;
        assert!(banner(&s).ends_with("ended: the values shown are the recording's last"));
    }
}

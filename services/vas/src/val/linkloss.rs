//! Lost ground link: the VAS follows the ground station's heartbeat
//! (`usal_types::StationHeartbeat`, published by `usal run`'s station) and the health of the
//! radio (`<namespace>/link/<radio>/stats`, published by the node carrying the radio, the
//! air-side gateway), and when the ground has been silent for `linkLossTimeoutMs` it applies
//! the configured action: continue the plan, hold, or return to launch. When the link comes
//! back it resumes the state it left, or waits for the operator, as configured. Both the loss
//! and the recovery raise an alarm and a `failsafe` event.
//!
//! Why the VAS and not the FPMa: the action is a flight-state change the VAS owns (the VAL's
//! state machine), it must work with no plan loaded (manual navigation from the FMo loses its
//! sticks just the same), and the VAS is the last USAL process before the autopilot, so it
//! still acts when the FPMa has died with the link.
//!
//! The watch is a pure state machine ([`LinkWatch`]) fed with instants; the VAL's task feeds it
//! the samples and a tick, and carries out its [`Decision`]s.
//!
//! The watch arms at the first heartbeat: a vehicle that never heard a station (a bench test,
//! a VAS driven by a script) has no ground link to lose.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// What to do when the ground link is lost (`linkLossAction`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LinkLossAction {
    /// Keep flying the plan; alarm only.
    #[default]
    Continue,
    /// Stop and hold (rover HOLD, the PARKING state).
    Hold,
    /// Return to launch (falls back to hold where the autopilot refuses).
    ReturnToLaunch,
}

impl LinkLossAction {
    /// The name in the configuration: `continue`, `hold`, `rtl`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Continue => "continue",
            Self::Hold => "hold",
            Self::ReturnToLaunch => "rtl",
        }
    }
}

impl std::str::FromStr for LinkLossAction {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "continue" => Ok(Self::Continue),
            "hold" => Ok(Self::Hold),
            "rtl" => Ok(Self::ReturnToLaunch),
            _ => Err(format!("`{s}`: expected continue, hold or rtl")),
        }
    }
}

/// What to do when the ground link returns (`linkRecovery`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LinkRecovery {
    /// Go back to the state the loss interrupted (if nobody changed it meanwhile).
    Resume,
    /// Stay as the action left it until the operator decides: the default, as the pilot in
    /// command decides when a held vehicle moves again.
    #[default]
    Wait,
}

impl LinkRecovery {
    /// The name in the configuration: `resume`, `wait`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Resume => "resume",
            Self::Wait => "wait",
        }
    }
}

impl std::str::FromStr for LinkRecovery {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "resume" => Ok(Self::Resume),
            "wait" => Ok(Self::Wait),
            _ => Err(format!("`{s}`: expected resume or wait")),
        }
    }
}

/// Settings of the lost-link watch.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkLossConfig {
    /// Pattern of the station heartbeat variable (`stationHeartbeat`).
    pub heartbeat: String,
    /// Name of the radio link whose health is followed (`radioLink`): the VAS subscribes to
    /// `<its namespace>/link/<radioLink>/stats`; `None`: the heartbeat only.
    pub radio_link: Option<String>,
    /// Silence after which the link is lost (`linkLossTimeoutMs`).
    pub timeout: Duration,
    /// What to do then (`linkLossAction`).
    pub action: LinkLossAction,
    /// What to do when it returns (`linkRecovery`).
    pub recovery: LinkRecovery,
}

impl Default for LinkLossConfig {
    fn default() -> Self {
        Self {
            heartbeat: "**/heartbeat".into(),
            radio_link: Some("radio".into()),
            timeout: Duration::from_secs(5),
            action: LinkLossAction::Continue,
            recovery: LinkRecovery::Wait,
        }
    }
}

/// What the watch decided on a tick.
#[derive(Clone, Debug, PartialEq)]
pub enum Decision {
    /// The link is lost; `why` says which signal went silent.
    Lost {
        /// For the alarm.
        why: String,
    },
    /// The link is back after `outage`.
    Restored {
        /// How long the ground was silent (from its last heartbeat, or from when the radio
        /// was declared dead).
        outage: Duration,
    },
}

/// The lost-link state machine.
#[derive(Debug)]
pub struct LinkWatch {
    timeout: Duration,
    last_heartbeat: Option<Instant>,
    /// Per radio link: since when it reports no peer (`None`: it has peers).
    radio_down: HashMap<String, Option<Instant>>,
    lost_since: Option<Instant>,
}

impl LinkWatch {
    /// A watch declaring the link lost after `timeout` of silence.
    pub fn new(timeout: Duration) -> Self {
        Self {
            timeout,
            last_heartbeat: None,
            radio_down: HashMap::new(),
            lost_since: None,
        }
    }

    /// A station heartbeat arrived at `now`.
    pub fn heartbeat(&mut self, now: Instant) {
        self.last_heartbeat = Some(now);
    }

    /// A health sample of radio link `link` at `now`, with `peers` reached over it.
    pub fn radio(&mut self, now: Instant, link: &str, peers: u32) {
        // Bounded by the links of the node(s) we follow; a forger inventing names is capped.
        if self.radio_down.len() >= 16 && !self.radio_down.contains_key(link) {
            return;
        }
        let e = self.radio_down.entry(link.to_owned()).or_default();
        if peers == 0 {
            e.get_or_insert(now);
        } else {
            *e = None;
        }
    }

    /// Whether the link is lost now.
    pub fn is_lost(&self) -> bool {
        self.lost_since.is_some()
    }

    /// Re-evaluates at `now`.
    pub fn poll(&mut self, now: Instant) -> Option<Decision> {
        // Never heard a station: nothing to lose.
        let last = self.last_heartbeat?;
        let silent = now.saturating_duration_since(last);
        let radio_dead = self
            .radio_down
            .iter()
            .filter_map(|(l, since)| since.map(|s| (l, now.saturating_duration_since(s))))
            .find(|(_, d)| *d >= self.timeout);
        match self.lost_since {
            None => {
                if silent >= self.timeout {
                    let mut why = format!("no station heartbeat for {:.1} s", silent.as_secs_f64());
                    if let Some((l, _)) = self.radio_down.iter().find(|(_, s)| s.is_some()) {
                        why += &format!(" (radio link `{l}` reaches no peer)");
                    }
                    // The silence began with the last heartbeat.
                    self.lost_since = Some(last);
                    Some(Decision::Lost { why })
                } else if let Some((l, d)) = radio_dead {
                    let why = format!(
                        "radio link `{l}` has reached no peer for {:.1} s",
                        d.as_secs_f64()
                    );
                    self.lost_since = Some(now);
                    Some(Decision::Lost { why })
                } else {
                    None
                }
            }
            Some(since) => {
                // Back when a heartbeat came after the loss and no radio is down.
                let fresh = last > since && silent < self.timeout;
                let radio_up = self.radio_down.values().all(Option::is_none);
                if fresh && radio_up {
                    self.lost_since = None;
                    Some(Decision::Restored {
                        outage: now.saturating_duration_since(since),
                    })
                } else {
                    None
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silence_loses_the_link_and_a_heartbeat_brings_it_back() {
        let t0 = Instant::now();
        let s = Duration::from_secs;
        let mut w = LinkWatch::new(s(3));
        // Never heard: never lost.
        assert_eq!(w.poll(t0 + s(100)), None);
        w.heartbeat(t0);
        assert_eq!(w.poll(t0 + s(2)), None);
        let Some(Decision::Lost { why }) = w.poll(t0 + s(3)) else {
            panic!("not lost")
        };
        assert!(why.contains("no station heartbeat for 3.0 s"), "{why}");
        assert!(w.is_lost());
        // Lost once, not on every tick.
        assert_eq!(w.poll(t0 + s(4)), None);
        w.heartbeat(t0 + s(10));
        assert_eq!(
            w.poll(t0 + s(10)),
            Some(Decision::Restored { outage: s(10) })
        );
        assert!(!w.is_lost());
    }

    #[test]
    fn a_radio_without_peers_loses_the_link_and_holds_recovery() {
        let t0 = Instant::now();
        let s = Duration::from_secs;
        let mut w = LinkWatch::new(s(3));
        w.heartbeat(t0);
        w.radio(t0, "radio", 0);
        // Heartbeats keep coming (from another path), the radio is down for the timeout.
        w.heartbeat(t0 + s(3));
        let Some(Decision::Lost { why }) = w.poll(t0 + s(3)) else {
            panic!("not lost")
        };
        assert!(why.contains("radio link `radio`"), "{why}");
        // A heartbeat alone does not restore while the radio reaches nobody.
        w.heartbeat(t0 + s(4));
        assert_eq!(w.poll(t0 + s(4)), None);
        w.radio(t0 + s(5), "radio", 1);
        w.heartbeat(t0 + s(5));
        assert!(matches!(w.poll(t0 + s(5)), Some(Decision::Restored { .. })));
    }

    #[test]
    fn actions_parse_by_their_names() {
        for a in [
            LinkLossAction::Continue,
            LinkLossAction::Hold,
            LinkLossAction::ReturnToLaunch,
        ] {
            assert_eq!(a.name().parse::<LinkLossAction>(), Ok(a));
        }
        for r in [LinkRecovery::Resume, LinkRecovery::Wait] {
            assert_eq!(r.name().parse::<LinkRecovery>(), Ok(r));
        }
        assert!("land".parse::<LinkLossAction>().is_err());
    }
}

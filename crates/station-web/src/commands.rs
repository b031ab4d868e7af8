//! The commands a station has sent, as the operator follows them: each is pending until the
//! vehicle answers or the call fails, then shows its outcome and how long it took. The log keeps
//! the newest [`CommandLog::KEPT`], dropping the oldest finished ones first (a pending command is
//! never dropped: its answer is still awaited).

use std::collections::VecDeque;
use std::time::Instant;

use serde::Serialize;

use crate::ms;

/// A command's outcome.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CommandStatus {
    /// Sent, no answer yet.
    Pending,
    /// The vehicle accepted it.
    Ok,
    /// Refused or lost, with the reason.
    Failed,
}

/// One command sent; `extra` is what the station keeps beside it (the FPMo: the plan an upload
/// sent, to match the FPMa's answer).
#[derive(Clone, Debug)]
pub struct Command<X> {
    /// The station's id of the command (what `202 {id}` returned).
    pub id: u64,
    /// The vehicle it was sent to, as the station names it.
    pub vehicle: String,
    /// What was asked, for display.
    pub what: String,
    /// Pending, done or failed.
    pub status: CommandStatus,
    /// Progress while pending; then the answer or the reason of the failure.
    pub detail: String,
    /// When it was sent.
    pub started: Instant,
    /// When it was answered.
    pub finished: Option<Instant>,
    /// The station's own data.
    pub extra: X,
}

impl<X> Command<X> {
    /// Records the outcome of a pending command (an answered one keeps its first outcome).
    pub fn finish(&mut self, outcome: Result<String, String>, now: Instant) {
        if self.status != CommandStatus::Pending {
            return;
        }
        (self.status, self.detail) = match outcome {
            Ok(d) => (CommandStatus::Ok, d),
            Err(e) => (CommandStatus::Failed, e),
        };
        self.finished = Some(now);
    }
}

/// The commands sent, oldest first.
#[derive(Clone, Debug)]
pub struct CommandLog<X = ()> {
    entries: VecDeque<Command<X>>,
}

impl<X> Default for CommandLog<X> {
    fn default() -> Self {
        Self {
            entries: VecDeque::new(),
        }
    }
}

/// One command as the page gets it.
#[derive(Clone, Debug, Serialize)]
pub struct CommandView {
    id: u64,
    vehicle: String,
    what: String,
    status: CommandStatus,
    detail: String,
    age_ms: u64,
    took_ms: Option<u64>,
}

impl<X> CommandLog<X> {
    /// Commands kept for display.
    pub const KEPT: usize = 30;

    /// Registers command `id` sent to `vehicle` at `now`, pending.
    pub fn start(&mut self, id: u64, vehicle: &str, what: String, now: Instant, extra: X) {
        self.entries.push_back(Command {
            id,
            vehicle: vehicle.to_owned(),
            what,
            status: CommandStatus::Pending,
            detail: String::new(),
            started: now,
            finished: None,
            extra,
        });
        while self.entries.len() > Self::KEPT {
            match self
                .entries
                .iter()
                .position(|c| c.status != CommandStatus::Pending)
            {
                Some(i) => {
                    self.entries.remove(i);
                }
                None => break,
            }
        }
    }

    /// Command `id`, if still kept.
    pub fn get(&self, id: u64) -> Option<&Command<X>> {
        self.entries.iter().find(|c| c.id == id)
    }

    /// Command `id`, if still kept.
    pub fn get_mut(&mut self, id: u64) -> Option<&mut Command<X>> {
        self.entries.iter_mut().find(|c| c.id == id)
    }

    /// Shows `detail` on command `id` while it is pending (how far it got); an answered one
    /// keeps its outcome, whichever came first (progress can trail the answer).
    pub fn progress(&mut self, id: u64, detail: String) {
        if let Some(c) = self
            .get_mut(id)
            .filter(|c| c.status == CommandStatus::Pending)
        {
            c.detail = detail;
        }
    }

    /// Records the outcome of command `id` (see [`Command::finish`]).
    pub fn finish(&mut self, id: u64, outcome: Result<String, String>, now: Instant) {
        if let Some(c) = self.get_mut(id) {
            c.finish(outcome, now);
        }
    }

    /// The first pending command sent to `vehicle` whose `extra` matches.
    pub fn pending_mut(
        &mut self,
        vehicle: &str,
        matches: impl Fn(&X) -> bool,
    ) -> Option<&mut Command<X>> {
        self.entries.iter_mut().find(|c| {
            c.vehicle == vehicle && c.status == CommandStatus::Pending && matches(&c.extra)
        })
    }

    /// How many are kept.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// None kept.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The page's view at `now`, newest first, each vehicle named by `label`.
    pub fn view(&self, now: Instant, label: impl Fn(&str) -> String) -> Vec<CommandView> {
        self.entries
            .iter()
            .rev()
            .map(|c| CommandView {
                id: c.id,
                vehicle: label(&c.vehicle),
                what: c.what.clone(),
                status: c.status.clone(),
                detail: c.detail.clone(),
                age_ms: ms(now.saturating_duration_since(c.started)),
                took_ms: c
                    .finished
                    .map(|f| ms(f.saturating_duration_since(c.started))),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Progress shows on a pending command only: one answered keeps its outcome even when the
    /// progress of its transfer comes after the answer.
    #[test]
    fn progress_never_overwrites_an_answer() {
        let t = Instant::now();
        let mut log = CommandLog::<()>::default();
        log.start(1, "r", "upload".into(), t, ());
        log.progress(1, "sending 10/20 bytes".into());
        assert_eq!(log.get(1).unwrap().detail, "sending 10/20 bytes");
        log.finish(1, Ok("loaded as version 1".into()), t);
        log.progress(1, "sending 20/20 bytes".into());
        log.progress(7, "no such command".into());
        assert_eq!(log.get(1).unwrap().detail, "loaded as version 1");
    }

    #[test]
    fn pending_then_answered_once_and_shown_newest_first() {
        let t = Instant::now();
        let mut log = CommandLog::<()>::default();
        log.start(1, "r", "a".into(), t, ());
        log.start(2, "r", "b".into(), t, ());
        assert_eq!(log.get(1).map(|c| &c.status), Some(&CommandStatus::Pending));
        log.finish(1, Err("lost".into()), t + Duration::from_millis(40));
        log.finish(1, Ok("late".into()), t + Duration::from_millis(90));
        let c = log.get(1).unwrap();
        assert_eq!(
            (&c.status, c.detail.as_str()),
            (&CommandStatus::Failed, "lost")
        );
        let v =
            serde_json::to_value(log.view(t + Duration::from_millis(100), |v| format!("<{v}>")))
                .unwrap();
        assert_eq!(v[0]["id"], 2);
        assert_eq!(v[0]["status"], "pending");
        assert_eq!(v[0]["took_ms"], serde_json::Value::Null);
        assert_eq!(v[1]["vehicle"], "<r>");
        assert_eq!(v[1]["status"], "failed");
        assert_eq!(v[1]["age_ms"], 100);
        assert_eq!(v[1]["took_ms"], 40);
    }

    #[test]
    fn the_oldest_finished_go_first_and_pending_ones_stay() {
        let t = Instant::now();
        let mut log = CommandLog::<u64>::default();
        log.start(0, "r", "waiting".into(), t, 0);
        for id in 1..100 {
            log.start(id, "r", "x".into(), t, id);
            log.finish(id, Ok(String::new()), t);
        }
        assert_eq!(log.len(), CommandLog::<u64>::KEPT);
        assert!(log.get(0).is_some(), "a pending command is kept");
        assert!(log.get(70).is_none() && log.get(71).is_some());
        assert_eq!(log.pending_mut("r", |x| *x == 0).map(|c| c.id), Some(0));
        assert!(log.pending_mut("r", |x| *x == 99).is_none(), "answered");
        assert!(
            log.pending_mut("s", |x| *x == 0).is_none(),
            "another vehicle"
        );
    }
}

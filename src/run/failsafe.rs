//! The station's side of the failsafes: it publishes the heartbeat by which the VAS knows its
//! ground station is there, rehearses a plan the FPMa must refuse (`refusedPlan`, e.g. one
//! crossing the geofence), and collects every failsafe that fired (the VAS's `failsafe` events,
//! the FPMa's emergency rules) for the run's lines and summary.

use std::path::Path;
use std::time::Duration;

use flightplan::api::items as fpma;
use serde::Serialize;
use usal_types::{Failsafe, FailsafeKind, StationHeartbeat};

/// Period of the station's heartbeat.
const HEARTBEAT: Duration = Duration::from_millis(250);

/// One failsafe that fired, as the summary lists it.
#[derive(Clone, Debug, Serialize)]
pub struct FailsafeNote {
    /// `link-lost`, `link-restored`, `fence`, `battery`.
    pub kind: String,
    /// What was done.
    pub action: String,
    /// In words.
    pub text: String,
    /// Seconds since the station started.
    pub at_s: f64,
}

impl FailsafeNote {
    /// From the VAS's `failsafe` event.
    pub fn from_event(f: &Failsafe, at_s: f64) -> Self {
        Self {
            kind: f.kind.name().to_owned(),
            action: f.action.clone(),
            text: f.text.clone(),
            at_s,
        }
    }

    /// The FPMa's emergency rule `rule` fired (the plan's battery rule, or another).
    pub fn from_rule(rule: &str, at_s: f64) -> Self {
        let kind = if rule.contains("battery") {
            FailsafeKind::Battery.name()
        } else {
            "emergency"
        };
        Self {
            kind: kind.to_owned(),
            action: format!("rule {rule}"),
            text: format!("the plan's emergency rule `{rule}` fired"),
            at_s,
        }
    }

    /// Whether it changes the plan's route by design (an emergency rule jumps to another
    /// stage or leg), so a completed plan off its nominal sequence is as planned.
    pub fn changes_route(&self) -> bool {
        self.action.starts_with("rule ")
    }

    /// The line shown when it fires.
    pub fn line(&self) -> String {
        format!("failsafe {} ({}): {}", self.kind, self.action, self.text)
    }
}

/// The summary's lines for `notes` (empty when none fired).
pub fn summary_text(notes: &[FailsafeNote]) -> String {
    if notes.is_empty() {
        return String::new();
    }
    let mut kinds: Vec<&str> = Vec::new();
    for n in notes {
        if !kinds.contains(&n.kind.as_str()) {
            kinds.push(&n.kind);
        }
    }
    let mut s = format!("  failsafes fired: {}\n", kinds.join(", "));
    for n in notes {
        s += &format!(
            "    {:>6.1} s  {} ({}): {}\n",
            n.at_s, n.kind, n.action, n.text
        );
    }
    s
}

/// Publishes `<station>/heartbeat` until the node shuts down.
///
/// # Errors
/// The variable cannot be declared.
pub fn start_heartbeat(svc: &marea::Service, station: &str) -> anyhow::Result<()> {
    let beat = usal_types::items::station::HEARTBEAT.publish(svc)?;
    let station = station.to_owned();
    let cx = svc.clone();
    svc.spawn(async move {
        let mut tick = tokio::time::interval(HEARTBEAT);
        for seq in 0.. {
            tokio::select! {
                () = cx.cancelled() => return,
                _ = tick.tick() => {
                    let _ = beat.set(&StationHeartbeat { station: station.clone(), seq });
                }
            }
        }
    });
    Ok(())
}

/// Offers the plan in `path` to the `load_plan` of the FPMa at `fpma_at` (`rover1/fpma`), which
/// must refuse it.
///
/// # Errors
/// The file cannot be read, the FPMa cannot be called, or it accepted the plan.
pub async fn rehearse_refusal(
    svc: &marea::Service,
    fpma_at: &str,
    path: &Path,
    at_s: f64,
    timeout: Duration,
) -> Result<FailsafeNote, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("reading refusedPlan {}: {e}", path.display()))?;
    let load = fpma::LOAD_PLAN
        .function(svc, fpma_at)
        .map_err(|e| e.to_string())?;
    if !load.wait_provider(timeout).await {
        let name = fpma::LOAD_PLAN.at(fpma_at);
        return Err(format!("no {name} to offer refusedPlan to"));
    }
    let name = path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    match load.call(&text, timeout).await {
        Ok(loaded) => Err(format!(
            "the FPMa accepted refusedPlan {name} (as version {}), which it must refuse",
            loaded.version
        )),
        Err(marea::CallError::Remote { message, .. }) => {
            let kind = if message.contains("fence") {
                FailsafeKind::Fence.name()
            } else {
                "plan-check"
            };
            Ok(FailsafeNote {
                kind: kind.to_owned(),
                action: "refused".to_owned(),
                text: format!("plan {name} refused by the FPMa: {message}"),
                at_s,
            })
        }
        Err(e) => Err(format!("offering refusedPlan {name}: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_summary_names_each_kind_once_then_lists_every_failsafe() {
        let lost = Failsafe {
            kind: FailsafeKind::LinkLost,
            action: "hold".into(),
            text: "ground link lost".into(),
        };
        let notes = vec![
            FailsafeNote::from_event(&lost, 40.0),
            FailsafeNote::from_rule("low-battery", 80.0),
            FailsafeNote::from_event(&lost, 90.0),
        ];
        let text = summary_text(&notes);
        assert!(
            text.starts_with("  failsafes fired: link-lost, battery\n"),
            "{text}"
        );
        assert!(
            text.contains("80.0 s  battery (rule low-battery)"),
            "{text}"
        );
        assert_eq!(text.lines().count(), 4, "{text}");
        assert!(summary_text(&[]).is_empty());
        assert!(notes[1].changes_route() && !notes[0].changes_route());
    }
}

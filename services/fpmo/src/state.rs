//! The FPMo's picture of the vehicles it follows, with no I/O: each one's progress, variables,
//! position and track, the plan its FPMa says it flies and when to ask for it again, its plan
//! events, and the commands sent to it. The middleware tasks feed it; the page reads
//! [`State::snapshot`] and [`State::plan_view`].

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use flightplan::api::{
    CommandAck, PlanEvent, PlanEventKind, PlanGeometry, PlanRejected, PlanState, Progress,
    Readiness, VarValue,
};
use marea::Function;
use station_web::{ms, CommandLog};
use usal_types::{AllowedChanges, FlightState, Position};

use crate::plan::{distance_m, CheckedPlan, PlanView};

/// Track points kept per vehicle.
const MAX_TRACK: usize = 2000;
/// A new track point when the vehicle moved at least this far.
const TRACK_STEP_M: f64 = 0.5;
/// A drawing older than the progress for this long is asked for (`plan_geometry`): the `plan`
/// variable was lost (a lossy radio) or is still on its way (it usually is, briefly).
pub(crate) const GEOMETRY_LAG: Duration = Duration::from_secs(3);
/// Least time between two `plan_geometry` calls to one FPMa.
const GEOMETRY_RETRY: Duration = Duration::from_secs(5);

/// A value with its arrival time.
#[derive(Clone, Debug)]
pub(crate) struct Stamped<T> {
    pub(crate) value: T,
    pub(crate) at: Instant,
}

impl<T> Stamped<T> {
    /// `value`, arrived now.
    pub(crate) fn now(value: T) -> Self {
        Self {
            value,
            at: Instant::now(),
        }
    }
}

/// What the station knows of one vehicle.
#[derive(Default)]
pub(crate) struct Vehicle {
    pub(crate) progress: Option<Stamped<Progress>>,
    /// The executive's variables and loop passes (the FPMa's `state`).
    pub(crate) plan_state: Option<Stamped<PlanState>>,
    position: Option<Stamped<Position>>,
    track: VecDeque<(f64, f64)>,
    /// The FPMa's plan as it last said (version 0: none loaded).
    geometry: Option<PlanGeometry>,
    /// Grows with every new drawing, so the page knows to fetch it.
    plan_rev: u64,
    /// Since when the drawing lags the progress' version.
    geometry_lags_since: Option<Instant>,
    /// When `plan_geometry` was last called.
    geometry_asked: Option<Instant>,
    events: VecDeque<(Instant, String)>,
    /// A function of its FPMa, whose provider's presence says whether the FPMa is reachable.
    pub(crate) probe: Option<Arc<Function<(), CommandAck>>>,
    /// The VAS's flight state (`flight_state`).
    pub(crate) flight_state: Option<Stamped<FlightState>>,
    /// What the VAS accepts from its state (`allowed_changes`, its own transition table).
    pub(crate) allowed: Option<Stamped<AllowedChanges>>,
    /// Whether the FPMa's plan waits for the operator's start (`ready`).
    pub(crate) readiness: Option<Stamped<Readiness>>,
    /// The vehicle's battery (the VAS's `battery`).
    pub(crate) battery: Option<Stamped<usal_types::Battery>>,
    /// The autopilot's home (the VAS's `home`).
    pub(crate) home: Option<usal_types::Home>,
    /// The fence in force on the vehicle (the VAS's `fence`; empty: none).
    pub(crate) fence: Option<usal_types::Fence>,
}

/// A state change the page offers as a button.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Offer {
    /// The state asked for.
    pub to: FlightState,
    /// The button's text: the state's name, or `Start` for WAYPOINT_NAVIGATION when the
    /// FPMa's plan is ready.
    pub label: String,
}

impl Vehicle {
    /// Exactly the state changes the VAS says it accepts from the state it is in (none while
    /// its `allowed_changes` describes another state than its `flight_state`: one of the two
    /// is still on its way), WAYPOINT_NAVIGATION labelled `Start` when a plan is ready.
    pub(crate) fn offers(&self) -> Vec<Offer> {
        let (Some(state), Some(allowed)) = (&self.flight_state, &self.allowed) else {
            return Vec::new();
        };
        if allowed.value.from != Some(state.value) {
            return Vec::new();
        }
        let ready = self.readiness.as_ref().is_some_and(|r| r.value.ready);
        allowed
            .value
            .states
            .iter()
            .map(|&to| Offer {
                to,
                label: if to == FlightState::WaypointNavigation && ready {
                    "Start".into()
                } else {
                    to.name().into()
                },
            })
            .collect()
    }

    /// The commands (ARM, DISARM) the VAS accepts from the state it is in; DIRECTED, which
    /// needs a bearing, altitude and speed, is the FMo's.
    pub(crate) fn command_offers(&self) -> Vec<String> {
        let (Some(state), Some(allowed)) = (&self.flight_state, &self.allowed) else {
            return Vec::new();
        };
        if allowed.value.from != Some(state.value) {
            return Vec::new();
        }
        allowed
            .value
            .commands
            .iter()
            .filter(|c| matches!(c.as_str(), "ARM" | "DISARM"))
            .cloned()
            .collect()
    }
}

/// The station's state.
pub struct State {
    pub(crate) vehicles: BTreeMap<String, Vehicle>,
    pub(crate) selected: Option<String>,
    /// The commands sent; an upload keeps the plan it sent until the FPMa loads or refuses it
    /// (`PlanLoaded { name }` / `plan_rejected { file }`).
    pub(crate) commands: CommandLog<Option<CheckedPlan>>,
    /// The next command's id (also names an upload's staging directory).
    pub(crate) next_id: u64,
    stale_after: Duration,
}

/// The `fpma` prefix of a vehicle label (`rover1` → `rover1/fpma`, `` → `fpma`).
pub fn fpma_prefix(label: &str) -> String {
    if label.is_empty() {
        "fpma".into()
    } else {
        format!("{label}/fpma")
    }
}

/// The vehicle label of an item name: what precedes `/<service>/<item>`.
pub(crate) fn label_of(name: &str, service: &str) -> Option<String> {
    let cut = name.rfind(&format!("{service}/"))?;
    Some(name[..cut].trim_end_matches('/').to_owned())
}

impl State {
    /// No vehicle heard yet; values older than `stale_after` are shown as stale.
    pub(crate) fn new(stale_after: Duration) -> Self {
        Self {
            vehicles: BTreeMap::new(),
            selected: None,
            commands: CommandLog::default(),
            next_id: 1,
            stale_after,
        }
    }

    pub(crate) fn vehicle(&mut self, label: &str) -> &mut Vehicle {
        if self.selected.is_none() {
            self.selected = Some(label.to_owned());
        }
        self.vehicles.entry(label.to_owned()).or_default()
    }

    /// Registers a command sent to `vehicle` (with the plan, for an upload); returns its id.
    pub(crate) fn start(
        &mut self,
        vehicle: &str,
        what: String,
        upload: Option<CheckedPlan>,
    ) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.commands
            .start(id, vehicle, what, Instant::now(), upload);
        id
    }

    /// Records the outcome of command `id`, if still pending.
    pub(crate) fn finish(&mut self, id: u64, outcome: Result<String, String>) {
        self.commands.finish(id, outcome, Instant::now());
    }

    /// The FPMa's plan geometry (variable `plan` or an answer of `plan_geometry`).
    pub(crate) fn geometry(&mut self, label: &str, g: PlanGeometry) {
        let v = self.vehicle(label);
        if v.geometry.as_ref() != Some(&g) {
            v.geometry = Some(g);
            v.plan_rev += 1;
        }
    }

    /// Vehicles whose drawing has lagged their progress long enough to ask for it again,
    /// among those whose FPMa is `reachable`.
    pub(crate) fn geometry_lagging(
        &mut self,
        now: Instant,
        reachable: impl Fn(&Vehicle) -> bool,
    ) -> Vec<String> {
        let mut ask = Vec::new();
        for (label, v) in &mut self.vehicles {
            let wanted = v.progress.as_ref().map_or(0, |p| p.value.version);
            let drawn = v.geometry.as_ref().map_or(0, |g| g.version);
            if wanted == drawn || !reachable(v) {
                v.geometry_lags_since = None;
                continue;
            }
            let since = *v.geometry_lags_since.get_or_insert(now);
            let asked_long_ago = v
                .geometry_asked
                .is_none_or(|t| now.saturating_duration_since(t) >= GEOMETRY_RETRY);
            if now.saturating_duration_since(since) >= GEOMETRY_LAG && asked_long_ago {
                v.geometry_asked = Some(now);
                ask.push(label.clone());
            }
        }
        ask
    }

    pub(crate) fn plan_event(&mut self, label: &str, ev: PlanEvent) {
        let text = match &ev.kind {
            PlanEventKind::PlanLoaded { name } => {
                // The upload that sent this plan is confirmed (the map follows the FPMa's `plan`).
                let hit = self.commands.pending_mut(label, |upload| {
                    upload.as_ref().is_some_and(|p| p.plan.name == *name)
                });
                if let Some(c) = hit {
                    c.finish(
                        Ok(format!("loaded as version {}", ev.version)),
                        Instant::now(),
                    );
                    c.extra = None;
                }
                format!("plan `{name}` loaded (version {})", ev.version)
            }
            k => k.to_string(),
        };
        let v = self.vehicle(label);
        v.events
            .push_back((Instant::now(), format!("v{}: {text}", ev.version)));
        while v.events.len() > 30 {
            v.events.pop_front();
        }
    }

    pub(crate) fn plan_rejected(&mut self, label: &str, r: PlanRejected) {
        let hit = self.commands.pending_mut(label, |upload| {
            upload.as_ref().is_some_and(|p| p.file == r.file)
        });
        if let Some(c) = hit {
            c.finish(Err(r.reason.clone()), Instant::now());
            c.extra = None;
        }
        let v = self.vehicle(label);
        v.events
            .push_back((Instant::now(), format!("rejected {}: {}", r.file, r.reason)));
    }

    pub(crate) fn position(&mut self, label: &str, p: Position) {
        let v = self.vehicle(label);
        let pt = (p.lat, p.lon);
        if v.track
            .back()
            .is_none_or(|&last| distance_m(last, pt) >= TRACK_STEP_M)
        {
            v.track.push_back(pt);
            while v.track.len() > MAX_TRACK {
                v.track.pop_front();
            }
        }
        v.position = Some(Stamped::now(p));
    }

    /// The page's view.
    pub fn snapshot(&self) -> serde_json::Value {
        let now = Instant::now();
        let vehicles: Vec<_> = self
            .vehicles
            .iter()
            .map(|(label, v)| {
                let reachable = v.probe.as_ref().map(|f| f.has_provider());
                let fpma_ok = reachable.unwrap_or(false);
                let pos_age = v
                    .position
                    .as_ref()
                    .map(|p| now.saturating_duration_since(p.at));
                serde_json::json!({
                    "label": label,
                    "fpma": fpma_prefix(label),
                    "fpma_reachable": fpma_ok,
                    "progress": v.progress.as_ref().map(|p| serde_json::json!({
                        "value": p.value,
                        "age_ms": ms(now.saturating_duration_since(p.at)),
                        "stale": !fpma_ok,
                    })),
                    "position": v.position.as_ref().map(|p| serde_json::json!({
                        "value": p.value,
                        "age_ms": pos_age.map(ms),
                        "stale": pos_age.is_none_or(|a| a > self.stale_after),
                    })),
                    "track": v.track,
                    "home": v.home,
                    "battery": v.battery.as_ref().map(|b| serde_json::json!({
                        "value": b.value,
                        "age_ms": ms(now.saturating_duration_since(b.at)),
                        "stale": now.saturating_duration_since(b.at) > self.stale_after,
                    })),
                    "fence": v.fence.as_ref().filter(|f| !f.is_empty()),
                    "vars": v.plan_state.as_ref().map(|s| s.value.vars.iter().map(|(name, val)| {
                        let value = match val {
                            VarValue::Bool(b) => serde_json::json!(b),
                            VarValue::Number(n) => serde_json::json!(n),
                        };
                        serde_json::json!({"name": name, "value": value})
                    }).collect::<Vec<_>>()).unwrap_or_default(),
                    "loops": v.plan_state.as_ref().map(|s| s.value.loops.clone()).unwrap_or_default(),
                    "flight_state": v.flight_state.as_ref().map(|f| serde_json::json!({
                        "value": f.value,
                        "age_ms": ms(now.saturating_duration_since(f.at)),
                    })),
                    "armed": v.allowed.as_ref().map(|a| a.value.armed),
                    "offers": v.offers(),
                    "command_offers": v.command_offers(),
                    "ready": v.readiness.as_ref().map(|r| serde_json::json!({
                        "ready": r.value.ready,
                        "text": r.value.text,
                        "stale": !fpma_ok,
                    })),
                    "plan_rev": v.plan_rev,
                    "plan_name": v.geometry.as_ref().filter(|g| g.version > 0).map(|g| g.name.clone()),
                    "plan_version": v.geometry.as_ref().map(|g| g.version),
                    "events": v.events.iter().rev().take(12).map(|(t, e)| serde_json::json!({
                        "age_ms": ms(now.saturating_duration_since(*t)), "text": e,
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        let commands = self.commands.view(now, str::to_owned);
        serde_json::json!({
            "selected": self.selected,
            "stale_after_ms": ms(self.stale_after),
            "vehicles": vehicles,
            "commands": commands,
        })
    }

    /// The plan of `label` for the map and the legs table, as its FPMa flies it.
    pub fn plan_view(&self, label: &str) -> Option<PlanView> {
        let v = self.vehicles.get(label)?;
        let g = v.geometry.as_ref().filter(|g| g.version > 0)?;
        Some(PlanView::of(g, v.plan_rev))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_offers_are_the_vas_answer_for_the_state_it_is_in_with_start_for_a_ready_plan() {
        use FlightState::*;
        let mut v = Vehicle::default();
        assert!(v.offers().is_empty());
        v.flight_state = Some(Stamped::now(Parking));
        v.allowed = Some(Stamped::now(AllowedChanges {
            from: Some(Parking),
            states: vec![Directed, WaypointNavigation, ReturnToLaunch],
            ..AllowedChanges::default()
        }));
        let names =
            |v: &Vehicle| -> Vec<String> { v.offers().into_iter().map(|o| o.label).collect() };
        assert_eq!(
            names(&v),
            ["DIRECTED", "WAYPOINT_NAVIGATION", "RETURN_TO_LAUNCH"]
        );
        v.readiness = Some(Stamped::now(Readiness {
            ready: true,
            ..Readiness::default()
        }));
        assert_eq!(names(&v), ["DIRECTED", "Start", "RETURN_TO_LAUNCH"]);
        assert_eq!(v.offers()[1].to, WaypointNavigation);
        v.allowed.as_mut().unwrap().value.commands = vec!["ARM".into(), "DIRECTED".into()];
        assert_eq!(v.command_offers(), ["ARM"]);
        // The state moved on and the VAS's answer for it is still on its way: offer nothing.
        v.flight_state = Some(Stamped::now(WaypointNavigation));
        assert!(v.offers().is_empty());
        assert!(v.command_offers().is_empty());
    }

    #[test]
    fn labels_of_item_names() {
        assert_eq!(
            label_of("rover1/fpma/progress", "fpma").as_deref(),
            Some("rover1")
        );
        assert_eq!(label_of("a/b/vas/position", "vas").as_deref(), Some("a/b"));
        assert_eq!(label_of("fpma/progress", "fpma").as_deref(), Some(""));
        assert_eq!(fpma_prefix(""), "fpma");
        assert_eq!(fpma_prefix("rover1"), "rover1/fpma");
    }

    #[test]
    fn a_drawing_lagging_the_progress_is_asked_for_after_a_while_and_not_too_often() {
        let mut st = State::new(Duration::from_secs(2));
        let t = Instant::now();
        let progress = |version| Progress {
            version,
            ..Progress::default()
        };
        let geometry = |version| PlanGeometry {
            version,
            ..PlanGeometry::default()
        };
        st.vehicle("r").progress = Some(Stamped {
            value: progress(2),
            at: t,
        });
        st.geometry("r", geometry(2));
        assert_eq!(st.vehicles["r"].plan_rev, 1);
        st.geometry("r", geometry(2));
        assert_eq!(
            st.vehicles["r"].plan_rev, 1,
            "the same drawing is not redrawn"
        );
        assert!(st.geometry_lagging(t, |_| true).is_empty(), "up to date");

        // Progress says version 3; the drawing is still 2 (the `plan` value lost or late).
        st.vehicle("r").progress = Some(Stamped {
            value: progress(3),
            at: t,
        });
        assert!(st.geometry_lagging(t, |_| true).is_empty(), "give it time");
        assert!(
            st.geometry_lagging(t + GEOMETRY_LAG, |_| false).is_empty(),
            "an unreachable FPMa is not asked"
        );
        assert!(
            st.geometry_lagging(t + GEOMETRY_LAG, |_| true).is_empty(),
            "lag restarts"
        );
        let later = t + GEOMETRY_LAG * 2;
        assert_eq!(st.geometry_lagging(later, |_| true), ["r"]);
        assert!(st
            .geometry_lagging(later + Duration::from_secs(1), |_| true)
            .is_empty());
        assert_eq!(st.geometry_lagging(later + GEOMETRY_RETRY, |_| true), ["r"]);
        st.geometry("r", geometry(3));
        assert!(st
            .geometry_lagging(later + GEOMETRY_RETRY * 2, |_| true)
            .is_empty());
        assert_eq!(st.plan_view("r").map(|p| p.rev), Some(2));
    }
}

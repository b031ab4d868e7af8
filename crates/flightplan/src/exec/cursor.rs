//! How the executive's cursor walks the plan: the stack of frames (stage, loop pass, branch),
//! the active leg and its waypoints, holds and their fix crossings, loops and alternatives
//! decided on the variables, emergency rules, events and progress.

use super::nominal::SIM_LIMIT;
use super::tree::{child_list, list_of};
use super::types::*;
use super::Executive;
use crate::expand::*;
use crate::expr::Value;
use crate::geo;
use crate::model::*;
use std::sync::Arc;

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub(super) struct Frame {
    pub(super) index: usize,
    pub(super) kind: FrameKind,
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub(super) enum FrameKind {
    Stage(Stage),
    Loop {
        iteration: u32,
        produced: bool,
        waits: bool,
    },
    Branch(usize),
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub(super) struct HoldState {
    pub(super) hold: Hold,
    pub(super) entered: bool,
    pub(super) circuits: u32,
    pub(super) exit: bool,
    pub(super) waits: bool,
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub(super) struct Active {
    pub(super) id: String,
    pub(super) wps: Vec<Waypoint>,
    pub(super) next: usize,
    pub(super) hold: Option<HoldState>,
    /// A hold-here or re-task that returns to the suspended leg when done.
    pub(super) interrupt: bool,
}

impl Executive {
    pub(super) fn apply(&mut self, action: &EmergencyAction) -> Result<(), CommandError> {
        match action {
            EmergencyAction::GotoStage { stage } => self.goto_stage(*stage),
            EmergencyAction::GotoLeg { leg } => self.goto_leg(leg),
            EmergencyAction::Hold => self.hold_here(&HoldHere::default()),
            EmergencyAction::Land => {
                if !self.plan.approach.is_empty() && self.stage() < Some(Stage::Approach) {
                    self.goto_stage(Stage::Approach)
                } else if !self.plan.landing.is_empty() {
                    self.goto_stage(Stage::Landing)
                } else {
                    self.hold_here(&HoldHere::default())
                }
            }
        }
    }

    pub(super) fn check_rules(&mut self) {
        let mut fire = None;
        for i in 0..self.plan.emergencies.len() {
            let now = self.plan.emergencies[i].on.holds(&|n| self.var(n));
            let was = self.rule_state.get(i).copied().unwrap_or(false);
            if let Some(s) = self.rule_state.get_mut(i) {
                *s = now;
            }
            if now && !was && fire.is_none() {
                fire = Some(i);
            }
        }
        if let Some(i) = fire {
            let rule = self.plan.emergencies[i].clone();
            self.emit(EventKind::EmergencyFired { rule: rule.name });
            // A reaction that cannot apply (e.g. a hold with no position yet) leaves the plan as
            // it is; the event still tells stations the rule fired.
            let _ = self.apply(&rule.action);
        }
    }

    pub(super) fn var(&self, name: &str) -> Option<Value> {
        if name == "iteration" {
            let it = self.frames.iter().rev().find_map(|f| match f.kind {
                FrameKind::Loop { iteration, .. } => Some(iteration),
                _ => None,
            });
            return Some(Value::Number(f64::from(it.unwrap_or(0))));
        }
        self.vars.get(name).copied()
    }

    pub(super) fn holds(&self, c: &crate::expr::Condition) -> bool {
        c.holds(&|n| self.var(n))
    }

    pub(super) fn emit(&mut self, kind: EventKind) {
        if !self.simulating {
            self.events.push(Event {
                version: self.version,
                kind,
            });
        }
    }

    pub(super) fn emit_progress(&mut self) {
        let (flown, remaining) = self.distances();
        let fraction = if self.completed || flown + remaining <= 0.0 {
            if self.completed {
                1.0
            } else {
                0.0
            }
        } else {
            flown / (flown + remaining)
        };
        self.emit(EventKind::Progress {
            fraction,
            flown_m: flown,
            remaining_m: remaining,
        });
    }

    pub(super) fn sim_copy(&self) -> Executive {
        let mut sim = Executive {
            events: Vec::new(),
            ..self.clone()
        };
        sim.simulating = true;
        sim
    }

    /// Reaches up to `n` heads; returns how many there were.
    pub(super) fn skip_heads(&mut self, n: usize) -> usize {
        let mut k = 0;
        while k < n && self.head().is_some() {
            self.reach_head();
            k += 1;
        }
        k
    }

    pub(super) fn head(&self) -> Option<&Waypoint> {
        self.active.as_ref().and_then(|a| a.wps.get(a.next))
    }

    pub(super) fn ctx(&self) -> Ctx<'_> {
        Ctx {
            vehicle: &self.vehicle,
            prev: self.last,
            plan_speed: self.plan.default_speed,
        }
    }

    pub(super) fn finish(&mut self) {
        if !self.completed {
            self.completed = true;
            self.frames.clear();
            self.emit(EventKind::PlanCompleted);
        }
    }

    pub(super) fn interrupt_with(&mut self, act: Active) {
        self.emit(EventKind::LegStarted {
            leg: act.id.clone(),
        });
        let old = self.active.take();
        match old {
            Some(o) if o.interrupt => {
                self.emit(EventKind::LegCompleted {
                    leg: o.id,
                    skipped: true,
                });
            }
            Some(o) => self.suspended = Some(o),
            None => {}
        }
        if self.completed {
            // A hold commanded after the end: fly it, then end again.
            self.completed = false;
        }
        self.active = Some(act);
    }

    pub(super) fn jump(&mut self, frames: Vec<Frame>) {
        if let Some(a) = self.active.take() {
            self.emit(EventKind::LegCompleted {
                leg: a.id,
                skipped: true,
            });
        }
        self.suspended = None;
        let old = self.stage();
        self.frames = frames;
        self.completed = false;
        if let Some(s) = self.stage() {
            if Some(s) != old {
                self.emit(EventKind::StageChanged { stage: s });
            }
        }
        // Entering a branch by a jump counts as taking it.
        let mut taken = Vec::new();
        self.walk_frames(|node, kind| {
            if let FrameKind::Branch(b) = kind {
                taken.push((node.id.clone(), *b));
            }
        });
        for (leg, branch) in taken {
            self.emit(EventKind::BranchTaken { leg, branch });
        }
        self.settle();
    }

    /// Calls `f` with each construct node on the cursor path and its frame.
    pub(super) fn walk_frames(&self, mut f: impl FnMut(&Node, &FrameKind)) {
        let Some(FrameKind::Stage(s)) = self.frames.first().map(|f| &f.kind) else {
            return;
        };
        let mut list: &[Node] = self.plan.stage(*s);
        for w in self.frames.windows(2) {
            let Some(node) = list.get(w[0].index) else {
                return;
            };
            f(node, &w[1].kind);
            list = match child_list(node, &w[1].kind) {
                Some(l) => l,
                None => return,
            };
        }
    }

    /// Brings the state to one where `head()` is the next waypoint, or the plan is completed.
    pub(super) fn settle(&mut self) {
        let plan = Arc::clone(&self.plan);
        for _ in 0..SIM_LIMIT {
            if self.completed {
                return;
            }
            if let Some(a) = &self.active {
                if a.next < a.wps.len() {
                    return;
                }
                let Some(a) = self.active.take() else { return };
                self.emit(EventKind::LegCompleted {
                    leg: a.id.clone(),
                    skipped: false,
                });
                if a.interrupt {
                    self.active = self.suspended.take();
                } else if let Some(f) = self.frames.last_mut() {
                    f.index += 1;
                }
                continue;
            }
            let Some(top) = self.frames.last().cloned() else {
                self.finish();
                return;
            };
            let list = list_of(&plan, &self.frames);
            let Some(node) = list.get(top.index) else {
                self.end_of_list(&plan);
                continue;
            };
            match &node.kind {
                NodeKind::Iterative(it) => {
                    if let LoopMode::While(c) = &it.mode {
                        // `iteration` reads 0 before the first pass.
                        self.frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Loop {
                                iteration: 0,
                                produced: false,
                                waits: false,
                            },
                        });
                        let go = self.holds(c);
                        self.frames.pop();
                        if !go {
                            self.bump();
                            continue;
                        }
                    }
                    let waits = self.loop_waits(&it.mode);
                    self.frames.push(Frame {
                        index: 0,
                        kind: FrameKind::Loop {
                            iteration: 0,
                            produced: false,
                            waits,
                        },
                    });
                }
                NodeKind::Alternative(alt) => {
                    let chosen = alt
                        .branches
                        .iter()
                        .position(|b| b.cond.as_ref().is_none_or(|c| self.holds(c)));
                    match chosen {
                        Some(b) => {
                            self.emit(EventKind::BranchTaken {
                                leg: node.id.clone(),
                                branch: b,
                            });
                            self.frames.push(Frame {
                                index: 0,
                                kind: FrameKind::Branch(b),
                            });
                        }
                        None => self.bump(),
                    }
                }
                _ => self.activate(node),
            }
        }
        // A plan that loops without producing anything: stop rather than spin.
        self.finish();
    }

    pub(super) fn bump(&mut self) {
        if let Some(f) = self.frames.last_mut() {
            f.index += 1;
        }
    }

    /// In a nominal run, a loop whose condition only plan variables decide would repeat forever
    /// (nothing changes them): it is flown once and marked.
    pub(super) fn loop_waits(&self, mode: &LoopMode) -> bool {
        let decided_by_vars = |c: &crate::expr::Condition| !c.expr.mentions("iteration");
        match mode {
            LoopMode::Count(_) => false,
            LoopMode::While(c) => decided_by_vars(c) && self.holds(c),
            LoopMode::Until(c) => decided_by_vars(c) && !self.holds(c),
        }
    }

    pub(super) fn end_of_list(&mut self, plan: &FlightPlan) {
        let Some(f) = self.frames.pop() else { return };
        match f.kind {
            FrameKind::Stage(s) => {
                let next = Stage::ALL
                    .into_iter()
                    .filter(|x| *x > s)
                    .find(|x| !plan.stage(*x).is_empty());
                match next {
                    Some(n) => {
                        self.frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Stage(n),
                        });
                        self.emit(EventKind::StageChanged { stage: n });
                    }
                    None => self.finish(),
                }
            }
            FrameKind::Loop {
                iteration,
                produced,
                waits,
            } => {
                let n = iteration + 1;
                let list = list_of(plan, &self.frames);
                let Some(node) = self.frames.last().and_then(|p| list.get(p.index)) else {
                    return;
                };
                self.emit(EventKind::IterationDone {
                    leg: node.id.clone(),
                    n,
                });
                let NodeKind::Iterative(it) = &node.kind else {
                    return;
                };
                self.frames.push(Frame {
                    index: 0,
                    kind: FrameKind::Loop {
                        iteration: n,
                        produced: false,
                        waits,
                    },
                });
                let again = produced
                    && !(self.nominal && waits)
                    && match &it.mode {
                        LoopMode::Count(c) => n < *c,
                        LoopMode::While(c) => self.holds(c),
                        LoopMode::Until(c) => !self.holds(c),
                    };
                if !again {
                    self.frames.pop();
                    self.bump();
                }
            }
            FrameKind::Branch(_) => self.bump(),
        }
    }

    pub(super) fn activate(&mut self, node: &Node) {
        let ctx = self.ctx();
        let id = node.id.as_str();
        let mut hold = None;
        let wps = match &node.kind {
            NodeKind::Path(l) => expand_path(l, id, &ctx),
            NodeKind::Hold(h) => {
                // An HM waits for its condition or a command, an HA for its altitude: a nominal
                // run shows one circuit of either, marked.
                let waits = h.circuits.is_none()
                    && match h.kind {
                        HoldKind::HM => !h.until.as_ref().is_some_and(|c| self.holds(c)),
                        HoldKind::HA => true,
                        HoldKind::HF => false,
                    };
                hold = Some(HoldState {
                    hold: h.clone(),
                    entered: false,
                    circuits: 0,
                    exit: false,
                    waits,
                });
                hold_entry(h, id, &ctx)
            }
            NodeKind::Scan(s) => expand_scan(s, id, &ctx),
            NodeKind::Perimeter(p) => expand_perimeter(p, id, &ctx),
            NodeKind::Takeoff(t) => expand_takeoff(t, id, &ctx),
            NodeKind::Landing(l) => expand_landing(l, id, &ctx),
            NodeKind::Iterative(_) | NodeKind::Alternative(_) => Vec::new(),
        };
        let mut wps =
            enforce_min_distance(self.last.map(|o| o.pos), wps, self.vehicle.min_wp_distance);
        let waits = self.in_waiting_loop() || hold.as_ref().is_some_and(|h| h.waits);
        for w in &mut wps {
            w.waits = waits;
        }
        if let Some(first) = wps.first_mut() {
            first.land_start = self.begins_landing_sequence();
        }
        self.emit(EventKind::LegStarted {
            leg: node.id.clone(),
        });
        let at_fix = hold.is_some() && wps.is_empty();
        self.active = Some(Active {
            id: node.id.clone(),
            wps,
            next: 0,
            hold,
            interrupt: false,
        });
        if at_fix {
            self.hold_crossing();
        }
        self.mark_produced();
    }

    /// Whether the node being activated is where the plan's landing sequence begins: the first
    /// one (first pass of any loop) of the stage [`FlightPlan::landing_begins`] names.
    fn begins_landing_sequence(&self) -> bool {
        let Some(FrameKind::Stage(s)) = self.frames.first().map(|f| &f.kind) else {
            return false;
        };
        Some(*s) == self.plan.landing_begins()
            && self.frames.iter().all(|f| {
                f.index == 0
                    && !matches!(f.kind, FrameKind::Loop { iteration, .. } if iteration > 0)
            })
    }

    pub(super) fn in_waiting_loop(&self) -> bool {
        self.frames
            .iter()
            .any(|f| matches!(f.kind, FrameKind::Loop { waits: true, .. }))
    }

    pub(super) fn mark_produced(&mut self) {
        if self.active.as_ref().is_some_and(|a| a.next < a.wps.len()) {
            for f in &mut self.frames {
                if let FrameKind::Loop { produced, .. } = &mut f.kind {
                    *produced = true;
                }
            }
        }
    }

    /// At a hold's fix: decide whether to exit, else append the next circuit.
    pub(super) fn hold_crossing(&mut self) {
        let nominal = self.nominal;
        // A nominal run assumes the altitude is reached during the first circuit.
        let alt = match (nominal, self.measured_alt, self.var("alt")) {
            (false, Some(a), _) => Some(a),
            (_, _, Some(Value::Number(a))) => Some(a),
            _ => None,
        };
        let until = self
            .active
            .as_ref()
            .and_then(|a| a.hold.as_ref())
            .and_then(|h| h.hold.until.clone())
            .is_some_and(|c| self.holds(&c));
        let ctx_last = self.last;
        let plan_speed = self.plan.default_speed;
        let vehicle = self.vehicle.clone();
        let in_loop_wait = self.in_waiting_loop();
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some(hs) = a.hold.as_mut() else { return };
        if hs.entered {
            hs.circuits += 1;
        } else {
            hs.entered = true;
        }
        let h = &hs.hold;
        let ctx = Ctx {
            vehicle: &vehicle,
            prev: ctx_last,
            plan_speed,
        };
        let limit = h.circuits.is_some_and(|c| hs.circuits >= c);
        let done = hs.exit
            || match h.kind {
                HoldKind::HF => hs.circuits >= h.circuits.unwrap_or(1),
                HoldKind::HA => {
                    let target = hold_alt(h, &ctx);
                    let reached =
                        nominal || alt.is_some_and(|a| (a - target).abs() <= h.alt_tolerance);
                    limit || (hs.circuits >= 1 && reached)
                }
                HoldKind::HM => limit || until || (nominal && hs.waits && hs.circuits >= 1),
            };
        if done {
            // Drop anything not yet flown: the leg ends here.
            a.wps.truncate(a.next);
            return;
        }
        let mut circuit = hold_circuit(h, &a.id, &ctx);
        let waits = hs.waits || in_loop_wait;
        for w in &mut circuit {
            w.waits = waits;
        }
        let prev = a
            .wps
            .get(a.next.wrapping_sub(1))
            .map(Waypoint::pos)
            .or(ctx_last.map(|o| o.pos));
        let circuit = enforce_min_distance(prev, circuit, vehicle.min_wp_distance);
        a.wps.truncate(a.next);
        a.wps.extend(circuit);
    }

    pub(super) fn reach_head(&mut self) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some(w) = a.wps.get(a.next).cloned() else {
            return;
        };
        a.next += 1;
        if let Some(l) = self.last {
            self.flown += geo::distance(l.pos, w.pos());
        }
        self.last = Some(Origin {
            pos: w.pos(),
            alt: w.alt,
            speed: w.speed,
        });
        self.present = None;
        self.vars.insert("alt".into(), Value::Number(w.alt));
        self.emit(EventKind::WaypointReached {
            seq: self.next_seq,
            leg: w.leg.clone(),
        });
        self.next_seq += 1;
        if w.fix_crossing {
            self.hold_crossing();
        }
        self.settle();
    }
}

//! The executive's in-flight commands: replace or modify the plan, skip / go to a leg or a
//! stage, set a variable, hold here / exit the hold, pause / resume, re-task, insert legs, fire
//! an emergency rule. Each validates first and leaves the executive unchanged when it refuses.

use super::cursor::{Active, Frame, FrameKind, HoldState};
use super::tree::{list_mut, node_mut, path_to};
use super::types::*;
use super::Executive;
use crate::check::{check, check_change, CheckError, CheckedPlan};
use crate::expand::*;
use crate::expr::Value;
use crate::geo::{self, GeoPoint};
use crate::model::*;
use crate::parse::modify_node;
use crate::vehicle::VehicleKind;

impl Executive {
    /// Replaces the whole plan, atomically: the old one is dropped and the new one starts from
    /// its first stage with a new version. Returns the version. A plan checked for another
    /// vehicle is checked again for this one.
    ///
    /// # Errors
    /// [`CommandError::InvalidPlan`] when the plan does not suit this vehicle.
    pub fn replace_plan(&mut self, plan: CheckedPlan) -> Result<u64, CommandError> {
        let plan = if *plan.vehicle() == self.vehicle {
            plan
        } else {
            let (plan, _, _) = plan.into_parts();
            check((*plan).clone(), &self.vehicle)?
        };
        if let Some(a) = self.active.take() {
            self.emit(EventKind::LegCompleted {
                leg: a.id,
                skipped: true,
            });
        }
        self.set_plan(plan);
        self.emit(EventKind::PlanReplaced);
        self.start();
        Ok(self.version)
    }

    /// Changes attributes of leg `id` (e.g. a scan's `spacing`, a hold's `length`), validated as
    /// the parser would. A leg being flown restarts from the present position with the new
    /// parameters (a hold keeps its circuit count). Returns the new version.
    ///
    /// # Errors
    /// Unknown leg, or the modified leg does not validate.
    pub fn modify_leg(
        &mut self,
        id: &str,
        changes: &[(String, String)],
    ) -> Result<u64, CommandError> {
        let node = self
            .plan
            .find(id)
            .ok_or_else(|| CommandError::UnknownLeg(id.into()))?;
        let new = modify_node(node, changes, &self.plan)?;
        let mut changed = (*self.plan).clone();
        if let Some(slot) = node_mut(&mut changed, id) {
            *slot = new;
        }
        self.set_plan(check_change(changed, &self.vehicle)?);
        self.emit(EventKind::PlanModified { leg: id.into() });
        let current = self
            .active
            .as_ref()
            .is_some_and(|a| a.id == id && !a.interrupt);
        if current {
            let circuits = self
                .active
                .as_ref()
                .and_then(|a| a.hold.as_ref())
                .map(|h| h.circuits);
            self.active = None;
            self.settle();
            if let (Some(c), Some(h)) =
                (circuits, self.active.as_mut().and_then(|a| a.hold.as_mut()))
            {
                h.circuits = c;
            }
        }
        Ok(self.version)
    }

    /// Ends the current leg now and continues with the next one.
    ///
    /// # Errors
    /// [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn skip_leg(&mut self) -> Result<(), CommandError> {
        let Some(a) = self.active.take() else {
            return Err(CommandError::NothingToSkip);
        };
        self.emit(EventKind::LegCompleted {
            leg: a.id.clone(),
            skipped: true,
        });
        if a.interrupt {
            self.active = self.suspended.take();
        } else if let Some(f) = self.frames.last_mut() {
            f.index += 1;
        }
        self.settle();
        Ok(())
    }

    /// Continues with node `id` (a leg, or a loop / alternative, which is entered afresh).
    ///
    /// # Errors
    /// [`CommandError::UnknownLeg`].
    pub fn goto_leg(&mut self, id: &str) -> Result<(), CommandError> {
        let frames = path_to(&self.plan, id).ok_or_else(|| CommandError::UnknownLeg(id.into()))?;
        self.jump(frames);
        Ok(())
    }

    /// Continues with the first node of `stage`.
    ///
    /// # Errors
    /// [`CommandError::EmptyStage`] when the plan has no such stage.
    pub fn goto_stage(&mut self, stage: Stage) -> Result<(), CommandError> {
        if self.plan.stage(stage).is_empty() {
            return Err(CommandError::EmptyStage(stage));
        }
        self.jump(vec![Frame {
            index: 0,
            kind: FrameKind::Stage(stage),
        }]);
        Ok(())
    }

    /// Sets a plan variable (or the built-ins `alt`, `ground_speed`, `battery`, `elapsed_s`).
    /// Conditions see it from now on; emergency rules are checked.
    ///
    /// # Errors
    /// Unknown variable or wrong type.
    pub fn set_var(&mut self, name: &str, value: Value) -> Result<(), CommandError> {
        let ty = match self.plan.var_type(name) {
            Some(_) if name == "iteration" => {
                return Err(CommandError::UnknownVariable(name.into()))
            }
            Some(t) => t,
            None => return Err(CommandError::UnknownVariable(name.into())),
        };
        if value.ty() != ty {
            return Err(CommandError::TypeMismatch {
                name: name.into(),
                expected: ty,
            });
        }
        if let Value::Number(n) = value {
            if !n.is_finite() {
                return Err(bad_arg(name, "must be a finite number"));
            }
            if name == "alt" {
                self.measured_alt = Some(n);
            }
        }
        self.vars.insert(name.into(), value);
        self.check_rules();
        Ok(())
    }

    /// Interrupts the current leg with a hold (HM) at the present position; `exit_hold` (or
    /// `skip_leg`) resumes the interrupted leg where it was.
    ///
    /// # Errors
    /// [`CommandError::NoPosition`] before any position is known.
    /// Lengths, widths and courses out of range are refused as [`CommandError::BadArgument`].
    pub fn hold_here(&mut self, p: &HoldHere) -> Result<(), CommandError> {
        let min = self.vehicle.min_wp_distance;
        for (what, v) in [("length", p.length), ("width", p.width)] {
            if let Some(v) = v {
                if !v.is_finite() || v < min {
                    return Err(bad_arg(
                        format!("hold {what} {v}"),
                        &format!("must be at least the minimum waypoint distance, {min} m"),
                    ));
                }
            }
        }
        let shape = p
            .shape
            .unwrap_or(if self.vehicle.kind == VehicleKind::Rover {
                HoldShape::Rectangle
            } else {
                HoldShape::Racetrack
            });
        if let Some(w) = p.width {
            let turn = 2.0 * self.vehicle.turn_radius;
            if shape == HoldShape::Racetrack && w < turn {
                return Err(bad_arg(
                    format!("hold width {w}"),
                    &format!("is below the vehicle's turn limit of {turn} m"),
                ));
            }
        }
        if let Some(c) = p.inbound_course.filter(|c| !c.is_finite()) {
            return Err(bad_arg(
                format!("inbound course {c}"),
                "must be a number of degrees",
            ));
        }
        let pos = self
            .present
            .or(self.last.map(|o| o.pos))
            .ok_or(CommandError::NoPosition)?;
        let course = p
            .inbound_course
            .unwrap_or_else(|| match (self.last, self.head()) {
                (Some(l), Some(h)) if geo::distance(l.pos, h.pos()) > 0.1 => {
                    geo::inverse(l.pos, h.pos()).azi1
                }
                _ => 0.0,
            });
        let hold = Hold {
            kind: HoldKind::HM,
            fix: Fix {
                id: "here".into(),
                pos,
                alt: self.last.map(|o| o.alt),
            },
            inbound_course: course,
            turn: p.turn,
            length: Some(p.length.unwrap_or(5.0 * self.vehicle.min_wp_distance)),
            time: None,
            width: p.width,
            shape,
            circuits: None,
            until: None,
            target_alt: None,
            alt_tolerance: 5.0,
            common: LegCommon::default(),
        };
        let id = format!("hold-here.{}", self.next_seq);
        let act = Active {
            id: id.clone(),
            wps: Vec::new(),
            next: 0,
            hold: Some(HoldState {
                hold,
                entered: false,
                circuits: 0,
                exit: false,
                waits: true,
            }),
            interrupt: true,
        };
        self.interrupt_with(act);
        // The vehicle is at the fix: the entry crossing is now.
        self.hold_crossing();
        self.settle();
        Ok(())
    }

    /// Ends the current hold: at its next fix crossing, or at once with `now`.
    ///
    /// # Errors
    /// [`CommandError::NotHolding`].
    pub fn exit_hold(&mut self, now: bool) -> Result<(), CommandError> {
        let a = self.active.as_mut().ok_or(CommandError::NotHolding)?;
        let h = a.hold.as_mut().ok_or(CommandError::NotHolding)?;
        h.exit = true;
        if now {
            return self.skip_leg();
        }
        Ok(())
    }

    /// Stops handing out waypoints (the look-ahead is empty) until `resume`.
    ///
    /// # Errors
    /// [`CommandError::AlreadyPaused`].
    pub fn pause(&mut self) -> Result<(), CommandError> {
        if self.paused {
            return Err(CommandError::AlreadyPaused);
        }
        self.paused = true;
        self.emit(EventKind::Paused);
        Ok(())
    }

    /// Resumes where the plan was paused.
    ///
    /// # Errors
    /// [`CommandError::NotPaused`].
    pub fn resume(&mut self) -> Result<(), CommandError> {
        if !self.paused {
            return Err(CommandError::NotPaused);
        }
        self.paused = false;
        self.emit(EventKind::Resumed);
        Ok(())
    }

    /// Re-tasks the vehicle to points of interest, visited in nearest-neighbour order (seed 002)
    /// from the present position (`Now`) or from the end of the current leg (`AfterCurrentLeg`),
    /// at `alt` (default the present altitude). Returns the plan version.
    ///
    /// # Errors
    /// No points, or no position known.
    pub fn retask(
        &mut self,
        points: &[GeoPoint],
        alt: Option<f64>,
        mode: RetaskMode,
    ) -> Result<u64, CommandError> {
        if points.is_empty() {
            return Err(CommandError::NoPoints);
        }
        for (k, p) in points.iter().enumerate() {
            check_point(&format!("point {}", k + 1), *p)?;
            if let Some(pf) = &self.plan.fence {
                let height = alt
                    .filter(|_| !matches!(self.plan.altitude_reference(), usal_types::AltRef::Msl));
                pf.fence
                    .check_point((p.lat, p.lon), height)
                    .map_err(|why| {
                        bad_arg(
                            format!("point {}", k + 1),
                            &format!("is outside the fence: {why}"),
                        )
                    })?;
            }
        }
        if let Some(a) = alt.filter(|a| !a.is_finite()) {
            return Err(bad_arg(
                format!("altitude {a}"),
                "must be a number of metres",
            ));
        }
        let here = self.present.or(self.last.map(|o| o.pos));
        // Points visited after the current leg are ordered from where that leg ends.
        let from = match mode {
            RetaskMode::Now => here,
            RetaskMode::AfterCurrentLeg => self
                .active
                .as_ref()
                .and_then(|a| a.wps.last())
                .map(Waypoint::pos)
                .or(here),
        }
        .ok_or(CommandError::NoPosition)?;
        let order = nearest_neighbour(from, points);
        let alt = alt.or(self.last.map(|o| o.alt));
        match mode {
            RetaskMode::Now => {
                let id = format!("retask.{}", self.next_seq);
                let ctx = self.ctx();
                let wps: Vec<Waypoint> = order
                    .iter()
                    .flat_map(|p| expand_path(&poi_leg("poi".into(), *p, alt), &id, &ctx))
                    .collect();
                let wps = enforce_min_distance(Some(from), wps, self.vehicle.min_wp_distance);
                self.interrupt_with(Active {
                    id,
                    wps,
                    next: 0,
                    hold: None,
                    interrupt: true,
                });
                self.settle();
            }
            RetaskMode::AfterCurrentLeg => {
                let base = format!("retask.v{}", self.version + 1);
                let nodes: Vec<Node> = order
                    .iter()
                    .enumerate()
                    .map(|(k, p)| Node {
                        id: format!("{base}.{}", k + 1),
                        line: 0,
                        col: 0,
                        kind: NodeKind::Path(poi_leg(format!("poi{}", k + 1), *p, alt)),
                        source: None,
                    })
                    .collect();
                self.insert_after_current(nodes)?;
            }
        }
        Ok(self.version)
    }

    /// Inserts legs written in the plan's XML (`<leg .../>`, `<scan>`, `<iterative>`...) right
    /// after the current leg: a new plan version. They may use the plan's fixes and variables;
    /// those without an `id` are named `insert.v<version>.<n>`. Returns the version.
    ///
    /// # Errors
    /// [`CommandError::InvalidPlan`] naming the line of the fragment that is wrong (an unknown
    /// fix, an id already used...), or [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn insert_legs(&mut self, xml: &str) -> Result<u64, CommandError> {
        if self.frames.is_empty() {
            return Err(CommandError::NothingToSkip);
        }
        let prefix = format!("insert.v{}", self.version + 1);
        let nodes = crate::parse::parse_fragment(xml, &self.plan, &prefix)?;
        if nodes.is_empty() {
            return Err(bad_arg("legs", "the fragment has no legs"));
        }
        self.insert_after_current(nodes)
    }

    /// Inserts nodes right after the current leg (a new plan version). Returns the version.
    ///
    /// # Errors
    /// [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn insert_after_current(&mut self, nodes: Vec<Node>) -> Result<u64, CommandError> {
        if self.frames.is_empty() {
            return Err(CommandError::NothingToSkip);
        }
        let first = nodes.first().map(|n| n.id.clone()).unwrap_or_default();
        let frames = self.frames.clone();
        let mut changed = (*self.plan).clone();
        let Some(list) = list_mut(&mut changed, &frames) else {
            return Err(CommandError::NothingToSkip);
        };
        let at = frames.last().map_or(0, |f| f.index + 1).min(list.len());
        for (k, n) in nodes.into_iter().enumerate() {
            list.insert(at + k, n);
        }
        self.set_plan(check_change(changed, &self.vehicle)?);
        self.emit(EventKind::PlanModified { leg: first });
        self.settle();
        Ok(self.version)
    }

    /// Fires emergency rule `name`, or with `None` the default reaction: the approach stage,
    /// else landing, else a hold here.
    ///
    /// # Errors
    /// Unknown rule, or the reaction cannot apply.
    pub fn emergency(&mut self, name: Option<&str>) -> Result<(), CommandError> {
        let (rule, action) = match name {
            Some(n) => {
                let r = self
                    .plan
                    .emergencies
                    .iter()
                    .find(|r| r.name == n)
                    .ok_or_else(|| CommandError::UnknownRule(n.into()))?;
                (r.name.clone(), r.action.clone())
            }
            None => ("default".to_string(), EmergencyAction::Land),
        };
        self.emit(EventKind::EmergencyFired { rule });
        self.apply(&action)
    }
}

/// A re-tasked point of interest as a leg: straight to it and over it (a TF to fix `fix_id`).
fn poi_leg(fix_id: String, pos: GeoPoint, alt: Option<f64>) -> PathLeg {
    PathLeg {
        kind: PathKind::TF,
        fix: Fix {
            id: fix_id,
            pos,
            alt,
        },
        course: None,
        length: None,
        center: None,
        turn: None,
        common: LegCommon {
            fly_over: Some(true),
            ..LegCommon::default()
        },
    }
}

/// Orders points by repeatedly going to the nearest unvisited one (seed 002's "Nearest
/// Neighbor": not optimal, but fast and predictable).
pub fn nearest_neighbour(from: GeoPoint, points: &[GeoPoint]) -> Vec<GeoPoint> {
    let mut left: Vec<GeoPoint> = points.to_vec();
    let mut cur = from;
    let mut out = Vec::with_capacity(left.len());
    while !left.is_empty() {
        let (i, _) = left
            .iter()
            .enumerate()
            .map(|(i, p)| (i, geo::distance(cur, *p)))
            .fold(
                (0, f64::INFINITY),
                |best, x| if x.1 < best.1 { x } else { best },
            );
        cur = left.remove(i);
        out.push(cur);
    }
    out
}

impl Executive {
    /// Takes a checked plan as the new version (the caller starts or settles the cursor).
    fn set_plan(&mut self, checked: CheckedPlan) {
        let (plan, _, nominal) = checked.into_parts();
        self.plan = plan;
        self.checked_nominal = Some(nominal);
        self.version += 1;
    }
}

impl From<CheckError> for CommandError {
    fn from(e: CheckError) -> Self {
        match e {
            CheckError::Plan(e) => CommandError::InvalidPlan(e),
            CheckError::Endless(e) => CommandError::Endless(e),
        }
    }
}

//! Fleet plans (`config/fleetplans/*.xml`, format in `services/fleet/README.md`): the vehicles,
//! the variables, the separation rule and one block of EAMOS-style statements over the
//! vehicles' flight plans. Parsed and checked whole before anything flies; every error names
//! the line and column of the element at fault (`12:5: <fly>: unknown vehicle `rover9``).

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

use flightplan::expr::{Condition, Expr, Value, ValueType};
use flightplan::vehicle::{VehicleKind, VehicleParams};
use marea::xml::Element;

/// Why a fleet plan was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{line}:{col}: <{element}>: {message}")]
pub struct FleetPlanError {
    /// 1-based line of the element (or of the XML syntax error).
    pub line: u32,
    /// 1-based column.
    pub col: u32,
    /// The element at fault.
    pub element: String,
    /// What is wrong.
    pub message: String,
}

impl FleetPlanError {
    fn at(e: &Element, message: impl fmt::Display) -> Self {
        Self {
            line: e.pos.line,
            col: e.pos.col,
            element: e.name.clone(),
            message: message.to_string(),
        }
    }
}

/// A vehicle of the fleet.
#[derive(Clone, Debug, PartialEq)]
pub struct VehicleDecl {
    /// Its name in the plan (`surveyor`).
    pub id: String,
    /// Its services' prefix, the node's namespace (`rover1`): `rover1/fpma`, `rover1/vas`.
    pub prefix: String,
    /// Higher wins: on a separation conflict the lower-priority vehicle holds.
    pub priority: i32,
    /// How its flight plans are checked.
    pub kind: VehicleKind,
}

/// The minimum distance between vehicles and the distances the hold uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeparationRule {
    /// Closer than this is a violation (counted).
    pub min_m: f64,
    /// Closer than this holds the lower-priority vehicle.
    pub hold_m: f64,
    /// A held vehicle goes on once every vehicle is farther than this.
    pub clear_m: f64,
    /// Vehicles at least this far apart in altitude are separated whatever their horizontal
    /// distance (aircraft at two altitudes, as Broz's surveyor and investigator); `None`:
    /// horizontal distance alone.
    pub vertical_m: Option<f64>,
}

/// An event a `<wait>` can wait for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaitEvent {
    /// A new detection by any vehicle (or by `vehicle`).
    Detection,
    /// The vehicle's flight plan completed.
    Completed,
}

/// One statement, with where it is written.
#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    /// Line of its element.
    pub line: u32,
    /// Column.
    pub col: u32,
    /// What it does.
    pub kind: BlockKind,
}

/// The statements.
#[derive(Clone, Debug, PartialEq)]
pub enum BlockKind {
    /// Children one after the other.
    Seq(Vec<Block>),
    /// Children at the same time; ends when all have.
    Par(Vec<Block>),
    /// Load a flight plan into the vehicle's FPMa, start it, and (with `wait`) wait for it to
    /// complete.
    Fly {
        /// Index in [`FleetPlan::vehicles`].
        vehicle: usize,
        /// The plan file.
        file: PathBuf,
        /// Its XML, checked for the vehicle.
        xml: String,
        /// Wait for completion.
        wait: bool,
    },
    /// The FPMa's `goto_leg`.
    Goto {
        /// Vehicle index.
        vehicle: usize,
        /// Leg id.
        leg: String,
    },
    /// Hold the vehicle where it is.
    Pause {
        /// Vehicle index.
        vehicle: usize,
    },
    /// Let a paused vehicle go on.
    Resume {
        /// Vehicle index.
        vehicle: usize,
    },
    /// Wait for an event.
    WaitEvent {
        /// Which.
        event: WaitEvent,
        /// Of this vehicle only.
        vehicle: Option<usize>,
        /// Give up (an error) after this long.
        timeout_s: Option<f64>,
    },
    /// Wait until a condition holds.
    WaitUntil {
        /// The condition.
        cond: Condition,
        /// Give up (an error) after this long.
        timeout_s: Option<f64>,
    },
    /// A loop.
    Repeat {
        /// Passes (`count`).
        count: Option<u32>,
        /// Checked before each pass.
        while_: Option<Condition>,
        /// Checked after each pass.
        until: Option<Condition>,
        /// The body.
        body: Vec<Block>,
    },
    /// A choice.
    If {
        /// The condition.
        cond: Condition,
        /// When it holds.
        then: Vec<Block>,
        /// Otherwise.
        else_: Vec<Block>,
    },
    /// A synchronisation point: waits until every `<sync>` of that name has been reached.
    Sync {
        /// Its name.
        name: String,
        /// How many `<sync>` of that name the plan has.
        parties: usize,
    },
    /// Set a plan variable.
    Set {
        /// Its name.
        var: String,
        /// The value, evaluated when the statement runs (the condition language: literals,
        /// names, comparisons, `and`/`or`/`not`).
        expr: Option<Expr>,
        /// Or a number added to it (`add="1"`: the language has no arithmetic).
        add: Option<f64>,
    },
    /// The Broz investigator: visit every detection, nearest first from where the vehicle is,
    /// until `until` holds and nothing is left to visit.
    Investigate {
        /// Vehicle index.
        vehicle: usize,
        /// When to stop (once nothing is pending).
        until: Condition,
        /// Flight plan speed, m/s.
        speed: f64,
        /// Altitude of the visits, metres above home (0 for a rover).
        alt_m: f64,
    },
    /// A line in the service's log.
    Log {
        /// The text.
        text: String,
    },
}

/// A whole fleet plan.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetPlan {
    /// Its name.
    pub name: String,
    /// The vehicles, in file order.
    pub vehicles: Vec<VehicleDecl>,
    /// Declared variables and their initial values.
    pub vars: Vec<(String, Value)>,
    /// The separation rule, if any.
    pub separation: Option<SeparationRule>,
    /// The static obstacles investigators fly around (`<obstacles>`).
    pub obstacles: Vec<crate::wavefront::Obstacle>,
    /// The statements (a sequence).
    pub body: Block,
}

impl FleetPlan {
    /// Index of the vehicle named `id`.
    pub fn vehicle(&self, id: &str) -> Option<usize> {
        self.vehicles.iter().position(|v| v.id == id)
    }

    /// The type of every name a condition may use (see the README's table).
    pub fn type_of(&self, name: &str) -> Option<ValueType> {
        type_of(&self.vehicles, &self.vars, name)
    }
}

fn type_of(vehicles: &[VehicleDecl], vars: &[(String, Value)], name: &str) -> Option<ValueType> {
    if let Some((_, v)) = vars.iter().find(|(n, _)| n == name) {
        return Some(v.ty());
    }
    match name {
        "detections" | "visited" | "pending" | "elapsed_s" => return Some(ValueType::Number),
        _ => {}
    }
    let (veh, field) = name.split_once('.')?;
    vehicles.iter().find(|v| v.id == veh)?;
    match field {
        "done" | "holding" | "paused" => Some(ValueType::Bool),
        "progress" => Some(ValueType::Number),
        _ => None,
    }
}

/// Reads and checks a fleet plan file; flight plans it names are read relative to it.
///
/// # Errors
/// A message `FILE:LINE:COL: <element>: what`.
pub fn load(path: &Path) -> Result<FleetPlan, String> {
    let src = std::fs::read_to_string(path)
        .map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
    let base = path.parent().unwrap_or(Path::new("."));
    parse(&src, base).map_err(|e| format!("{}:{e}", path.display()))
}

/// Parses a fleet plan; `base` is the directory flight-plan paths are relative to.
///
/// # Errors
/// [`FleetPlanError`] naming the line, column and element.
pub fn parse(src: &str, base: &Path) -> Result<FleetPlan, FleetPlanError> {
    let root = marea::xml::parse_document(src).map_err(|e| FleetPlanError {
        line: e.pos.line,
        col: e.pos.col,
        element: e
            .element
            .as_ref()
            .map_or("fleetPlan", |el| &el.name)
            .to_owned(),
        message: e.kind.to_string(),
    })?;
    if root.name != "fleetPlan" {
        return Err(FleetPlanError::at(
            &root,
            "the root element must be <fleetPlan>",
        ));
    }
    let mut a = Attrs::new(&root, &["name"]);
    let name = a.req("name")?;
    a.finish()?;

    let mut p = Parser {
        base,
        vehicles: Vec::new(),
        vars: Vec::new(),
        syncs: HashMap::new(),
    };
    let mut separation = None;
    let mut obstacles = Vec::new();
    let mut body: Option<&Element> = None;
    for c in &root.children {
        match c.name.as_str() {
            "vehicle" => p.vehicle(c)?,
            "variables" => p.variables(c)?,
            "separation" if separation.is_none() => separation = Some(separation_rule(c)?),
            "obstacles" => {
                for o in &c.children {
                    obstacles.push(obstacle(o)?);
                }
            }
            "seq" | "par" if body.is_none() => body = Some(c),
            "separation" | "seq" | "par" => {
                return Err(FleetPlanError::at(c, "only one of these per plan"))
            }
            other => {
                return Err(FleetPlanError::at(
                    c,
                    format!("unknown element <{other}> (expected vehicle, variables, separation, obstacles, seq or par)"),
                ))
            }
        }
    }
    if p.vehicles.is_empty() {
        return Err(FleetPlanError::at(&root, "a fleet plan needs a <vehicle>"));
    }
    let Some(body) = body else {
        return Err(FleetPlanError::at(
            &root,
            "a fleet plan needs one <seq> or <par> with the statements",
        ));
    };
    count_syncs(body, &mut p.syncs);
    let body = p.block(body)?;
    Ok(FleetPlan {
        name,
        vehicles: p.vehicles,
        vars: p.vars,
        separation,
        obstacles,
        body,
    })
}

/// `<obstacle name height><pt lat lon/>...</obstacle>`: an area at least 3 points round and
/// how tall it stands above home.
fn obstacle(e: &Element) -> Result<crate::wavefront::Obstacle, FleetPlanError> {
    if e.name != "obstacle" {
        return Err(FleetPlanError::at(
            e,
            format!(
                "unknown element <{}> in <obstacles> (expected obstacle)",
                e.name
            ),
        ));
    }
    let mut a = Attrs::new(e, &["name", "height"]);
    let name = a.req("name")?;
    let height_m = a
        .number("height")?
        .ok_or_else(|| FleetPlanError::at(e, "missing attribute `height` (metres above home)"))?;
    a.finish()?;
    if !(height_m.is_finite() && height_m > 0.0) {
        return Err(FleetPlanError::at(
            e,
            format!("height {height_m} must be above 0 metres"),
        ));
    }
    let mut polygon = Vec::new();
    for p in &e.children {
        if p.name != "pt" {
            return Err(FleetPlanError::at(
                p,
                format!("unknown element <{}> in <obstacle> (expected pt)", p.name),
            ));
        }
        let mut a = Attrs::new(p, &["lat", "lon"]);
        let (lat, lon) = (a.number("lat")?, a.number("lon")?);
        a.finish()?;
        match (lat, lon) {
            (Some(lat), Some(lon))
                if (-90.0..=90.0).contains(&lat) && (-180.0..=180.0).contains(&lon) =>
            {
                polygon.push((lat, lon));
            }
            _ => {
                return Err(FleetPlanError::at(
                    p,
                    "a point needs lat (-90..90) and lon (-180..180)",
                ))
            }
        }
    }
    if polygon.len() < 3 {
        return Err(FleetPlanError::at(
            e,
            format!("obstacle `{name}` has {} points: at least 3", polygon.len()),
        ));
    }
    Ok(crate::wavefront::Obstacle {
        name,
        polygon,
        height_m,
    })
}

fn count_syncs(e: &Element, out: &mut HashMap<String, usize>) {
    if e.name == "sync" {
        if let Some(a) = e.attrs.iter().find(|a| a.name == "name") {
            *out.entry(a.value.clone()).or_default() += 1;
        }
    }
    for c in &e.children {
        count_syncs(c, out);
    }
}

fn separation_rule(e: &Element) -> Result<SeparationRule, FleetPlanError> {
    let mut a = Attrs::new(
        e,
        &[
            "minDistance",
            "holdDistance",
            "clearDistance",
            "verticalDistance",
        ],
    );
    let min_m = a
        .number("minDistance")?
        .ok_or_else(|| FleetPlanError::at(e, "missing attribute `minDistance` (metres)"))?;
    let hold_m = a.number("holdDistance")?.unwrap_or(2.0 * min_m);
    let clear_m = a.number("clearDistance")?.unwrap_or(hold_m + min_m / 2.0);
    let vertical_m = a.number("verticalDistance")?;
    a.finish()?;
    if vertical_m.is_some_and(|v| v.is_nan() || v <= 0.0) {
        return Err(FleetPlanError::at(e, "verticalDistance must be above 0 m"));
    }
    if !(min_m > 0.0 && hold_m >= min_m && clear_m > hold_m) {
        return Err(FleetPlanError::at(
            e,
            "distances must be 0 < minDistance <= holdDistance < clearDistance",
        ));
    }
    Ok(SeparationRule {
        min_m,
        hold_m,
        clear_m,
        vertical_m,
    })
}

struct Parser<'b> {
    base: &'b Path,
    vehicles: Vec<VehicleDecl>,
    vars: Vec<(String, Value)>,
    syncs: HashMap<String, usize>,
}

impl Parser<'_> {
    fn vehicle(&mut self, e: &Element) -> Result<(), FleetPlanError> {
        let mut a = Attrs::new(e, &["id", "prefix", "priority", "vehicle"]);
        let id = a.req("id")?;
        let prefix = a.req("prefix")?;
        let priority = match a.opt("priority") {
            None => 0,
            Some(v) => v.trim().parse().map_err(|_| {
                FleetPlanError::at(
                    e,
                    format!("attribute `priority`: `{v}` is not a whole number"),
                )
            })?,
        };
        let kind = match a.opt("vehicle").as_deref() {
            None => VehicleKind::Rover,
            Some(name) => VehicleKind::from_name(name).ok_or_else(|| {
                FleetPlanError::at(
                    e,
                    format!(
                        "attribute `vehicle`: `{name}` is not {}",
                        VehicleKind::choices()
                    ),
                )
            })?,
        };
        a.finish()?;
        let ok = |s: &str| {
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
                && s.starts_with(|c: char| c.is_ascii_alphabetic())
        };
        if !ok(&id) {
            return Err(FleetPlanError::at(
                e,
                format!("id `{id}`: start with a letter; letters, digits, '_' and '-'"),
            ));
        }
        if prefix.is_empty() || prefix.contains(['*', ' ']) || prefix.ends_with('/') {
            return Err(FleetPlanError::at(
                e,
                format!("prefix `{prefix}` is not a namespace such as rover1"),
            ));
        }
        if self.vehicles.iter().any(|v| v.id == id) {
            return Err(FleetPlanError::at(e, format!("duplicate vehicle `{id}`")));
        }
        if self.vehicles.iter().any(|v| v.prefix == prefix) {
            return Err(FleetPlanError::at(
                e,
                format!("another vehicle already has prefix `{prefix}`"),
            ));
        }
        self.vehicles.push(VehicleDecl {
            id,
            prefix,
            priority,
            kind,
        });
        Ok(())
    }

    fn variables(&mut self, e: &Element) -> Result<(), FleetPlanError> {
        Attrs::new(e, &[]).finish()?;
        for v in &e.children {
            if v.name != "var" {
                return Err(FleetPlanError::at(
                    v,
                    "unknown element (expected <var name type init>)",
                ));
            }
            let mut a = Attrs::new(v, &["name", "type", "init"]);
            let name = a.req("name")?;
            let ty = match a.req("type")?.as_str() {
                "bool" => ValueType::Bool,
                "number" => ValueType::Number,
                other => {
                    return Err(FleetPlanError::at(
                        v,
                        format!("attribute `type`: `{other}` is not bool or number"),
                    ))
                }
            };
            let init = a.req("init")?;
            a.finish()?;
            let value = Value::parse(ty, &init).ok_or_else(|| {
                FleetPlanError::at(v, format!("attribute `init`: `{init}` is not a {ty:?}"))
            })?;
            if name.contains('.') || type_of(&self.vehicles, &[], &name).is_some() {
                return Err(FleetPlanError::at(
                    v,
                    format!("`{name}` is a built-in name (or has a '.')"),
                ));
            }
            if self.vars.iter().any(|(n, _)| *n == name) {
                return Err(FleetPlanError::at(
                    v,
                    format!("duplicate variable `{name}`"),
                ));
            }
            self.vars.push((name, value));
        }
        Ok(())
    }

    fn vehicle_ref(&self, e: &Element, a: &mut Attrs) -> Result<usize, FleetPlanError> {
        let id = a.req("vehicle")?;
        self.vehicles
            .iter()
            .position(|v| v.id == id)
            .ok_or_else(|| {
                FleetPlanError::at(
                    e,
                    format!("unknown vehicle `{id}` (declare it with <vehicle>)"),
                )
            })
    }

    fn cond(&self, e: &Element, key: &str, src: &str) -> Result<Condition, FleetPlanError> {
        let c = Condition::parse(src)
            .map_err(|err| FleetPlanError::at(e, format!("attribute `{key}`: {err}")))?;
        let ty = c
            .expr
            .check(&|n| type_of(&self.vehicles, &self.vars, n))
            .map_err(|err| FleetPlanError::at(e, format!("attribute `{key}`: {err}")))?;
        if ty != ValueType::Bool {
            return Err(FleetPlanError::at(
                e,
                format!("attribute `{key}`: `{src}` is not a condition (true or false)"),
            ));
        }
        Ok(c)
    }

    fn body(&self, e: &Element) -> Result<Vec<Block>, FleetPlanError> {
        e.children.iter().map(|c| self.block(c)).collect()
    }

    fn block(&self, e: &Element) -> Result<Block, FleetPlanError> {
        let kind = match e.name.as_str() {
            "seq" | "par" => {
                Attrs::new(e, &[]).finish()?;
                let body = self.body(e)?;
                if body.is_empty() {
                    return Err(FleetPlanError::at(e, "an empty block"));
                }
                if e.name == "seq" {
                    BlockKind::Seq(body)
                } else {
                    BlockKind::Par(body)
                }
            }
            "fly" => {
                let mut a = Attrs::new(e, &["vehicle", "plan", "wait"]);
                let vehicle = self.vehicle_ref(e, &mut a)?;
                let rel = a.req("plan")?;
                let wait = a.boolean("wait")?.unwrap_or(true);
                a.finish()?;
                self.no_children(e)?;
                let file = self.base.join(&rel);
                let xml = std::fs::read_to_string(&file).map_err(|err| {
                    FleetPlanError::at(e, format!("plan `{}`: {err}", file.display()))
                })?;
                let params = VehicleParams::for_kind(self.vehicles[vehicle].kind);
                flightplan::check::load(&xml, &params)
                    .map_err(|err| FleetPlanError::at(e, format!("plan {}", err.in_file(&rel))))?;
                BlockKind::Fly {
                    vehicle,
                    file,
                    xml,
                    wait,
                }
            }
            "goto" => {
                let mut a = Attrs::new(e, &["vehicle", "leg"]);
                let vehicle = self.vehicle_ref(e, &mut a)?;
                let leg = a.req("leg")?;
                a.finish()?;
                self.no_children(e)?;
                BlockKind::Goto { vehicle, leg }
            }
            "pause" | "resume" => {
                let mut a = Attrs::new(e, &["vehicle"]);
                let vehicle = self.vehicle_ref(e, &mut a)?;
                a.finish()?;
                self.no_children(e)?;
                if e.name == "pause" {
                    BlockKind::Pause { vehicle }
                } else {
                    BlockKind::Resume { vehicle }
                }
            }
            "wait" => {
                let mut a = Attrs::new(e, &["event", "vehicle", "until", "timeoutS"]);
                let event = a.opt("event");
                let until = a.opt("until");
                let timeout_s = a.number("timeoutS")?;
                if timeout_s.is_some_and(|t| !(t > 0.0 && t < 1e9)) {
                    return Err(FleetPlanError::at(e, "timeoutS must be a positive number of seconds"));
                }
                let vehicle = if a.has("vehicle") {
                    Some(self.vehicle_ref(e, &mut a)?)
                } else {
                    None
                };
                a.finish()?;
                self.no_children(e)?;
                match (event.as_deref(), until) {
                    (Some(ev), None) => {
                        let event = match ev {
                            "detection" => WaitEvent::Detection,
                            "completed" => WaitEvent::Completed,
                            other => {
                                return Err(FleetPlanError::at(
                                    e,
                                    format!("attribute `event`: `{other}` is not detection or completed"),
                                ))
                            }
                        };
                        if event == WaitEvent::Completed && vehicle.is_none() {
                            return Err(FleetPlanError::at(
                                e,
                                "event `completed` needs `vehicle`",
                            ));
                        }
                        BlockKind::WaitEvent {
                            event,
                            vehicle,
                            timeout_s,
                        }
                    }
                    (None, Some(src)) => {
                        if vehicle.is_some() {
                            return Err(FleetPlanError::at(
                                e,
                                "`vehicle` goes with `event`, not `until`",
                            ));
                        }
                        BlockKind::WaitUntil {
                            cond: self.cond(e, "until", &src)?,
                            timeout_s,
                        }
                    }
                    _ => {
                        return Err(FleetPlanError::at(
                            e,
                            "exactly one of `event` and `until`",
                        ))
                    }
                }
            }
            "repeat" => {
                let mut a = Attrs::new(e, &["count", "while", "until"]);
                let count = match a.opt("count") {
                    None => None,
                    Some(v) => match v.trim().parse::<u32>() {
                        Ok(n) if n > 0 => Some(n),
                        _ => {
                            return Err(FleetPlanError::at(
                                e,
                                format!("attribute `count`: `{v}` is not a whole number above 0"),
                            ))
                        }
                    },
                };
                let while_ = a.opt("while").map(|s| self.cond(e, "while", &s)).transpose()?;
                let until = a.opt("until").map(|s| self.cond(e, "until", &s)).transpose()?;
                a.finish()?;
                if count.is_none() && while_.is_none() && until.is_none() {
                    return Err(FleetPlanError::at(
                        e,
                        "a <repeat> needs `count`, `while` or `until`",
                    ));
                }
                let body = self.body(e)?;
                if body.is_empty() {
                    return Err(FleetPlanError::at(e, "an empty block"));
                }
                BlockKind::Repeat {
                    count,
                    while_,
                    until,
                    body,
                }
            }
            "if" => {
                let mut a = Attrs::new(e, &["cond"]);
                let src = a.req("cond")?;
                a.finish()?;
                let cond = self.cond(e, "cond", &src)?;
                let mut then = None;
                let mut else_ = None;
                for c in &e.children {
                    match c.name.as_str() {
                        "then" if then.is_none() && else_.is_none() => {
                            Attrs::new(c, &[]).finish()?;
                            then = Some(self.body(c)?);
                        }
                        "else" if then.is_some() && else_.is_none() => {
                            Attrs::new(c, &[]).finish()?;
                            else_ = Some(self.body(c)?);
                        }
                        _ => {
                            return Err(FleetPlanError::at(
                                c,
                                "an <if> holds one <then> and at most one <else> after it",
                            ))
                        }
                    }
                }
                let Some(then) = then else {
                    return Err(FleetPlanError::at(e, "an <if> needs a <then>"));
                };
                BlockKind::If {
                    cond,
                    then,
                    else_: else_.unwrap_or_default(),
                }
            }
            "sync" => {
                let mut a = Attrs::new(e, &["name"]);
                let name = a.req("name")?;
                a.finish()?;
                self.no_children(e)?;
                let parties = self.syncs.get(&name).copied().unwrap_or(0);
                if parties < 2 {
                    return Err(FleetPlanError::at(
                        e,
                        format!("sync point `{name}` is the only one of its name: nothing to wait for"),
                    ));
                }
                BlockKind::Sync { name, parties }
            }
            "set" => {
                let mut a = Attrs::new(e, &["var", "value", "add"]);
                let var = a.req("var")?;
                let src = a.opt("value");
                let add = a.number("add")?;
                a.finish()?;
                self.no_children(e)?;
                let Some((_, init)) = self.vars.iter().find(|(n, _)| *n == var) else {
                    return Err(FleetPlanError::at(
                        e,
                        format!("unknown variable `{var}` (declare it in <variables>)"),
                    ));
                };
                match (src, add) {
                    (Some(src), None) => {
                        let expr = Expr::parse(&src).map_err(|err| {
                            FleetPlanError::at(e, format!("attribute `value`: {err}"))
                        })?;
                        let ty = expr
                            .check(&|n| type_of(&self.vehicles, &self.vars, n))
                            .map_err(|err| {
                                FleetPlanError::at(e, format!("attribute `value`: {err}"))
                            })?;
                        if ty != init.ty() {
                            return Err(FleetPlanError::at(
                                e,
                                format!(
                                    "attribute `value`: `{src}` is a {ty:?}, `{var}` a {:?}",
                                    init.ty()
                                ),
                            ));
                        }
                        BlockKind::Set {
                            var,
                            expr: Some(expr),
                            add: None,
                        }
                    }
                    (None, Some(x)) if init.ty() == ValueType::Number => BlockKind::Set {
                        var,
                        expr: None,
                        add: Some(x),
                    },
                    (None, Some(_)) => {
                        return Err(FleetPlanError::at(
                            e,
                            format!("`add` needs a number variable; `{var}` is a bool"),
                        ))
                    }
                    _ => {
                        return Err(FleetPlanError::at(
                            e,
                            "exactly one of `value` and `add`",
                        ))
                    }
                }
            }
            "investigate" => {
                let mut a = Attrs::new(e, &["vehicle", "until", "speed", "alt"]);
                let vehicle = self.vehicle_ref(e, &mut a)?;
                let src = a.req("until")?;
                let speed = a.number("speed")?.unwrap_or(2.0);
                let alt = a.number("alt")?;
                a.finish()?;
                self.no_children(e)?;
                if !(speed > 0.0 && speed < 1000.0) {
                    return Err(FleetPlanError::at(e, "speed must be above 0 m/s"));
                }
                let rover = self.vehicles[vehicle].kind == VehicleKind::Rover;
                let alt_m = match alt {
                    None if rover => 0.0,
                    None => {
                        return Err(FleetPlanError::at(
                            e,
                            "an aircraft investigates at an altitude: give `alt` (metres above home)",
                        ))
                    }
                    Some(a) if rover && a != 0.0 => {
                        return Err(FleetPlanError::at(e, "a rover has no `alt` to fly at"))
                    }
                    Some(a) if !rover && !(2.0..=1000.0).contains(&a) => {
                        return Err(FleetPlanError::at(
                            e,
                            "alt must be between 2 and 1000 m above home",
                        ))
                    }
                    Some(a) => a,
                };
                BlockKind::Investigate {
                    vehicle,
                    until: self.cond(e, "until", &src)?,
                    speed,
                    alt_m,
                }
            }
            "log" => {
                let mut a = Attrs::new(e, &["text"]);
                let text = a.req("text")?;
                a.finish()?;
                self.no_children(e)?;
                BlockKind::Log { text }
            }
            other => {
                return Err(FleetPlanError::at(
                    e,
                    format!("unknown statement <{other}> (expected seq, par, fly, goto, pause, resume, wait, repeat, if, sync, set, investigate or log)"),
                ))
            }
        };
        Ok(Block {
            line: e.pos.line,
            col: e.pos.col,
            kind,
        })
    }

    fn no_children(&self, e: &Element) -> Result<(), FleetPlanError> {
        match e.children.first() {
            None => Ok(()),
            Some(c) => Err(FleetPlanError::at(
                c,
                format!("<{}> takes no child elements", e.name),
            )),
        }
    }
}

/// An element's attributes, taken one by one; those left over are errors.
struct Attrs<'a> {
    el: &'a Element,
    left: Vec<(String, String)>,
    known: &'static [&'static str],
}

impl<'a> Attrs<'a> {
    fn new(el: &'a Element, known: &'static [&'static str]) -> Self {
        Self {
            el,
            left: el
                .attrs
                .iter()
                .map(|a| (a.name.clone(), a.value.clone()))
                .collect(),
            known,
        }
    }

    fn has(&self, key: &str) -> bool {
        self.left.iter().any(|(k, _)| k == key)
    }

    fn opt(&mut self, key: &str) -> Option<String> {
        let i = self.left.iter().position(|(k, _)| k == key)?;
        Some(self.left.remove(i).1)
    }

    fn req(&mut self, key: &str) -> Result<String, FleetPlanError> {
        self.opt(key)
            .ok_or_else(|| FleetPlanError::at(self.el, format!("missing attribute `{key}`")))
    }

    fn number(&mut self, key: &str) -> Result<Option<f64>, FleetPlanError> {
        match self.opt(key) {
            None => Ok(None),
            Some(v) => match v.trim().parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(Some(x)),
                _ => Err(FleetPlanError::at(
                    self.el,
                    format!("attribute `{key}`: `{v}` is not a number"),
                )),
            },
        }
    }

    fn boolean(&mut self, key: &str) -> Result<Option<bool>, FleetPlanError> {
        match self.opt(key).as_deref() {
            None => Ok(None),
            Some("true") => Ok(Some(true)),
            Some("false") => Ok(Some(false)),
            Some(v) => Err(FleetPlanError::at(
                self.el,
                format!("attribute `{key}`: `{v}` is not true or false"),
            )),
        }
    }

    fn finish(self) -> Result<(), FleetPlanError> {
        match self.left.first() {
            None => Ok(()),
            Some((k, _)) => Err(FleetPlanError::at(
                self.el,
                format!(
                    "unknown attribute `{k}` (expected {})",
                    if self.known.is_empty() {
                        "none".to_owned()
                    } else {
                        self.known.join(", ")
                    }
                ),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/fleetplans")
    }

    fn parse_str(src: &str) -> Result<FleetPlan, String> {
        parse(src, &dir()).map_err(|e| e.to_string())
    }

    const GOOD: &str = r#"<fleetPlan name="t">
  <vehicle id="a" prefix="rover1" priority="2"/>
  <vehicle id="b" prefix="rover2"/>
  <variables><var name="n" type="number" init="0"/></variables>
  <separation minDistance="5" holdDistance="15" clearDistance="20"/>
  <par>
    <seq>
      <fly vehicle="a" plan="../flightplans/search-surveyor-start.xml"/>
      <sync name="start"/>
      <fly vehicle="a" plan="../flightplans/search-area.xml"/>
    </seq>
    <seq>
      <fly vehicle="b" plan="../flightplans/search-investigator-start.xml"/>
      <sync name="start"/>
      <investigate vehicle="b" until="a.done and pending == 0"/>
    </seq>
    <repeat count="2"><set var="n" add="1"/></repeat>
    <if cond="n >= 2"><then><log text="two"/></then><else><wait until="detections > 0" timeoutS="5"/></else></if>
    <wait event="completed" vehicle="a"/>
  </par>
</fleetPlan>"#;

    #[test]
    fn obstacles_are_read_and_a_bad_one_names_its_line() {
        let with = |o: &str| {
            parse_str(&GOOD.replace("<par>", &format!("<obstacles>{o}</obstacles>\n  <par>")))
        };
        let p = with(r#"<obstacle name="shed" height="6"><pt lat="41.2" lon="1.9"/><pt lat="41.3" lon="1.9"/><pt lat="41.3" lon="2.0"/></obstacle>"#).unwrap();
        assert_eq!(p.obstacles.len(), 1);
        assert_eq!(
            (p.obstacles[0].name.as_str(), p.obstacles[0].height_m),
            ("shed", 6.0)
        );
        assert_eq!(p.obstacles[0].polygon[2], (41.3, 2.0));
        let e = with(r#"<obstacle name="shed" height="6"><pt lat="41.2" lon="1.9"/></obstacle>"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("<obstacle>") && e.contains("at least 3"), "{e}");
        let e = with(r#"<obstacle name="x" height="-1"/>"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("height -1 must be above 0"), "{e}");
        let e = with(r#"<obstacle name="x" height="3"><pt lat="95" lon="1"/></obstacle>"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("<pt>"), "{e}");
    }

    #[test]
    fn a_good_plan_parses_with_its_blocks_and_sync_parties() {
        let p = parse_str(GOOD).unwrap();
        assert_eq!(p.name, "t");
        assert_eq!(p.vehicles.len(), 2);
        assert_eq!((p.vehicles[0].priority, p.vehicles[1].priority), (2, 0));
        let sep = p.separation.unwrap();
        assert_eq!((sep.min_m, sep.hold_m, sep.clear_m), (5.0, 15.0, 20.0));
        let BlockKind::Par(branches) = &p.body.kind else {
            panic!("a par");
        };
        assert_eq!(branches.len(), 5);
        let BlockKind::Seq(first) = &branches[0].kind else {
            panic!("a seq");
        };
        assert!(matches!(
            &first[1].kind,
            BlockKind::Sync { name, parties: 2 } if name == "start"
        ));
        assert_eq!((first[1].line, first[1].col), (9, 7));
        assert!(matches!(
            &first[0].kind,
            BlockKind::Fly {
                vehicle: 0,
                wait: true,
                ..
            }
        ));
    }

    #[test]
    fn errors_name_line_column_and_element() {
        let cases: &[(&str, &str, &str)] = &[
            (
                r#"vehicle="b" plan="../flightplans/search-investigator-start.xml""#,
                r#"vehicle="c" plan="../flightplans/search-investigator-start.xml""#,
                "13:7: <fly>: unknown vehicle `c`",
            ),
            ("search-area.xml", "nope.xml", "10:7: <fly>: plan `"),
            (
                r#"until="a.done and pending == 0""#,
                r#"until="a.gone""#,
                "15:7: <investigate>: attribute `until`",
            ),
            (
                r#"until="a.done and pending == 0""#,
                r#"until="pending""#,
                "15:7: <investigate>: attribute `until`: `pending` is not a condition",
            ),
            (
                "<repeat count=\"2\">",
                "<repeat count=\"0\">",
                "17:5: <repeat>: attribute `count`",
            ),
            (
                "<set var=\"n\"",
                "<set var=\"m\"",
                "17:23: <set>: unknown variable `m`",
            ),
            (
                "<if cond=\"n >= 2\"><then>",
                "<if cond=\"n >= 2\"><else/><then>",
                "18:23: <else>: an <if> holds one <then>",
            ),
            (
                "timeoutS=\"5\"",
                "timeoutS=\"-5\"",
                "18:59: <wait>: timeoutS must be",
            ),
            (
                "<wait event=\"completed\" vehicle=\"a\"/>",
                "<wait event=\"completed\"/>",
                "19:5: <wait>: event `completed` needs `vehicle`",
            ),
            (
                "<wait event=\"completed\" vehicle=\"a\"/>",
                "<wait event=\"landed\" vehicle=\"a\"/>",
                "19:5: <wait>: attribute `event`",
            ),
            (
                "<log text=\"two\"/>",
                "<log text=\"two\" colour=\"red\"/>",
                "18:29: <log>: unknown attribute `colour`",
            ),
            (
                "<sync name=\"start\"/>\n      <investigate",
                "<sync name=\"go\"/>\n      <investigate",
                "9:7: <sync>: sync point `start` is the only one",
            ),
            (
                "<vehicle id=\"b\" prefix=\"rover2\"/>",
                "<vehicle id=\"a\" prefix=\"rover3\"/>",
                "3:3: <vehicle>: duplicate vehicle `a`",
            ),
            (
                "minDistance=\"5\"",
                "minDistance=\"50\"",
                "5:3: <separation>: distances must be",
            ),
            (
                "clearDistance=\"20\"",
                "clearDistance=\"20\" verticalDistance=\"0\"",
                "5:3: <separation>: verticalDistance must be above 0 m",
            ),
            (
                "until=\"a.done and pending == 0\"",
                "until=\"a.done and pending == 0\" alt=\"10\"",
                "15:7: <investigate>: a rover has no `alt` to fly at",
            ),
            (
                "<wait until",
                "<whait until",
                "18:59: <whait>: unknown statement",
            ),
            (
                "</par>",
                "</seq>",
                "20:3: <par>: ill-formed document: expected `</par>`",
            ),
        ];
        for (from, to, want) in cases {
            assert!(GOOD.contains(from), "{from}");
            let e = parse_str(&GOOD.replacen(from, to, 1)).unwrap_err();
            assert!(e.starts_with(want), "{from} -> {to}: got {e}, want {want}");
        }
    }

    #[test]
    fn a_bad_flight_plan_is_reported_at_the_fly_that_names_it_with_its_own_position() {
        let dir = std::env::temp_dir().join(format!("fleet-plan-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(
            dir.join("bad.xml"),
            "<flightPlan name=\"x\">\n  <mission>\n    <leg type=\"TF\" fix=\"P9\"/>\n  </mission>\n</flightPlan>",
        )
        .unwrap();
        let src = "<fleetPlan name=\"t\">\n<vehicle id=\"a\" prefix=\"r1\"/>\n<seq>\n  <fly vehicle=\"a\" plan=\"bad.xml\"/>\n</seq>\n</fleetPlan>";
        let e = parse(src, &dir).unwrap_err().to_string();
        let _ = std::fs::remove_dir_all(&dir);
        assert!(e.starts_with("4:3: <fly>: plan bad.xml:3:"), "{e}");
        assert!(e.contains("P9"), "{e}");
    }

    #[test]
    fn truncated_input_is_an_error_never_a_panic() {
        for cut in 0..GOOD.len() {
            if GOOD.is_char_boundary(cut) {
                let _ = parse_str(&GOOD[..cut]);
            }
        }
    }

    #[test]
    fn the_shipped_fleet_plans_parse() {
        let mut n = 0;
        for entry in std::fs::read_dir(dir()).unwrap() {
            let p = entry.unwrap().path();
            if p.extension().is_some_and(|e| e == "xml") {
                load(&p).unwrap_or_else(|e| panic!("{e}"));
                n += 1;
            }
        }
        assert!(n > 0);
        // An aircraft investigates at an altitude it is given.
        let copter = GOOD
            .replace(
                "<vehicle id=\"b\" prefix=\"rover2\"/>",
                "<vehicle id=\"b\" prefix=\"rover2\" vehicle=\"copter\"/>",
            )
            .replace(
                "search-investigator-start.xml",
                "search-copter-investigator-start.xml",
            );
        let e = parse_str(&copter).unwrap_err();
        assert!(
            e.starts_with("15:7: <investigate>: an aircraft investigates at an altitude"),
            "{e}"
        );
        let with_alt = copter.replace("pending == 0\"", "pending == 0\" alt=\"12\"");
        let p = parse_str(&with_alt).unwrap();
        let BlockKind::Par(branches) = &p.body.kind else {
            panic!("{:?}", p.body)
        };
        let BlockKind::Seq(b) = &branches[1].kind else {
            panic!("{:?}", branches[1])
        };
        assert!(
            matches!(b[2].kind, BlockKind::Investigate { alt_m, .. } if alt_m == 12.0),
            "{:?}",
            b[2]
        );
        // The copters' search: two altitudes, the investigator's low.
        let p = load(&dir().join("search-copters.xml")).unwrap();
        assert_eq!(p.separation.and_then(|s| s.vertical_m), Some(10.0));
        assert!(p.vehicles.iter().all(|v| v.kind == VehicleKind::Copter));
    }
}

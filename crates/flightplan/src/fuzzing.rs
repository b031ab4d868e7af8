//! Structure-aware fuzzing of plan XML (feature `fuzzing`, off by default): plans of realistic
//! size (variables, a dozen to a few dozen fixes, departure, holds, scans, perimeters, loops,
//! alternatives, approach, emergencies) with mostly sensible attribute values and a share of
//! bent ones (NaN, huge, negative, missing, unknown), then XML-level damage (a range cut,
//! duplicated or swapped). The harness [`plan_xml`] parses for both vehicles and expands the
//! plans that parse, checking: never a panic, every expanded waypoint finite and in range, the
//! expansion within its stated limit. It runs from `fuzz/` (target `fpma_plan`) and
//! on stable from `tests/structured_fuzz.rs`.

use std::fmt::Write;

use arbitrary::{Result, Unstructured};

use crate::check::load;
use crate::vehicle::VehicleParams;

thread_local! {
    /// Whether the plan being generated gets bent values (a quarter of them); a plan is
    /// otherwise meant to parse, so the parser's deeper checks and the expansion run.
    static BENT: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

fn bent() -> bool {
    BENT.with(std::cell::Cell::get)
}

fn num(u: &mut Unstructured<'_>, lo: f64, hi: f64) -> Result<String> {
    let pick = if bent() {
        u.int_in_range(0u8..=63)?
    } else {
        63
    };
    Ok(match pick {
        0 => "NaN".into(),
        1 => "inf".into(),
        2 => "-1e308".into(),
        3 => "1e308".into(),
        4 => "".into(),
        5 => "12abc".into(),
        6 => "0".into(),
        _ => {
            let f = f64::from(u.int_in_range(0u32..=1_000_000)?) / 1_000_000.0;
            format!("{:.6}", lo + (hi - lo) * f)
        }
    })
}

/// One of the `good` values, or `bad` now and then in a bent plan.
fn pick(
    u: &mut Unstructured<'_>,
    good: &[&'static str],
    bad: &'static str,
) -> Result<&'static str> {
    if bent() && u.ratio(1u8, 8)? {
        Ok(bad)
    } else {
        Ok(*u.choose(good)?)
    }
}

fn attr(out: &mut String, name: &str, value: &str) {
    let _ = write!(out, " {name}=\"{value}\"");
}

fn pts(u: &mut Unstructured<'_>, out: &mut String, lat: f64, lon: f64) -> Result<()> {
    let n = u.int_in_range(0usize..=8)?;
    for _ in 0..n {
        out.push_str("<pt");
        attr(out, "lat", &num(u, lat - 0.01, lat + 0.01)?);
        attr(out, "lon", &num(u, lon - 0.01, lon + 0.01)?);
        out.push_str("/>");
    }
    Ok(())
}

fn leg(u: &mut Unstructured<'_>, out: &mut String, fixes: usize) -> Result<()> {
    let ty = if bent() {
        *u.choose(&["TF", "DF", "IF", "HF", "HM", "HA", "CF", "XX"])?
    } else {
        *u.choose(&["TF", "TF", "TF", "DF", "HF", "HM"])?
    };
    out.push_str("<leg");
    if u.ratio(1u8, 3)? {
        attr(out, "id", &format!("l{}", u.int_in_range(0u8..=20)?));
    }
    attr(out, "type", ty);
    let last = if bent() { fixes } else { fixes - 1 };
    attr(out, "fix", &format!("F{}", u.int_in_range(0..=last)?));
    if ty.starts_with('H') {
        attr(out, "inboundCourse", &num(u, 0.0, 360.0)?);
        attr(out, "turn", pick(u, &["L", "R"], "X")?);
        attr(out, "length", &num(u, 1.0, 800.0)?);
        attr(out, "width", &num(u, 1.0, 400.0)?);
        if u.arbitrary()? {
            attr(
                out,
                "shape",
                pick(u, &["rectangle", "racetrack"], "circle")?,
            );
        }
        if u.arbitrary()? {
            attr(
                out,
                "until",
                pick(u, &["inspect", "laps &gt; 1", "not inspect"], "((")?,
            );
        }
    }
    if u.arbitrary()? {
        attr(out, "speed", &num(u, 0.5, 40.0)?);
    }
    if u.arbitrary()? {
        attr(out, "flyOver", pick(u, &["true", "false"], "maybe")?);
    }
    out.push_str("/>");
    Ok(())
}

fn element(
    u: &mut Unstructured<'_>,
    out: &mut String,
    fixes: usize,
    depth: u32,
    (lat, lon): (f64, f64),
) -> Result<()> {
    match u.int_in_range(0u8..=9)? {
        0..=4 => leg(u, out, fixes)?,
        5 => {
            out.push_str("<scan");
            attr(out, "spacing", &num(u, 0.5, 200.0)?);
            attr(out, "sweepAngle", &num(u, -360.0, 360.0)?);
            if u.arbitrary()? {
                attr(out, "alt", &num(u, 0.0, 300.0)?);
            }
            attr(
                out,
                "entry",
                pick(u, &["nearest", "left", "right"], "first")?,
            );
            out.push('>');
            pts(u, out, lat, lon)?;
            out.push_str("</scan>");
        }
        6 => {
            out.push_str("<perimeter");
            attr(out, "spacing", &num(u, 0.5, 200.0)?);
            attr(out, "rings", &num(u, 0.0, 20.0)?);
            attr(out, "turn", u.choose(&["L", "R"])?);
            out.push('>');
            pts(u, out, lat, lon)?;
            out.push_str("</perimeter>");
        }
        7 if depth < 3 => {
            out.push_str("<iterative");
            attr(out, "id", &format!("it{depth}"));
            attr(out, "count", &num(u, 0.0, 10.0)?);
            out.push('>');
            for _ in 0..u.int_in_range(0u8..=3)? {
                element(u, out, fixes, depth + 1, (lat, lon))?;
            }
            out.push_str("</iterative>");
        }
        8 if depth < 3 => {
            out.push_str("<alternative");
            attr(out, "id", &format!("alt{depth}"));
            out.push_str("><when");
            attr(
                out,
                "cond",
                pick(
                    u,
                    &["inspect", "laps &gt; 1", "inspect and laps &gt; 0"],
                    "nope +",
                )?,
            );
            out.push('>');
            for _ in 0..u.int_in_range(0u8..=3)? {
                element(u, out, fixes, depth + 1, (lat, lon))?;
            }
            out.push_str("</when><otherwise>");
            for _ in 0..u.int_in_range(0u8..=2)? {
                element(u, out, fixes, depth + 1, (lat, lon))?;
            }
            out.push_str("</otherwise></alternative>");
        }
        _ => leg(u, out, fixes)?,
    }
    Ok(())
}

/// A plan document: well formed and mostly valid.
pub fn plan(u: &mut Unstructured<'_>) -> Result<String> {
    let (lat, lon) = (41.275, 1.987);
    BENT.with(|b| b.set(false));
    let bend = u.ratio(1u8, 4)?;
    BENT.with(|b| b.set(bend));
    let mut out = String::with_capacity(4096);
    out.push_str(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<flightPlan name=\"fuzz\" version=\"1\"",
    );
    if u.arbitrary()? {
        attr(&mut out, "vehicle", pick(u, &["rover"], "boat")?);
    }
    attr(&mut out, "altRef", pick(u, &["REL", "MSL"], "AGL?")?);
    attr(&mut out, "defaultSpeed", &num(u, 0.5, 30.0)?);
    out.push_str(">\n<variables>");
    out.push_str("<var name=\"inspect\" type=\"bool\" init=\"false\"/>");
    out.push_str("<var name=\"laps\" type=\"number\"");
    attr(&mut out, "init", &num(u, 0.0, 5.0)?);
    out.push_str("/></variables>\n<fixes>");
    let fixes = u.int_in_range(2usize..=40)?;
    for i in 0..fixes {
        out.push_str("<fix");
        attr(&mut out, "id", &format!("F{i}"));
        attr(&mut out, "lat", &num(u, lat - 0.02, lat + 0.02)?);
        attr(&mut out, "lon", &num(u, lon - 0.02, lon + 0.02)?);
        attr(&mut out, "alt", &num(u, 0.0, 300.0)?);
        out.push_str("/>");
    }
    out.push_str("</fixes>\n<departure><leg type=\"IF\" fix=\"F0\"/>");
    for _ in 0..u.int_in_range(0u8..=3)? {
        leg(u, &mut out, fixes)?;
    }
    out.push_str("</departure>\n<mission>");
    for _ in 0..u.int_in_range(1u8..=12)? {
        element(u, &mut out, fixes, 0, (lat, lon))?;
    }
    out.push_str("</mission>\n<approach>");
    for _ in 0..u.int_in_range(0u8..=3)? {
        leg(u, &mut out, fixes)?;
    }
    out.push_str("</approach>\n");
    if u.arbitrary()? {
        out.push_str("<emergency name=\"low\"");
        attr(&mut out, "on", pick(u, &["laps &lt; 1", "inspect"], "x +")?);
        attr(&mut out, "action", pick(u, &["goto-stage", "land"], "?")?);
        attr(
            &mut out,
            "stage",
            pick(u, &["approach", "mission"], "nowhere")?,
        );
        out.push_str("/>");
    }
    out.push_str("</flightPlan>\n");
    Ok(out)
}

/// XML-level damage: a byte range cut, duplicated or replaced.
fn damage(u: &mut Unstructured<'_>, s: String) -> Result<String> {
    let mut b = s.into_bytes();
    for _ in 0..u.int_in_range(0u8..=3)? {
        if b.is_empty() {
            break;
        }
        let i = u.int_in_range(0..=b.len() - 1)?;
        let j = u.int_in_range(i..=b.len().min(i + 64))?;
        match u.int_in_range(0u8..=2)? {
            0 => {
                b.drain(i..j);
            }
            1 => {
                let piece = b[i..j].to_vec();
                b.splice(j..j, piece);
            }
            _ => b[i] = *u.choose(b"<>/\"=&; \x00\xff")?,
        }
    }
    Ok(String::from_utf8_lossy(&b).into_owned())
}

/// Parses a generated (and maybe damaged) plan for a rover and an aircraft; expands those that
/// parse. Panics when a property fails.
pub fn plan_xml(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let Ok(doc) = plan(&mut u) else { return };
    let doc = if u.ratio(1u8, 3).unwrap_or(false) {
        match damage(&mut u, doc) {
            Ok(d) => d,
            Err(_) => return,
        }
    } else {
        doc
    };
    for vehicle in [VehicleParams::rover(), VehicleParams::aircraft()] {
        if let Ok(checked) = load(&doc, &vehicle) {
            let wps = checked.nominal();
            assert!(wps.len() <= 1_000_000, "expansion past its limit");
            for w in wps.iter() {
                assert!(
                    w.lat.is_finite()
                        && w.lon.is_finite()
                        && w.alt.is_finite()
                        && w.speed.is_finite(),
                    "non-finite waypoint {w:?} from\n{doc}"
                );
                assert!(
                    w.lat.abs() <= 90.0 && w.lon.abs() <= 180.0,
                    "waypoint out of range {w:?} from\n{doc}"
                );
            }
        }
    }
}

/// Whether the undamaged plan generated from `data` parses for a rover (`None` when `data` is
/// too short to make one): the generator's aim is plans that mostly do.
pub fn generated_plan_parses(data: &[u8]) -> Option<Result<(), String>> {
    let doc = plan(&mut Unstructured::new(data)).ok()?;
    Some(
        load(&doc, &VehicleParams::rover())
            .map(|_| ())
            .map_err(|e| format!("{e}")),
    )
}

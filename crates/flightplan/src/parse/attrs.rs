//! Reading one element's attributes as the format's values (numbers, booleans, fixes, turns,
//! conditions), each error at the attribute or element at fault.

use super::error::{PlanError, PlanErrorKind, Result};
use crate::expr::{Condition, ExprError, ValueType};
use crate::geo::GeoPoint;
use crate::model::*;
use crate::xml::{Attr, Element};
use std::collections::BTreeSet;

pub(super) fn node(el: &Element, id: String, kind: NodeKind) -> Node {
    Node {
        id,
        line: el.pos.line,
        col: el.pos.col,
        kind,
        source: Some(el.clone()),
    }
}

pub(super) fn node_id(el: &Element, auto: &str, ids: &mut BTreeSet<String>) -> Result<String> {
    let (id, pos) = match el.attr("id") {
        Some(a) => (a.value.clone(), a.pos),
        None => (auto.to_string(), el.pos),
    };
    if id.is_empty() {
        return Err(PlanError::at(
            pos,
            PlanErrorKind::Structure("an id cannot be empty".into()),
        ));
    }
    if !ids.insert(id.clone()) {
        return Err(PlanError::at(pos, PlanErrorKind::DuplicateId(id)));
    }
    Ok(id)
}

pub(super) fn is_identifier(s: &str) -> bool {
    let mut c = s.chars();
    c.next().is_some_and(|f| f.is_alphabetic() || f == '_')
        && c.all(|ch| ch.is_alphanumeric() || ch == '_' || ch == '.')
        && !matches!(s, "and" | "or" | "not" | "true" | "false")
}

pub(super) fn unknown_element(el: &Element, parent: &Element) -> PlanError {
    PlanError::at(
        el.pos,
        PlanErrorKind::UnknownElement {
            name: el.name.clone(),
            parent: parent.name.clone(),
        },
    )
}

pub(super) fn allow(el: &Element, allowed: &[&str]) -> Result<()> {
    for a in &el.attrs {
        if !allowed.contains(&a.name.as_str()) {
            return Err(PlanError::at(
                a.pos,
                PlanErrorKind::UnknownAttribute {
                    name: a.name.clone(),
                    element: el.name.clone(),
                },
            ));
        }
    }
    Ok(())
}

pub(super) fn no_children(el: &Element) -> Result<()> {
    match el.children.first() {
        Some(c) => Err(unknown_element(c, el)),
        None => Ok(()),
    }
}

pub(super) fn req<'a>(el: &'a Element, name: &str) -> Result<&'a Attr> {
    el.attr(name).ok_or_else(|| {
        PlanError::at(
            el.pos,
            PlanErrorKind::MissingAttribute {
                name: name.into(),
                element: el.name.clone(),
            },
        )
    })
}

pub(super) fn bad_value(a: &Attr, v: &str, why: &str) -> PlanError {
    PlanError::at(
        a.pos,
        PlanErrorKind::BadValue {
            name: a.name.clone(),
            value: v.to_string(),
            why: why.to_string(),
        },
    )
}

pub(super) fn number(a: &Attr) -> Result<f64> {
    a.value
        .trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| {
            PlanError::at(
                a.pos,
                PlanErrorKind::BadNumber {
                    name: a.name.clone(),
                    value: a.value.clone(),
                },
            )
        })
}

pub(super) fn opt_num(el: &Element, name: &str) -> Result<Option<f64>> {
    el.attr(name).map(number).transpose()
}

pub(super) fn req_num(el: &Element, name: &str) -> Result<f64> {
    number(req(el, name)?)
}

pub(super) fn opt_pos_num(el: &Element, name: &str) -> Result<Option<f64>> {
    match el.attr(name) {
        None => Ok(None),
        Some(a) => {
            let v = number(a)?;
            if v <= 0.0 {
                return Err(bad_value(a, &a.value, "must be greater than zero"));
            }
            Ok(Some(v))
        }
    }
}

/// The altitudes a plan may give, metres (MSL, above home or above ground): from below the
/// lowest shore on Earth to above any small aircraft's ceiling. A value outside is a typo.
const ALTITUDES_M: std::ops::RangeInclusive<f64> = -500.0..=20_000.0;
/// The fastest a plan may ask any vehicle to go, m/s.
const FASTEST_MPS: f64 = 150.0;

/// An altitude, checked against [`ALTITUDES_M`].
pub(super) fn opt_alt(el: &Element, name: &str) -> Result<Option<f64>> {
    match el.attr(name) {
        None => Ok(None),
        Some(a) => {
            let v = number(a)?;
            if !ALTITUDES_M.contains(&v) {
                return Err(bad_value(
                    a,
                    &a.value,
                    &format!(
                        "is not an altitude a vehicle flies ({} to {} m)",
                        ALTITUDES_M.start(),
                        ALTITUDES_M.end()
                    ),
                ));
            }
            Ok(Some(v))
        }
    }
}

/// A speed: greater than zero and at most [`FASTEST_MPS`].
pub(super) fn opt_speed(el: &Element, name: &str) -> Result<Option<f64>> {
    let v = opt_pos_num(el, name)?;
    if let (Some(v), Some(a)) = (v, el.attr(name)) {
        if v > FASTEST_MPS {
            return Err(bad_value(
                a,
                &a.value,
                &format!("is faster than any vehicle flies a plan (at most {FASTEST_MPS} m/s)"),
            ));
        }
    }
    Ok(v)
}

pub(super) fn req_pos_num(el: &Element, name: &str) -> Result<f64> {
    req(el, name)?;
    opt_pos_num(el, name).map(|v| v.unwrap_or_default())
}

pub(super) fn opt_u32(el: &Element, name: &str) -> Result<Option<u32>> {
    el.attr(name)
        .map(|a| {
            a.value
                .trim()
                .parse::<u32>()
                .map_err(|_| bad_value(a, &a.value, "is not a whole number"))
        })
        .transpose()
}

pub(super) fn opt_bool(el: &Element, name: &str) -> Result<Option<bool>> {
    el.attr(name)
        .map(|a| match a.value.trim() {
            "true" | "1" | "yes" => Ok(true),
            "false" | "0" | "no" => Ok(false),
            v => Err(bad_value(a, v, "must be true or false")),
        })
        .transpose()
}

pub(super) fn lat_lon(el: &Element, lat: &str, lon: &str) -> Result<GeoPoint> {
    let la = req(el, lat)?;
    let lo = req(el, lon)?;
    let (y, x) = (number(la)?, number(lo)?);
    if !(-90.0..=90.0).contains(&y) {
        return Err(bad_value(la, &la.value, "is not a latitude (-90..90)"));
    }
    if !(-180.0..=180.0).contains(&x) {
        return Err(bad_value(lo, &lo.value, "is not a longitude (-180..180)"));
    }
    Ok(GeoPoint::new(y, x))
}

pub(super) fn point(el: &Element) -> Result<GeoPoint> {
    lat_lon(el, "lat", "lon")
}

pub(super) fn fix_ref(el: &Element, plan: &FlightPlan) -> Result<Fix> {
    let a = req(el, "fix")?;
    plan.fixes
        .get(&a.value)
        .cloned()
        .ok_or_else(|| PlanError::at(a.pos, PlanErrorKind::UnknownFix(a.value.clone())))
}

pub(super) fn center(el: &Element, plan: &FlightPlan) -> Result<Option<GeoPoint>> {
    if let Some(a) = el.attr("center") {
        return plan
            .fixes
            .get(&a.value)
            .map(|f| Some(f.pos))
            .ok_or_else(|| PlanError::at(a.pos, PlanErrorKind::UnknownFix(a.value.clone())));
    }
    if el.attr("centerLat").is_some() || el.attr("centerLon").is_some() {
        return lat_lon(el, "centerLat", "centerLon").map(Some);
    }
    Ok(None)
}

pub(super) fn turn(el: &Element) -> Result<Option<Turn>> {
    el.attr("turn")
        .map(|a| match a.value.as_str() {
            "R" | "r" | "right" => Ok(Turn::R),
            "L" | "l" | "left" => Ok(Turn::L),
            v => Err(bad_value(a, v, "must be R or L")),
        })
        .transpose()
}

pub(super) fn common(el: &Element, with_fly_over: bool) -> Result<LegCommon> {
    Ok(LegCommon {
        alt: opt_alt(el, "alt")?,
        speed: opt_speed(el, "speed")?,
        fly_over: if with_fly_over {
            opt_bool(el, "flyOver")?
        } else {
            None
        },
    })
}

pub(super) fn condition(a: &Attr, plan: &FlightPlan) -> Result<Condition> {
    let at = |e: ExprError| PlanError::at(a.pos, PlanErrorKind::Condition(e));
    let c = Condition::parse(&a.value).map_err(at)?;
    match c.expr.check(&|n| plan.var_type(n)).map_err(at)? {
        ValueType::Bool => Ok(c),
        ValueType::Number => Err(at(ExprError::NotBoolean)),
    }
}

//! What a plan file holds, loaded and checked for a vehicle: a USAL flight plan (XML), or a
//! QGroundControl `.plan` (JSON), imported; anything else named for what it is. The one reading
//! of plan files: the FPMa's loads and `fpma expand` both use it.

use crate::check::{self, CheckError, CheckedPlan};
use crate::qgc;
use crate::vehicle::VehicleParams;

/// Why a plan file cannot be flown, as a message naming the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanFileError {
    /// Not a plan, a plan that does not parse, or one that does not suit the vehicle:
    /// `file:line:col: what` where a position is known.
    #[error("{0}")]
    Refused(String),
    /// A plan that never ends.
    #[error("{0}")]
    Endless(String),
}

/// Loads `text`, the content of the file named `source`, and checks it for `vehicle`: a
/// QGroundControl plan when `source` ends in `.plan` or the text is JSON (a QGC plan has
/// `"fileType": "Plan"`; other JSON is refused for what it is), else a USAL flight plan.
///
/// # Errors
/// [`PlanFileError::Refused`] naming the file and, for XML, the line and column;
/// [`PlanFileError::Endless`] for a plan that never ends.
pub fn load(
    text: &str,
    source: &str,
    vehicle: &VehicleParams,
) -> Result<CheckedPlan, PlanFileError> {
    let json = text.trim_start().starts_with(['{', '[']);
    let named_qgc = source.ends_with(".plan");
    let checked = if named_qgc || json {
        let stem = source.strip_suffix(".plan").unwrap_or(source);
        let (plan, _xml) = qgc::import(text, stem).map_err(|e| match e {
            // JSON that is no QGC plan, in a file not named as one: named for what it is.
            qgc::QgcImportError::NotAPlan(_) if !named_qgc => PlanFileError::Refused(format!(
                "{source}: holds JSON, not a flight plan (a USAL flight plan is XML, \
                 <flightPlan>; a QGroundControl plan has \"fileType\": \"Plan\")"
            )),
            e => PlanFileError::Refused(format!("{source}: {e}")),
        })?;
        check::check(plan, vehicle)
    } else {
        check::load(text, vehicle)
    };
    checked.map_err(|e| match e {
        CheckError::Plan(_) => PlanFileError::Refused(e.in_file(source)),
        CheckError::Endless(_) => PlanFileError::Endless(e.in_file(source)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const XML: &str = r#"<flightPlan name="p"><fixes><fix id="A" lat="41.275" lon="1.987"/>
      <fix id="B" lat="41.2754" lon="1.987"/></fixes>
      <mission><leg type="IF" fix="A"/><leg type="TF" fix="B"/></mission></flightPlan>"#;

    #[test]
    fn a_qgc_plan_is_imported_by_its_name_or_its_content() {
        let rover = VehicleParams::rover();
        let plan = check::load(XML, &rover).unwrap();
        let doc = serde_json::to_string(&qgc::export(plan.plan(), &rover).unwrap()).unwrap();
        for name in ["p.plan", "p.json", "p"] {
            let got = load(&doc, name, &rover).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(got.nominal().len(), plan.nominal().len(), "{name}");
        }
        assert_eq!(load(XML, "p.xml", &rover).unwrap().nominal().len(), 2);
    }

    #[test]
    fn other_json_is_named_for_what_it_is_and_a_bad_plan_keeps_its_position() {
        let rover = VehicleParams::rover();
        let e = load(r#"{"fileType": "Mission", "items": []}"#, "x.json", &rover).unwrap_err();
        assert!(
            matches!(&e, PlanFileError::Refused(m) if m.starts_with("x.json: holds JSON, not a flight plan")),
            "{e}"
        );
        let bad = XML.replace(r#"fix="B"/></mission>"#, r#"fix="NOPE"/></mission>"#);
        let e = load(&bad, "bad.xml", &rover).unwrap_err();
        assert!(
            matches!(&e, PlanFileError::Refused(m) if m.starts_with("bad.xml:3:") && m.contains("NOPE")),
            "{e}"
        );
    }
}

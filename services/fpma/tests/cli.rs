//! `fpma expand` run as a child process, on the example plan and on a malformed one.

use std::ffi::{OsStr, OsString};
use std::process::Command;

fn fpma() -> Command {
    Command::new(env!("CARGO_BIN_EXE_fpma"))
}

/// Runs `fpma` with `args`, which must succeed; returns its standard output.
fn fpma_ok<S: AsRef<OsStr>>(args: &[S]) -> String {
    let out = fpma().args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

const ROVER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../config/flightplans/rover-carpark.xml"
);

#[test]
fn expand_prints_one_json_waypoint_per_line() {
    // No --vehicle: the plan says it is for a rover.
    let text = fpma_ok(&["expand", ROVER]);
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(lines.len() > 20);
    for l in &lines {
        for k in ["lat", "lon", "alt", "speed"] {
            assert!(l[k].is_f64(), "{k} in {l}");
        }
        assert!(l["fly_over"].is_boolean() && l["leg"].is_string());
    }
    assert_eq!(lines[0]["leg"], "departure.1");
    assert!((lines[0]["lat"].as_f64().unwrap() - 41.275).abs() < 1e-9);
    assert!(lines.iter().any(|l| l["leg"] == "area"));
    // The HM hold waits for `inspect`: shown for one circuit, marked.
    let waiting: Vec<_> = lines.iter().filter(|l| l["waits"] == true).collect();
    assert_eq!(waiting.len(), 5);
    assert!(waiting.iter().all(|l| l["leg"] == "wait"));
    assert_eq!(lines.last().unwrap()["leg"], "approach.2");
}

#[test]
fn malformed_plan_exits_2_naming_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.xml");
    std::fs::write(
        &path,
        "<flightPlan>\n  <fixes><fix id=\"A\" lat=\"41\" lon=\"2\"/></fixes>\n  <mission>\n    <leg type=\"TF\" fix=\"B\"/>\n  </mission>\n</flightPlan>\n",
    )
    .unwrap();
    let out = fpma().args(["expand"]).arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("bad.xml:4:20: unknown fix `B`"), "{err}");
    assert!(out.stdout.is_empty());

    std::fs::write(
        &path,
        "<flightPlan>\n<mission>\n<leg type=\"TF\" fix=\"A\">\n</flightPlan>\n",
    )
    .unwrap();
    let out = fpma().args(["expand"]).arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("bad.xml:4:"), "{err}");
}

#[test]
fn a_plan_for_another_vehicle_or_bad_overrides_are_refused() {
    let out = fpma()
        .args(["expand", ROVER, "--vehicle", "aircraft"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("rover-carpark.xml:6:") && err.contains("written for vehicle `rover`"),
        "{err}"
    );
    let out = fpma()
        .args(["expand", ROVER, "--min-wp-distance=-3"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("minWaypointDistance must be a positive"),
        "{err}"
    );
}

#[test]
fn vehicle_overrides_shape_the_stream() {
    // Fixes north of A at 0, 3.3, 10, 16.7 and 26.7 m; no speeds anywhere.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("line.xml");
    let fixes: String = [0, 3, 9, 15, 24]
        .iter()
        .map(|k| {
            format!(
                r#"<fix id="F{k}" lat="{}" lon="2"/>"#,
                41.0 + f64::from(*k) * 1e-5
            )
        })
        .collect();
    let legs: String = [0, 3, 9, 15, 24]
        .iter()
        .map(|k| format!(r#"<leg type="TF" fix="F{k}"/>"#))
        .collect();
    std::fs::write(
        &path,
        format!(r#"<flightPlan vehicle="rover"><fixes>{fixes}</fixes><mission>{legs}</mission></flightPlan>"#),
    )
    .unwrap();
    let stream = |extra: &[&str]| -> Vec<serde_json::Value> {
        let mut args = vec![OsString::from("expand"), path.clone().into()];
        args.extend(extra.iter().map(Into::into));
        fpma_ok(&args)
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let lat = |ws: &[serde_json::Value]| -> Vec<i64> {
        ws.iter()
            .map(|w| ((w["lat"].as_f64().unwrap() - 41.0) * 1e5).round() as i64)
            .collect()
    };
    // The rover's 4.5 m drops the point 3.3 m on; 8 m also drops the one 6.7 m after 10 m.
    let normal = stream(&[]);
    assert_eq!(lat(&normal), [0, 9, 15, 24]);
    assert!(
        normal.iter().all(|w| w["speed"] == 2.0),
        "the rover's default speed"
    );
    let sparse = stream(&["--min-wp-distance", "8", "--default-speed", "0.5"]);
    assert_eq!(lat(&sparse), [0, 9, 24]);
    assert!(sparse.iter().all(|w| w["speed"] == 0.5));
}

#[test]
fn qgc_export_writes_a_plan_file_and_refusals_give_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let demo = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/flightplans/rover-demo.xml"
    );
    let out_plan = dir.path().join("demo.plan");
    let printed = fpma_ok(&[
        OsStr::new("expand"),
        OsStr::new(demo),
        OsStr::new("--qgc"),
        out_plan.as_os_str(),
    ])
    .lines()
    .count();
    let text = std::fs::read_to_string(&out_plan).unwrap();
    let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(doc["fileType"], "Plan");
    let items = doc["mission"]["items"].as_array().unwrap();
    assert!(items.iter().any(|i| i["complexItemType"] == "survey"));
    assert!(
        items.iter().any(|i| i["command"] == 177),
        "the laps loop is a DO_JUMP"
    );
    // Read back, it flies the same stream the preview printed.
    let v = flightplan::vehicle::VehicleParams::rover();
    let (plan, _) = flightplan::qgc::import(&text, "demo").unwrap();
    let checked = flightplan::check::check(plan, &v).unwrap();
    assert_eq!(checked.nominal().len(), printed);
    // `fpma expand` reads the exported plan itself (imported by its name), the same stream.
    let expanded = fpma_ok(&[
        OsStr::new("expand"),
        out_plan.as_os_str(),
        OsStr::new("--vehicle"),
        OsStr::new("rover"),
    ]);
    assert_eq!(expanded.lines().count(), printed);
    // JSON that is no QGroundControl plan is named for what it is, briefly.
    let other = dir.path().join("other.json");
    std::fs::write(&other, format!("{{\"items\": [{}0]}}", "1, ".repeat(3000))).unwrap();
    let out = fpma().arg("expand").arg(&other).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("holds JSON, not a flight plan") && err.len() < 300,
        "{err}"
    );

    // The car-park plan waits for a variable and has an emergency rule: refused, with why.
    let refused = dir.path().join("carpark.plan");
    let out = fpma()
        .args(["expand", ROVER, "--qgc"])
        .arg(&refused)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("`low-battery` cannot be exported to QGroundControl")
            && err.contains("emergency rules react to conditions"),
        "{err}"
    );
    assert!(!refused.exists(), "nothing written when refused");
    assert!(out.stdout.is_empty());
}

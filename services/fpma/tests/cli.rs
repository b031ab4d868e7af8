//! `fpma expand` run as a child process, on the example plan and on a malformed one.

use std::process::Command;

fn fpma() -> Command {
    Command::new(env!("CARGO_BIN_EXE_fpma"))
}

const ROVER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../config/flightplans/rover-carpark.xml"
);

#[test]
fn expand_prints_one_json_waypoint_per_line() {
    let out = fpma()
        .args(["expand", ROVER, "--vehicle", "rover"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
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

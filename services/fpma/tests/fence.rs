//! The plan's geofence through the processes: `fpma run` + `vas` + `mavsim`. A plan one of
//! whose legs crosses its `<fence>` is refused with the leg's line and column; the same plan
//! without that leg loads, its fence reaches the autopilot (mavsim logs the polygon it
//! received), and a change that would cross the fence is refused in flight.

use std::time::Duration;

use flightplan::api::{CommandAck, PlanLoaded};
use tokio::time::{timeout, Instant};
use usal_types::FlightState;

mod common;
use common::{ground, kill, start_fpma, start_mavsim, start_vas};

const STEP: Duration = Duration::from_secs(30);
const HOME: (f64, f64) = (41.275, 1.987);

/// A rover plan 40 m north and back inside a 60 m fence (a square polygon and a circle); the
/// leg `far` (line 11) goes 120 m north, outside.
fn plan(with_far: bool) -> String {
    let far = if with_far {
        r#"<leg id="far" type="TF" fix="FAR"/>"#
    } else {
        ""
    };
    let d = 0.0006; // about 66 m of latitude
    format!(
        r#"<flightPlan name="fenced" vehicle="rover" altRef="REL" defaultSpeed="2">
  <fixes>
    <fix id="HOME" lat="{h0}" lon="{h1}" alt="0"/>
    <fix id="N" lat="{n}" lon="{h1}" alt="0"/>
    <fix id="FAR" lat="{f}" lon="{h1}" alt="0"/>
  </fixes>
  <mission>
    <leg type="IF" fix="HOME"/>
    <leg id="north" type="TF" fix="N"/>
    <leg id="back" type="TF" fix="HOME"/>
    {far}
  </mission>
  <fence maxDistance="60" maxHeight="20" action="hold">
    <pt lat="{s}" lon="{w}"/><pt lat="{nn}" lon="{w}"/><pt lat="{nn}" lon="{e}"/><pt lat="{s}" lon="{e}"/>
  </fence>
</flightPlan>"#,
        h0 = HOME.0,
        h1 = HOME.1,
        n = HOME.0 + 0.00036, // 40 m
        f = HOME.0 + 0.00108, // 120 m
        s = HOME.0 - d,
        nn = HOME.0 + d,
        w = HOME.1 - d,
        e = HOME.1 + d,
    )
}

async fn run() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let domain = format!("fpma-fence-{}", std::process::id());
    let home = format!("{},{},0", HOME.0, HOME.1);
    let (sim, addr) = start_mavsim(&[
        "--home",
        &home,
        "--speedup",
        "10",
        "--log",
        log.to_str().unwrap(),
    ])
    .await;
    let vas = start_vas(&addr, &domain, &[]);
    let fpma = start_fpma(
        &domain,
        "rover",
        &dir.path().join("plans"),
        &dir.path().join("state"),
        &[],
    );
    let node = ground(&domain).await;
    let gcs = node.service("fpmo").unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    let insert = gcs
        .function::<String, CommandAck>("rover1/fpma/insert_legs")
        .unwrap();
    let flight_state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    timeout(STEP, async {
        while flight_state.recv().await.expect("flight_state").value != FlightState::Parking {}
    })
    .await
    .expect("the VAS reached PARKING");

    // The leg `far` leaves the fence: refused at its line and column, nothing flown.
    let e = load.call(&plan(true), STEP).await.unwrap_err().to_string();
    assert!(
        e.contains(":11:5: leg `far` leaves the fence") && e.contains("m from home (fence: 60 m)"),
        "{e}"
    );

    // Without it, the plan loads and its fence reaches the autopilot.
    load.call(&plan(false), STEP)
        .await
        .expect("the fenced plan loads");
    let deadline = Instant::now() + STEP;
    let uploaded = loop {
        let up: Vec<serde_json::Value> = std::fs::read_to_string(&log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .filter(|r: &serde_json::Value| r["event"] == "fence_uploaded")
            .collect();
        if let Some(last) = up.last() {
            break last.clone();
        }
        assert!(Instant::now() < deadline, "mavsim got no fence");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(uploaded["vertices"], 4, "{uploaded}");

    // A change crossing the fence is refused, in flight.
    let e = insert
        .call(&r#"<leg type="TF" fix="FAR"/>"#.to_owned(), STEP)
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("leaves the fence"), "{e}");

    drop(node);
    for c in [sim, vas, fpma] {
        kill(c).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plan_crossing_its_fence_is_refused_and_a_fenced_plan_uploads_its_fence() {
    timeout(Duration::from_secs(180), run())
        .await
        .expect("the test took too long");
}

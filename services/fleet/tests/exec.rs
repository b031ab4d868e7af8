//! The executor's statements on a real node (loopback, a domain of its own), with no vehicle
//! to command: loops, choices, variables, sync points inside a `par`, waits on conditions, and
//! a wait that times out failing the plan with its line and column. The plan's end is read
//! from the service's `status` variable, as the launcher and the stations read it.

use std::path::Path;
use std::time::Duration;

use flightplan::api::VarValue;
use flightplan::fleet_api::FleetStatus;
use tokio_util::sync::CancellationToken;

/// Runs `plan` (the statements inside a `<seq>`) and returns its final status. With `alarm`,
/// vehicle `a`'s VAS is played by this test: it raises that `alarm` text every 200 ms.
async fn run_plan(tag: &str, vars: &str, body: &str) -> FleetStatus {
    run_plan_with(tag, vars, body, None).await
}

async fn run_plan_with(
    tag: &str,
    vars: &str,
    body: &str,
    detection: Option<usal_types::PoiDetection>,
) -> FleetStatus {
    let src = format!(
        "<fleetPlan name=\"{tag}\">\n<vehicle id=\"a\" prefix=\"nobody-{tag}\"/>\n<variables>{vars}</variables>\n<seq>\n{body}\n</seq>\n</fleetPlan>"
    );
    let plan = fleet::plan::parse(&src, Path::new(".")).unwrap_or_else(|e| panic!("{e}"));
    let domain = format!("fleet-exec-{tag}-{}", std::process::id());
    let mut config = fleet::FleetConfig::new(plan);
    config.domain = Some(domain.clone());
    config.namespace = Some("gcs".into());
    config.node = format!("fleet-{tag}");
    let stop = CancellationToken::new();
    let service = tokio::spawn(fleet::run(config, stop.clone()));

    let net = marea::NetworkConfig::for_service(None, "watcher", Some(&domain), None).unwrap();
    let node = marea::Node::open(&net).await.unwrap();
    let sub = node
        .service("watcher")
        .unwrap()
        .subscribe_variable::<FleetStatus>("gcs/fleet/status")
        .unwrap();
    // The vehicle's VAS, as far as detections go: a node in its namespace.
    let vas_net = marea::NetworkConfig::for_service(
        None,
        "vas",
        Some(&domain),
        Some(&format!("nobody-{tag}")),
    )
    .unwrap();
    let vas_node = marea::Node::open(&vas_net).await.unwrap();
    let detections = vas_node
        .service("vas")
        .unwrap()
        .publish_event::<usal_types::PoiDetection>("detection")
        .unwrap();
    let detections = std::sync::Arc::new(detections);
    // Raised once the plan waits for an event, so the wait cannot miss it.
    let mut raising = None;
    let end = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            let s = sub.recv().await.expect("status").value;
            if let Some(d) = detection.clone().filter(|_| raising.is_none()) {
                if s.doing.iter().any(|d| d.contains("wait for")) {
                    let detections = detections.clone();
                    raising = Some(tokio::spawn(async move {
                        loop {
                            let _ = detections.raise(&d).await;
                            tokio::time::sleep(Duration::from_millis(200)).await;
                        }
                    }));
                }
            }
            if s.done || s.failed.is_some() {
                return s;
            }
        }
    })
    .await
    .expect("the plan did not end within 30 s");
    if let Some(r) = raising {
        r.abort();
    }
    stop.cancel();
    tokio::time::timeout(Duration::from_secs(10), service)
        .await
        .expect("the service did not stop")
        .expect("service task")
        .expect("service");
    node.shutdown().await;
    vas_node.shutdown().await;
    end
}

fn var(s: &FleetStatus, name: &str) -> VarValue {
    s.vars
        .iter()
        .find(|(n, _)| n == name)
        .unwrap_or_else(|| panic!("no {name} in {:?}", s.vars))
        .1
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loops_choices_variables_and_sync_points_run_in_order() {
    let s = run_plan(
        "blocks",
        r#"<var name="n" type="number" init="0"/><var name="ok" type="bool" init="false"/>
           <var name="left" type="number" init="0"/><var name="right" type="number" init="0"/>"#,
        r#"<repeat count="3"><set var="n" add="1"/></repeat>
<if cond="n == 3"><then><set var="ok" value="true"/></then><else><set var="ok" value="false"/></else></if>
<par>
  <seq><sync name="s"/><set var="left" add="1"/><sync name="t"/><set var="left" value="right"/></seq>
  <seq><wait until="n == 3"/><sync name="s"/><set var="right" add="7"/><sync name="t"/></seq>
</par>
<repeat until="n >= 5"><set var="n" add="1"/></repeat>
<repeat while="n < 5"><set var="n" add="100"/></repeat>
<wait until="n == 5 and ok" timeoutS="5"/>
<log text="done"/>"#,
    )
    .await;
    assert!(s.done, "{s:?}");
    assert_eq!(s.failed, None);
    assert_eq!(var(&s, "n"), VarValue::Number(5.0));
    assert_eq!(var(&s, "ok"), VarValue::Bool(true));
    // `left` read `right` after both passed the second sync point: 7, never 0.
    assert_eq!(var(&s, "left"), VarValue::Number(7.0));
    assert!(s.doing.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wait_past_its_time_fails_the_plan_naming_the_statement() {
    let s = run_plan(
        "timeout",
        r#"<var name="n" type="number" init="0"/>"#,
        r#"<set var="n" add="1"/>
<wait until="n == 2" timeoutS="0.5"/>
<set var="n" add="1"/>"#,
    )
    .await;
    assert!(!s.done);
    let f = s.failed.clone().unwrap();
    assert!(
        f.contains("line 6:1 <wait>: `n == 2`: not within 0.5 s"),
        "{f}"
    );
    assert_eq!(
        var(&s, "n"),
        VarValue::Number(1.0),
        "nothing after the failure ran"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_detection_event_of_the_vas_ends_a_wait_for_detections_once() {
    let s = run_plan_with(
        "detect",
        r#"<var name="seen" type="bool" init="false"/>"#,
        r#"<wait event="detection" vehicle="a" timeoutS="20"/>
<wait until="detections == 1 and pending == 1 and visited == 0" timeoutS="5"/>
<set var="seen" value="true"/>"#,
        Some(usal_types::PoiDetection {
            id: 3,
            lat: 41.275_123_4,
            lon: 1.987_123_4,
            confidence: 0.8,
            by: "nobody-detect".into(),
        }),
    )
    .await;
    assert!(s.done, "{s:?}");
    assert_eq!(var(&s, "seen"), VarValue::Bool(true));
    // Raised again and again, kept once.
    assert_eq!(s.detections.len(), 1, "{:?}", s.detections);
    let d = &s.detections[0];
    assert_eq!((d.id, d.by.as_str(), d.visited.is_none()), (3, "a", true));
    assert_eq!(d.confidence, 0.8);
    assert!((d.lat - 41.275_123_4).abs() < 1e-9 && (d.lon - 1.987_123_4).abs() < 1e-9);
}

//! The `fmo` binary over HTTP against a stand-in fleet: a marea node in the test process that
//! publishes two VASes' items (`rover1/vas/...`, `rover2/vas/...`), provides their
//! `change_state` and `allowed_states`, and listens to `**/fmo/manual_control`.

mod common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use marea::{NetworkConfig, Node};
use usal_types::{
    Alarm, AutopilotStatus, FlightState, ManualCommand, Position, Severity, StateChangeReply,
    StateChangeRequest,
};

/// A fake VAS: its state, the transitions it accepts, and the items it publishes.
struct FakeVas {
    state: Arc<Mutex<FlightState>>,
    flight_state: marea::Variable<FlightState>,
    _position: Arc<marea::Variable<Position>>,
    ticker: tokio::task::JoinHandle<()>,
    alarm: marea::Event<Alarm>,
    _autopilot: marea::Variable<AutopilotStatus>,
    _providers: Vec<marea::FunctionProvider>,
}

/// The fake table: PARKING ⇄ DIRECTED ⇄ MANUAL_NAVIGATION, MANUAL from anywhere.
fn allowed_from(s: FlightState) -> Vec<FlightState> {
    use FlightState::*;
    match s {
        Parking => vec![Directed, Manual],
        Directed => vec![Parking, ManualNavigation, Manual],
        ManualNavigation => vec![Directed, Manual],
        _ => vec![],
    }
}

fn fake_vas(node: &Node) -> FakeVas {
    let svc = node.service("vas").unwrap();
    let state = Arc::new(Mutex::new(FlightState::Parking));
    let flight_state = svc.publish_variable::<FlightState>("flight_state").unwrap();
    flight_state.set(&FlightState::Parking).unwrap();
    let position = Arc::new(svc.publish_variable::<Position>("position").unwrap());
    // Telemetry at 5 Hz, as a VAS publishes it: the station's link health depends on it.
    let pos = position.clone();
    let ticker = tokio::spawn(async move {
        let mut p = Position::default();
        loop {
            p.lat += 1e-6;
            let _ = pos.set(&p);
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    });
    let autopilot = svc
        .publish_variable::<AutopilotStatus>("autopilot")
        .unwrap();
    autopilot
        .set(&AutopilotStatus {
            connected: true,
            armed: true,
            mode: "HOLD".into(),
            mode_number: 4,
            system_status: "ACTIVE".into(),
        })
        .unwrap();
    let alarm = svc.publish_event::<Alarm>("alarm").unwrap();
    let st = state.clone();
    let allowed = svc
        .provide_function("allowed_states", move |(): ()| {
            let s = *st.lock().unwrap();
            async move { Ok(allowed_from(s)) }
        })
        .unwrap();
    let st = state.clone();
    let change = svc
        .provide_function("change_state", move |r: StateChangeRequest| {
            let st = st.clone();
            async move {
                let from = *st.lock().unwrap();
                if !allowed_from(from).contains(&r.to) {
                    return Err(format!("{} is not allowed from {from}", r.to));
                }
                *st.lock().unwrap() = r.to;
                Ok(StateChangeReply { from, to: r.to })
            }
        })
        .unwrap();
    FakeVas {
        state,
        flight_state,
        _position: position,
        ticker,
        alarm,
        _autopilot: autopilot,
        _providers: vec![allowed, change],
    }
}

async fn vehicle_node(domain: &str, ns: &str) -> Node {
    let mut cfg = NetworkConfig::ethernet_loopback(&format!("{ns}-node"));
    cfg.domain = domain.to_owned();
    cfg.namespace = Some(ns.to_owned());
    Node::open(&cfg).await.expect("vehicle node")
}

fn veh<'a>(s: &'a serde_json::Value, label: &str) -> &'a serde_json::Value {
    vehicle(s, label).unwrap_or_else(|| panic!("no {label} in {s:#}"))
}

/// Page, snapshot, SSE, state changes (pending → confirmed / failed with the reason), only the
/// allowed transitions, alarms acknowledged, two vehicles and switching between them, manual
/// control at 20 Hz with the dead-man, and staleness when a vehicle goes silent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn station_against_a_fake_fleet() {
    tokio::time::timeout(Duration::from_secs(120), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let domain = unique_domain("fmo");
    let n1 = vehicle_node(&domain, "rover1").await;
    let v1 = fake_vas(&n1);
    let n2 = vehicle_node(&domain, "rover2").await;
    let v2 = fake_vas(&n2);

    // The vehicles' side of manual control.
    let ground = n1.service("probe").unwrap();
    let sticks = ground
        .subscribe_variable::<ManualCommand>("**/fmo/manual_control")
        .unwrap();

    let fmo = Station::start(
        env!("CARGO_BIN_EXE_fmo"),
        "FMO_URL",
        &[
            "--domain",
            &domain,
            "--stale-ms",
            "1500",
            "--call-timeout-ms",
            "1500",
        ],
    )
    .await;

    // The page is served, self-contained.
    let (status, page) = fmo.get("/").await;
    assert_eq!(status, 200);
    assert!(page.contains("FMo — Flight Monitor"));
    assert!(page.contains("EventSource(\"/api/events\")"));
    // The URL it printed moves its token into a cookie, which then opens the API.
    let (status, _) = request(&fmo.addr, "GET", &fmo.with_token("/"), None).await;
    assert_eq!(status, 303, "the token leaves the URL");
    let port = fmo.addr.rsplit(':').next().unwrap();
    let cookie = format!("Cookie: usal_station_{port}={}\r\n", fmo.token);
    let (status, _) = request_with(&fmo.addr, "GET", "/api/state", None, &cookie).await;
    assert_eq!(status, 200, "the station's cookie");

    // The real binary guards its API: no token, a wrong one, a cross-origin POST refused.
    let (status, _) = request(&fmo.addr, "GET", "/api/state", None).await;
    assert_eq!(status, 401, "no token");
    let (status, _) = request(&fmo.addr, "GET", "/api/state?token=0", None).await;
    assert_eq!(status, 403, "wrong token");
    let (status, _) = request(&fmo.addr, "GET", &fmo.with_token("/api/state"), None).await;
    assert_eq!(status, 200, "token in the query");
    let cross = format!(
        "Origin: http://evil.example\r\nX-Station-Token: {}\r\n",
        fmo.token
    );
    let body = r#"{"to": "DIRECTED"}"#;
    let (status, _) =
        request_with(&fmo.addr, "POST", "/api/change_state", Some(body), &cross).await;
    assert_eq!(status, 403, "cross-origin POST");
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "no internet resources"
    );

    // Both vehicles appear; the first heard is commanded; PARKING offers DIRECTED and MANUAL only.
    let s = fmo
        .wait_state("two vehicles with allowed transitions", |s| {
            vehicle(s, "rover1").is_some()
                && vehicle(s, "rover2").is_some()
                && s["selected"].is_string()
                && s["vehicles"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|v| v["allowed"]["current"] == true)
        })
        .await;
    let sel = s["selected"].as_str().unwrap().to_owned();
    let (status, _) = fmo
        .post("/api/select", serde_json::json!({"vehicle": "rover1/vas"}))
        .await;
    assert_eq!(status, 204);
    let (status, _) = fmo
        .post("/api/select", serde_json::json!({"vehicle": "nope/vas"}))
        .await;
    assert_eq!(status, 404);
    let s = fmo
        .wait_state("rover1 selected with its transitions and telemetry", |s| {
            let r = veh(s, "rover1");
            s["selected"] == "rover1/vas"
                && r["allowed"]["current"] == true
                && r["position"].is_object()
                && r["autopilot"].is_object()
        })
        .await;
    let r1 = veh(&s, "rover1");
    assert_eq!(r1["flight_state"]["value"], "PARKING");
    assert_eq!(r1["autopilot"]["value"]["mode"], "HOLD");
    assert_eq!(r1["link"], "ok");
    assert!(r1["position"]["value"]["lat"].as_f64().unwrap() > 0.0);
    assert_eq!(r1["position"]["stale"], false);
    assert_eq!(
        r1["allowed"]["states"],
        serde_json::json!(["DIRECTED", "MANUAL"]),
        "only the transitions the VAS allows"
    );
    let _ = sel;

    // The live channel carries the same snapshots.
    let mut sse = Sse::open(&fmo.addr, &fmo.with_token("/api/events")).await;
    let ev = sse.next("state").await;
    assert!(vehicle(&ev, "rover1").is_some(), "{ev:#}");

    // A refused change fails with the VAS's reason.
    let (status, body) = fmo
        .post(
            "/api/change_state",
            serde_json::json!({"to": "MANUAL_NAVIGATION"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let id = body["id"].as_u64().unwrap();
    let s = fmo
        .wait_state("the refusal", |s| {
            command(s, id).is_some_and(|c| c["status"] != "pending")
        })
        .await;
    let c = command(&s, id).expect("the command is listed");
    assert_eq!(c["status"], "failed");
    assert_eq!(c["detail"], "MANUAL_NAVIGATION is not allowed from PARKING");

    // An accepted change is confirmed, and the new state's transitions are offered.
    let (status, body) = fmo
        .post("/api/change_state", serde_json::json!({"to": "DIRECTED"}))
        .await;
    assert_eq!(status, 202);
    let id = body["id"].as_u64().unwrap();
    fmo.wait_state("the confirmation", |s| {
        command(s, id).is_some_and(|c| c["status"] == "ok" && c["detail"] == "PARKING → DIRECTED")
    })
    .await;
    v1.flight_state.set(&FlightState::Directed).unwrap();
    let s = fmo
        .wait_state("DIRECTED's transitions", |s| {
            let r = veh(s, "rover1");
            r["flight_state"]["value"] == "DIRECTED" && r["allowed"]["current"] == true
        })
        .await;
    assert_eq!(
        veh(&s, "rover1")["allowed"]["states"],
        serde_json::json!(["PARKING", "MANUAL_NAVIGATION", "MANUAL"])
    );
    let (status, _) = fmo
        .post("/api/change_state", serde_json::json!({"to": "FLYING"}))
        .await;
    assert_eq!(status, 400, "unknown state names are refused");

    // Alarms arrive and are acknowledged.
    v1.alarm
        .raise(&Alarm {
            severity: Severity::Warning,
            text: "battery low".into(),
        })
        .await
        .unwrap();
    let s = fmo
        .wait_state("the alarm", |s| veh(s, "rover1")["unacked_alarms"] == 1)
        .await;
    let aid = veh(&s, "rover1")["alarms"][0]["id"].as_u64().unwrap();
    assert_eq!(veh(&s, "rover1")["alarms"][0]["text"], "battery low");
    let (status, body) = fmo
        .post("/api/alarms/ack", serde_json::json!({"id": aid}))
        .await;
    assert_eq!((status, &body["acked"]), (200, &serde_json::json!(1)));
    fmo.wait_state("the alarm acknowledged", |s| {
        veh(s, "rover1")["unacked_alarms"] == 0
    })
    .await;

    // Manual control: nothing is sent while idle; held sticks at 20 Hz; release = neutral.
    tokio::time::sleep(Duration::from_millis(300)).await;
    while sticks.try_recv().is_some() {}
    let started = tokio::time::Instant::now();
    let mut got = Vec::new();
    while started.elapsed() < Duration::from_millis(1000) {
        let (status, _) = fmo
            .post(
                "/api/manual",
                serde_json::json!({"throttle": 0.5, "roll": -0.25, "deadman": true, "source": "keyboard"}),
            )
            .await;
        assert_eq!(status, 204);
        while let Some(Ok(s)) = sticks.try_recv() {
            got.push(s.value);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        got.iter()
            .any(|c| c.sticks.throttle == 0.5 && c.sticks.roll == -0.25),
        "held sticks reach the vehicle: {got:?}"
    );
    assert!(
        got.iter().all(|c| c.target == "rover1/vas"),
        "addressed to the commanded vehicle only: {got:?}"
    );
    assert!(
        got.windows(2)
            .all(|w| w[0].sticks.timestamp_ms <= w[1].sticks.timestamp_ms),
        "timestamps increase"
    );
    fmo.post(
        "/api/manual",
        serde_json::json!({"throttle": 0.5, "deadman": false}),
    )
    .await;
    let deadline = tokio::time::Instant::now() + STEP;
    loop {
        let s = sticks.recv_timeout(STEP).await.expect("manual_control");
        if s.value.sticks.throttle == 0.0 && s.value.sticks.roll == 0.0 {
            break;
        }
        assert!(tokio::time::Instant::now() < deadline, "never neutral");
    }
    // After the neutral tail the station falls silent.
    tokio::time::sleep(Duration::from_millis(2000)).await;
    while sticks.try_recv().is_some() {}
    assert!(
        sticks
            .recv_timeout(Duration::from_millis(600))
            .await
            .is_err(),
        "an idle station publishes nothing"
    );

    // Switch to rover2: its own state and transitions.
    fmo.post("/api/select", serde_json::json!({"vehicle": "rover2/vas"}))
        .await;
    fmo.wait_state("rover2 commanded", |s| {
        s["selected"] == "rover2/vas" && veh(s, "rover2")["allowed"]["current"] == true
    })
    .await;
    let (_, body) = fmo
        .post("/api/change_state", serde_json::json!({"to": "DIRECTED"}))
        .await;
    let id = body["id"].as_u64().unwrap();
    fmo.wait_state("rover2 confirmed", |s| {
        command(s, id).is_some_and(|c| c["status"] == "ok" && c["vehicle"] == "rover2")
    })
    .await;
    assert_eq!(*v2.state.lock().unwrap(), FlightState::Directed);
    assert_eq!(*v1.state.lock().unwrap(), FlightState::Directed);

    // rover2 goes away: its data goes stale and a command to it fails, without blocking the
    // station (the snapshot still answers at once).
    v2.ticker.abort();
    drop(v2);
    n2.shutdown().await;
    let s = fmo
        .wait_state("rover2 stale", |s| veh(s, "rover2")["link"] == "stale")
        .await;
    assert_eq!(veh(&s, "rover2")["flight_state"]["stale"], true);
    let (_, body) = fmo
        .post("/api/change_state", serde_json::json!({"to": "PARKING"}))
        .await;
    let id = body["id"].as_u64().unwrap();
    let t = tokio::time::Instant::now();
    let _ = fmo.get_json("/api/state").await;
    assert!(
        t.elapsed() < Duration::from_secs(3),
        "the station stays responsive"
    );
    let s = fmo
        .wait_state("the command to the lost vehicle failed", |s| {
            command(s, id).is_some_and(|c| c["status"] == "failed")
        })
        .await;
    assert!(vehicle(&s, "rover1").is_some());

    drop(sse);
    fmo.kill().await;
    v1.ticker.abort();
    drop(v1);
    n1.shutdown().await;
}

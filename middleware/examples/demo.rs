//! Two services in two processes exchanging all four primitives over UDP on this machine.
//!
//! `cargo run -p marea --example demo` starts itself twice: an `air` process (a vehicle
//! publishing its position, raising alarms, providing `change_state` and accepting flight
//! plans) and a `ground` process (a station following the position and alarms, calling
//! `change_state` and uploading a plan). Both print what they see, then stop.

use std::time::Duration;

use marea::{NetworkConfig, Node, SendFileOptions};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Serialize, Deserialize)]
struct Position {
    lat: f64,
    lon: f64,
    alt: f64,
    heading: f32,
    speed: f32,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct Alarm {
    severity: u8,
    text: String,
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let role = std::env::args().nth(1);
    match role.as_deref() {
        Some("air") => air().await,
        Some("ground") => ground().await,
        _ => launch(),
    }
}

fn launch() -> Result<(), Box<dyn std::error::Error>> {
    let me = std::env::current_exe()?;
    let domain = format!("demo-{}", std::process::id());
    println!("demo: starting 'air' and 'ground' as two processes (domain {domain})");
    let mut air = std::process::Command::new(&me)
        .arg("air")
        .env("DEMO_DOMAIN", &domain)
        .spawn()?;
    let ground = std::process::Command::new(&me)
        .arg("ground")
        .env("DEMO_DOMAIN", &domain)
        .status()?;
    let _ = air.wait();
    if ground.success() {
        println!("demo: done");
        Ok(())
    } else {
        Err("ground process failed".into())
    }
}

fn open_config(node: &str, namespace: Option<&str>) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.namespace = namespace.map(str::to_owned);
    c.domain = std::env::var("DEMO_DOMAIN").unwrap_or_else(|_| "demo".into());
    c
}

async fn air() -> Result<(), Box<dyn std::error::Error>> {
    let node = Node::open(&open_config("air", Some("rover1"))).await?;
    let vas = node.service("vas")?;
    let position = vas.publish_variable::<Position>("position")?;
    let alarm = vas.publish_event::<Alarm>("alarm")?;
    let _state = vas.provide_function("change_state", |to: String| async move {
        if to == "WAYPOINT_NAVIGATION" || to == "PARKING" {
            println!("[air]    change_state({to}) accepted");
            Ok(format!("now {to}"))
        } else {
            println!("[air]    change_state({to}) refused");
            Err(format!("no transition to {to} from PARKING"))
        }
    })?;
    // A private directory of a random name (0700), not a guessable path in /tmp.
    let dir = tempfile::tempdir()?;
    let plans = vas.file_sink("plans", dir.path())?;
    println!("[air]    publishing rover1/vas/position, raising rover1/vas/alarm, providing rover1/vas/change_state, accepting files on rover1/vas/plans");
    position
        .wait_remote_subscribers(1, Duration::from_secs(10))
        .await;
    for i in 0..20u32 {
        position.set(&Position {
            lat: 41.2750 + f64::from(i) * 1e-5,
            lon: 1.9870,
            alt: 0.0,
            heading: 90.0,
            speed: 1.5,
        })?;
        if i % 5 == 4 {
            let report = alarm
                .raise(&Alarm {
                    severity: 4,
                    text: format!("battery at {}%", 90 - i),
                })
                .await?;
            println!("[air]    alarm acknowledged by {:?}", report.acknowledged());
        }
        if let Ok(Ok(f)) = tokio::time::timeout(Duration::from_millis(100), plans.recv()).await {
            println!(
                "[air]    received file {} ({} bytes) from {}",
                f.name, f.size, f.from
            );
        }
    }
    drop(dir);
    node.shutdown().await;
    Ok(())
}

async fn ground() -> Result<(), Box<dyn std::error::Error>> {
    let node = Node::open(&open_config("ground", None)).await?;
    let station = node.service("fmo")?;
    let positions = station.subscribe_variable::<Position>("*/vas/position")?;
    let alarms = station.subscribe_event::<Alarm>("*/vas/alarm")?;
    let change_state = station.function::<String, String>("rover1/vas/change_state")?;
    if !change_state.wait_provider(Duration::from_secs(10)).await {
        return Err("the air process was not discovered within 10 s".into());
    }
    for to in ["WAYPOINT_NAVIGATION", "LANDING"] {
        match change_state
            .call(&to.to_owned(), Duration::from_secs(2))
            .await
        {
            Ok(r) => println!("[ground] change_state({to}) -> {r}"),
            Err(e) => println!("[ground] change_state({to}) failed: {e}"),
        }
    }
    let plan = std::env::temp_dir().join(format!("demo-plan-{}.xml", std::process::id()));
    std::fs::write(&plan, "<flightplan name=\"demo\"/>\n".repeat(200))?;
    let upload = station.send_file(&plan, "rover1/vas/plans", SendFileOptions::default());
    let (mut got_pos, mut got_alarms) = (0, 0);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(8);
    while got_alarms < 4 && tokio::time::Instant::now() < deadline {
        tokio::select! {
            p = positions.recv() => {
                let p = p?;
                got_pos += 1;
                println!("[ground] {} from {}: lat {:.5} lon {:.5} speed {} m/s", p.name, p.publisher, p.value.lat, p.value.lon, p.value.speed);
            }
            a = alarms.recv() => {
                let a = a?;
                got_alarms += 1;
                println!("[ground] {} from {}: severity {} \"{}\"", a.name, a.publisher, a.value.severity, a.value.text);
            }
            _ = tokio::time::sleep_until(deadline) => {}
        }
    }
    let r = upload.wait().await?;
    println!(
        "[ground] uploaded {} bytes to {} in {:?}",
        r.size, r.receiver, r.elapsed
    );
    println!("[ground] saw {got_pos} positions and {got_alarms} alarms");
    let _ = std::fs::remove_file(&plan);
    node.shutdown().await;
    Ok(())
}

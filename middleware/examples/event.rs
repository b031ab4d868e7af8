//! Raise and receive events: every subscriber gets every event exactly once, in order, and
//! `raise` reports who acknowledged.
//!
//! `cargo run -p marea --example event`

use std::time::Duration;

use marea::{NetworkConfig, Node};

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let vehicle = Node::open(&NetworkConfig::ethernet_loopback("vehicle")).await?;
    let station = Node::open(&NetworkConfig::ethernet_loopback("station")).await?;

    let alarm = vehicle.service("vas")?.publish_event::<String>("alarm")?;
    let alarms = station
        .service("fmo")?
        .subscribe_event::<String>("vas/alarm")?;
    alarm
        .wait_remote_subscribers(1, Duration::from_secs(5))
        .await;

    for text in ["battery low", "GPS glitch"] {
        let report = alarm.raise(&text.to_owned()).await?;
        println!(
            "raised {text:?}: acknowledged by {:?}",
            report.acknowledged()
        );
    }
    for _ in 0..2 {
        let e = alarms.recv_timeout(Duration::from_secs(5)).await?;
        println!("station got {} = {:?}", e.name, e.value);
    }

    drop((alarm, alarms));
    vehicle.shutdown().await;
    station.shutdown().await;
    Ok(())
}

//! Publish and subscribe a variable: best effort, newest value wins, late joiners get the last
//! value at once. Two nodes in one process talking over UDP on 127.0.0.1.
//!
//! `cargo run -p marea --example variable`

use std::time::Duration;

use marea::{NetworkConfig, Node};

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let vehicle = Node::open(&NetworkConfig::ethernet_loopback("vehicle")).await?;
    let station = Node::open(&NetworkConfig::ethernet_loopback("station")).await?;

    let speed = vehicle.service("vas")?.publish_variable::<f32>("speed")?;
    speed.set(&1.5)?; // published before anyone listens

    let sub = station
        .service("fmo")?
        .subscribe_variable::<f32>("vas/speed")?;
    let s = sub.recv_timeout(Duration::from_secs(5)).await?;
    println!(
        "late joiner got {} = {} from {}",
        s.name, s.value, s.publisher
    );

    speed.set(&2.0)?;
    let s = sub.recv_timeout(Duration::from_secs(5)).await?;
    println!("then {} = {}", s.name, s.value);

    drop((speed, sub));
    vehicle.shutdown().await;
    station.shutdown().await;
    Ok(())
}

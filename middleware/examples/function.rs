//! Provide and call a function: request/response with a deadline and distinct errors.
//!
//! `cargo run -p marea --example function`

use std::time::Duration;

use marea::{CallError, NetworkConfig, Node};

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let vehicle = Node::open(&NetworkConfig::ethernet_loopback("vehicle")).await?;
    let station = Node::open(&NetworkConfig::ethernet_loopback("station")).await?;

    let vas = vehicle.service("vas")?;
    let _provider = vas.provide_function("change_state", |to: String| async move {
        match to.as_str() {
            "PARKING" | "WAYPOINT_NAVIGATION" => Ok(format!("state is now {to}")),
            _ => Err(format!("transition to {to} not allowed from PARKING")),
        }
    })?;

    let fmo = station.service("fmo")?;
    let change_state = fmo.function::<String, String>("vas/change_state")?;
    change_state.wait_provider(Duration::from_secs(5)).await;
    for to in ["WAYPOINT_NAVIGATION", "LANDING"] {
        match change_state
            .call(&to.to_owned(), Duration::from_secs(2))
            .await
        {
            Ok(r) => println!("{to}: {r}"),
            Err(CallError::Remote { node, message }) => {
                println!("{to}: refused by {node}: {message}")
            }
            Err(e) => println!("{to}: {e}"),
        }
    }
    let missing = fmo.function::<(), ()>("vas/self_destruct")?;
    println!(
        "{}",
        missing.call(&(), Duration::from_secs(1)).await.unwrap_err()
    );

    drop((_provider, change_state, missing, vas, fmo));
    vehicle.shutdown().await;
    station.shutdown().await;
    Ok(())
}

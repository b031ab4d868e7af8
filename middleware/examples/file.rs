//! Send and receive a file: chunked, verified, atomically renamed, with progress.
//!
//! `cargo run -p marea --example file`

use std::time::Duration;

use marea::{NetworkConfig, Node, SendFileOptions};

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let vehicle = Node::open(&NetworkConfig::ethernet_loopback("vehicle")).await?;
    let station = Node::open(&NetworkConfig::ethernet_loopback("station")).await?;
    // A private directory of a random name (0700), not a guessable path in /tmp. Without a
    // directory, `file_sink_with(.., FileSinkOptions::default())` stores under the user's
    // state directory.
    let tmp = tempfile::tempdir()?;
    let dir = tmp.path();

    let fpma = vehicle.service("fpma")?;
    let plans = fpma.file_sink("plans", dir.join("inbox"))?;

    let plan = dir.join("carpark.xml");
    std::fs::write(&plan, "<flightplan/>\n".repeat(50_000))?;
    let fpmo = station.service("fpmo")?;
    // The sender waits for the sink to be discovered, then sends.
    let transfer = fpmo.send_file(&plan, "fpma/plans", SendFileOptions::default());
    let mut progress = transfer.watch_progress();
    tokio::spawn(async move {
        while progress.changed().await.is_ok() {
            let p = *progress.borrow();
            if p.total > 0 && p.acknowledged == p.total {
                println!(
                    "progress: {} / {} bytes acknowledged",
                    p.acknowledged, p.total
                );
            }
        }
    });
    let report = transfer.wait().await?;
    println!(
        "sent {} bytes to {} in {:?}",
        report.size, report.receiver, report.elapsed
    );
    let got = plans.recv_timeout(Duration::from_secs(5)).await?;
    println!(
        "received {} ({} bytes) from {}",
        got.path.display(),
        got.size,
        got.from
    );

    drop((plans, fpma, fpmo));
    vehicle.shutdown().await;
    station.shutdown().await;
    drop(tmp);
    Ok(())
}

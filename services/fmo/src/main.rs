//! The `fmo` binary: arguments, tracing, then [`fmo::run`] until Ctrl-C or SIGTERM.

use std::net::SocketAddr;

use anyhow::Context;
use clap::Parser;

/// USAL Flight Monitor: the pilot's station as a web page (state, telemetry, alarms, state
/// changes, manual control). Prints FMO_URL=http://ADDR/?token=TOKEN when listening.
#[derive(Parser)]
#[command(name = "fmo", version)]
struct Cli {
    /// Address of the HTTP server (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:8081")]
    listen: SocketAddr,
    /// Node name when no network file is given.
    #[arg(long, default_value = "fmo")]
    node: String,
    /// The VASes to follow, as a pattern of their item prefix: `**/vas` (a fleet) or
    /// `rover1/vas` (one vehicle).
    #[arg(long, default_value = "**/vas")]
    vas: String,
    /// Network, staleness and call options every station takes.
    #[command(flatten)]
    station: station_web::StationArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    station_web::init_tracing("fmo=info,marea=warn");
    let config = fmo::FmoConfig {
        station: cli.station.config(cli.listen, cli.node),
        vas: cli.vas,
    };
    let shutdown = marea::process::cancelled_on_signal();
    fmo::run(config, shutdown).await.context("fmo")
}

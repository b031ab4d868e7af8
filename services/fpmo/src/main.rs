//! The `fpmo` binary: arguments, tracing, then [`fpmo::run`] until Ctrl-C or SIGTERM.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use fpma::vehicle::VehicleParams;

/// USAL Flight Plan Monitor: the flight-plan station as a web page (upload, legs, progress,
/// map, skip / go to / pause / resume / modify / re-task). Prints FPMO_URL=http://ADDR/.
#[derive(Parser)]
#[command(name = "fpmo", version)]
struct Cli {
    /// Address of the HTTP server (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:8082")]
    listen: SocketAddr,
    /// The middleware's network.xml (default: Ethernet on loopback).
    #[arg(long)]
    network: Option<PathBuf>,
    /// Middleware domain (overrides the network file's).
    #[arg(long)]
    domain: Option<String>,
    /// Namespace of the station's own items (overrides the network file's).
    #[arg(long)]
    namespace: Option<String>,
    /// Node name when no network file is given.
    #[arg(long, default_value = "fpmo")]
    node: String,
    /// Vehicles followed, as a namespace pattern: `*` (a fleet) or one namespace (`rover1`).
    #[arg(long, default_value = "*")]
    vehicles: String,
    /// Vehicle parameters uploads are checked with before sending (as the FPMa's --vehicle).
    #[arg(long, value_enum, default_value_t = Vehicle::Rover)]
    vehicle: Vehicle,
    /// Values older than this many milliseconds are shown as stale.
    #[arg(long, default_value_t = 2000)]
    stale_ms: u64,
    /// Time limit of each call to the FPMa, milliseconds.
    #[arg(long, default_value_t = 5000)]
    call_timeout_ms: u64,
    /// A georeferenced image drawn under the map: a file the station serves, or an
    /// http(s):// URL the browser loads. North up; give its edges with --background-bounds.
    #[arg(long, requires = "background_bounds")]
    background: Option<String>,
    /// The background image's edges, degrees: NORTH,WEST,SOUTH,EAST.
    #[arg(long, requires = "background", allow_hyphen_values = true)]
    background_bounds: Option<String>,
}

#[derive(Clone, Copy, ValueEnum)]
enum Vehicle {
    Rover,
    Aircraft,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let background = match (&cli.background, &cli.background_bounds) {
        (Some(image), Some(bounds)) => {
            Some(fpmo::background::Background::parse(image, bounds).map_err(anyhow::Error::msg)?)
        }
        _ => None,
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "fpmo=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let config = fpmo::FpmoConfig {
        network: cli.network,
        domain: cli.domain,
        namespace: cli.namespace,
        node: cli.node,
        listen: cli.listen,
        vehicles: cli.vehicles,
        vehicle: match cli.vehicle {
            Vehicle::Rover => VehicleParams::rover(),
            Vehicle::Aircraft => VehicleParams::aircraft(),
        },
        stale_after: Duration::from_millis(cli.stale_ms.max(100)),
        call_timeout: Duration::from_millis(cli.call_timeout_ms.max(100)),
        background,
    };
    let shutdown = marea::process::cancelled_on_signal();
    fpmo::run(config, shutdown).await.context("fpmo")
}

//! The `fpmo` binary: arguments, tracing, then [`fpmo::run`] until Ctrl-C or SIGTERM.

use std::net::SocketAddr;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use flightplan::vehicle::VehicleParams;

/// USAL Flight Plan Monitor: the flight-plan station as a web page (upload, legs, progress,
/// map, skip / go to / pause / resume / modify / re-task). Prints FPMO_URL=http://ADDR/?token=TOKEN.
#[derive(Parser)]
#[command(name = "fpmo", version)]
struct Cli {
    /// Address of the HTTP server (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:8082")]
    listen: SocketAddr,
    /// Node name when no network file is given.
    #[arg(long, default_value = "fpmo")]
    node: String,
    /// Vehicles followed, as a namespace pattern: `*` (a fleet) or one namespace (`rover1`).
    #[arg(long, default_value = "*")]
    vehicles: String,
    /// Vehicle parameters uploads are checked with before sending (as the FPMa's --vehicle).
    #[arg(long, value_enum, default_value_t = Vehicle::Rover)]
    vehicle: Vehicle,
    /// Network, staleness and call options every station takes.
    #[command(flatten)]
    station: station_web::StationArgs,
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
    station_web::init_tracing("fpmo=info,marea=warn");
    let config = fpmo::FpmoConfig {
        station: cli.station.config(cli.listen, cli.node),
        vehicles: cli.vehicles,
        vehicle: match cli.vehicle {
            Vehicle::Rover => VehicleParams::rover(),
            Vehicle::Aircraft => VehicleParams::aircraft(),
        },
        background,
    };
    let shutdown = marea::process::cancelled_on_signal();
    fpmo::run(config, shutdown).await.context("fpmo")
}

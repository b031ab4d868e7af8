//! The `fpma` command-line tool: `fpma expand` previews a plan's waypoint stream. Subcommands are
//! an enum so the networked service can join as `fpma run` without touching the others.

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use fpma::exec::expand_nominal;
use fpma::parse::parse_plan;
use fpma::vehicle::{VehicleKind, VehicleParams};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "fpma", version, about = "USAL Flight Plan Manager")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the waypoint stream of a plan flown with no in-flight changes, one JSON object per line.
    Expand {
        /// The XML flight plan.
        plan: PathBuf,
        /// Vehicle whose parameters shape the waypoints.
        #[arg(long, value_enum, default_value_t = Vehicle::Aircraft)]
        vehicle: Vehicle,
        /// Also write the plan as a QGroundControl `.plan` file.
        #[arg(long, value_name = "OUT.plan")]
        qgc: Option<PathBuf>,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum Vehicle {
    Rover,
    Aircraft,
}

impl From<Vehicle> for VehicleKind {
    fn from(v: Vehicle) -> Self {
        match v {
            Vehicle::Rover => VehicleKind::Rover,
            Vehicle::Aircraft => VehicleKind::Aircraft,
        }
    }
}

/// Exit code for a plan that does not load (2, like a usage error: the input is at fault).
const EXIT_BAD_PLAN: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Expand { plan, vehicle, qgc } => {
            match expand(&plan, vehicle.into(), qgc.as_deref()) {
                Ok(code) => code,
                Err(e) => {
                    eprintln!("fpma: {e:#}");
                    ExitCode::FAILURE
                }
            }
        }
    }
}

fn expand(
    path: &std::path::Path,
    kind: VehicleKind,
    qgc: Option<&std::path::Path>,
) -> anyhow::Result<ExitCode> {
    let src =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let vehicle = VehicleParams::for_kind(kind);
    let plan = match parse_plan(&src, &vehicle) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("{}:{e}", path.display());
            return Ok(ExitCode::from(EXIT_BAD_PLAN));
        }
    };
    if let Some(out) = qgc {
        let doc = fpma::qgc::export(&plan, &vehicle)
            .with_context(|| format!("exporting {}", path.display()))?;
        std::fs::write(out, serde_json::to_string_pretty(&doc)?)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    let wps =
        expand_nominal(plan, vehicle).with_context(|| format!("expanding {}", path.display()))?;
    let mut stdout = std::io::stdout().lock();
    for w in wps {
        let mut line = serde_json::json!({
            "lat": w.lat, "lon": w.lon, "alt": w.alt, "speed": w.speed,
            "fly_over": w.fly_over, "leg": w.leg,
        });
        if w.waits {
            line["waits"] = true.into();
        }
        if w.tag != fpma::expand::WaypointTag::Nav {
            line["tag"] = serde_json::to_value(w.tag)?;
        }
        writeln!(stdout, "{line}")?;
    }
    Ok(ExitCode::SUCCESS)
}

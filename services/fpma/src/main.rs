//! The `fpma` command-line tool: `fpma run` is the networked service (arguments, tracing, config,
//! then [`fpma::run`]); `fpma expand` previews a plan's waypoint stream.

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use flightplan::parse::declared_vehicle;
use flightplan::plan_file::{self, PlanFileError};
use flightplan::vehicle::VehicleKind;
use fpma::service::FpmaConfig;
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
        /// Vehicle whose parameters shape the waypoints [default: the plan's `vehicle`
        /// attribute, else aircraft].
        #[arg(long, value_enum)]
        vehicle: Option<Vehicle>,
        #[command(flatten)]
        params: VehicleArgs,
        /// Also write the plan as a QGroundControl `.plan` file.
        #[arg(long, value_name = "OUT.plan")]
        qgc: Option<PathBuf>,
    },
    /// Run the FPMa service: take plans, feed the VAS, accept changes in flight.
    Run(RunArgs),
}

/// `fpma run` flags; each overrides the config file (`<fpma .../>`, see fpma.example.xml).
#[derive(clap::Args)]
struct RunArgs {
    /// Configuration file.
    #[arg(short, long)]
    config: Option<PathBuf>,
    /// The middleware's network.xml.
    #[arg(long)]
    network: Option<PathBuf>,
    /// Middleware domain (overrides the network file's).
    #[arg(long)]
    domain: Option<String>,
    /// Namespace of the items, e.g. rover1 (overrides the network file's).
    #[arg(long)]
    namespace: Option<String>,
    /// The VAS to feed: a service name in the namespace (`vas`) or a full prefix (`rover1/vas`).
    #[arg(long)]
    vas: Option<String>,
    /// Vehicle whose parameters shape the plans.
    #[arg(long, value_enum)]
    vehicle: Option<Vehicle>,
    #[command(flatten)]
    params: VehicleArgs,
    /// Waypoints kept in the VAS queue ahead of the vehicle.
    #[arg(long)]
    lookahead: Option<usize>,
    /// Ignored (the FPMa never changes the flight state; the operator starts a plan); kept
    /// so older command lines still run.
    #[arg(long)]
    start_navigation: Option<bool>,
    /// Where plan files sent to fpma/plans are stored.
    #[arg(long)]
    plans_dir: Option<PathBuf>,
    /// A plan to load at start.
    #[arg(long)]
    plan: Option<PathBuf>,
    /// Where the plan and progress are persisted (default: the user's state directory).
    #[arg(long)]
    state_dir: Option<PathBuf>,
}

/// Overrides of the vehicle's parameters (config `minWaypointDistance`, `defaultSpeed`,
/// `turnRadius`).
#[derive(clap::Args)]
struct VehicleArgs {
    /// Minimum distance between waypoints, metres (rover 4.5, copter 3, aircraft 100).
    #[arg(long, value_name = "M")]
    min_wp_distance: Option<f64>,
    /// Speed when neither the leg nor the plan gives one, m/s.
    #[arg(long, value_name = "M/S")]
    default_speed: Option<f64>,
    /// Minimum turn radius, metres.
    #[arg(long, value_name = "M")]
    turn_radius: Option<f64>,
}

impl VehicleArgs {
    /// Puts the overrides given into `cfg`.
    fn apply(&self, cfg: &mut FpmaConfig) {
        cfg.min_wp_distance = self.min_wp_distance.or(cfg.min_wp_distance);
        cfg.default_speed = self.default_speed.or(cfg.default_speed);
        cfg.turn_radius = self.turn_radius.or(cfg.turn_radius);
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum Vehicle {
    Rover,
    Aircraft,
    Copter,
}

impl From<Vehicle> for VehicleKind {
    fn from(v: Vehicle) -> Self {
        match v {
            Vehicle::Rover => VehicleKind::Rover,
            Vehicle::Aircraft => VehicleKind::Aircraft,
            Vehicle::Copter => VehicleKind::Copter,
        }
    }
}

/// Exit code for a plan that does not load (2, like a usage error: the input is at fault).
const EXIT_BAD_PLAN: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Run(args) => match run_service(args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("fpma: {e:#}");
                ExitCode::FAILURE
            }
        },
        Command::Expand {
            plan,
            vehicle,
            params,
            qgc,
        } => match expand(&plan, vehicle.map(Into::into), &params, qgc.as_deref()) {
            Ok(code) => code,
            Err(e) => {
                eprintln!("fpma: {e:#}");
                ExitCode::FAILURE
            }
        },
    }
}

fn run_service(args: RunArgs) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "fpma=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let mut cfg = match &args.config {
        Some(p) => FpmaConfig::load(p).with_context(|| format!("loading {}", p.display()))?,
        None => FpmaConfig::default(),
    };
    if args.network.is_some() {
        cfg.network = args.network;
    }
    if args.domain.is_some() {
        cfg.domain = args.domain;
    }
    if args.namespace.is_some() {
        cfg.namespace = args.namespace;
    }
    if let Some(v) = args.vas {
        cfg.vas = v;
    }
    if let Some(v) = args.vehicle {
        cfg.vehicle = v.into();
    }
    args.params.apply(&mut cfg);
    if let Some(v) = args.lookahead {
        cfg.lookahead = v;
    }
    if let Some(v) = args.start_navigation {
        cfg.start_navigation = v;
    }
    if args.plans_dir.is_some() {
        cfg.plans_dir = args.plans_dir;
    }
    if args.state_dir.is_some() {
        cfg.state_dir = args.state_dir;
    }
    if args.plan.is_some() {
        cfg.plan = args.plan;
    }
    // The service's runtime: this binary's only async part.
    let rt = tokio::runtime::Runtime::new().context("starting the tokio runtime")?;
    rt.block_on(async {
        let shutdown = marea::process::cancelled_on_signal();
        fpma::run(cfg, shutdown).await
    })
}

fn expand(
    path: &std::path::Path,
    kind: Option<VehicleKind>,
    params: &VehicleArgs,
    qgc: Option<&std::path::Path>,
) -> anyhow::Result<ExitCode> {
    let src =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut cfg = FpmaConfig {
        vehicle: kind
            .or_else(|| declared_vehicle(&src))
            .unwrap_or(VehicleKind::Aircraft),
        ..FpmaConfig::default()
    };
    params.apply(&mut cfg);
    let vehicle = cfg.vehicle_params()?;
    let checked = match plan_file::load(&src, &path.display().to_string(), &vehicle) {
        Ok(p) => p,
        Err(PlanFileError::Refused(e)) => {
            eprintln!("{e}");
            return Ok(ExitCode::from(EXIT_BAD_PLAN));
        }
        Err(PlanFileError::Endless(e)) => return Err(anyhow::anyhow!("{e}")),
    };
    if let Some(out) = qgc {
        let doc = flightplan::qgc::export(checked.plan(), &vehicle)
            .with_context(|| format!("exporting {}", path.display()))?;
        std::fs::write(out, serde_json::to_string_pretty(&doc)?)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    let mut stdout = std::io::stdout().lock();
    for w in checked.nominal().iter() {
        let mut line = serde_json::json!({
            "lat": w.lat, "lon": w.lon, "alt": w.alt, "speed": w.speed,
            "fly_over": w.fly_over, "leg": w.leg,
        });
        if w.waits {
            line["waits"] = true.into();
        }
        if w.tag != flightplan::expand::WaypointTag::Nav {
            line["tag"] = serde_json::to_value(w.tag)?;
        }
        writeln!(stdout, "{line}")?;
    }
    Ok(ExitCode::SUCCESS)
}

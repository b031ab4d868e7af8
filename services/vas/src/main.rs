//! `vas`: the Virtual Autopilot System service binary (parses arguments, starts tracing,
//! loads the configuration and calls [`vas::run`]).

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use usal_types::VehicleKind;
use vas::config::VasConfig;

/// USAL Virtual Autopilot System: the only service that talks to the autopilot.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Configuration file (`<vas .../>`, see services/vas/vas.example.xml).
    #[arg(short, long)]
    config: Option<PathBuf>,
    /// MAVLink endpoint (udpout:HOST:PORT, udpin:ADDR:PORT, tcpout:HOST:PORT, serial:PATH:BAUD).
    #[arg(long)]
    endpoint: Option<String>,
    /// Vehicle kind: rover, copter or plane.
    #[arg(long)]
    vehicle: Option<VehicleKind>,
    /// Autopilot family: auto (the heartbeat's), ardupilot, px4 or generic.
    #[arg(long)]
    autopilot: Option<vas::config::AutopilotKind>,
    /// Rolling-queue slots on the autopilot (≥ 3).
    #[arg(long)]
    queue_size: Option<u16>,
    /// Telemetry rate, Hz.
    #[arg(long)]
    telemetry_hz: Option<f32>,
    /// Status rate, Hz.
    #[arg(long)]
    status_hz: Option<f32>,
    /// Autopilot heartbeat timeout, ms.
    #[arg(long)]
    heartbeat_timeout_ms: Option<u64>,
    /// How long one attempt of a MAVLink request or mission item waits for its answer, ms.
    #[arg(long)]
    request_timeout_ms: Option<u64>,
    /// Attempts per MAVLink request and per mission item.
    #[arg(long)]
    retries: Option<u32>,
    /// The middleware's network.xml.
    #[arg(long)]
    network: Option<PathBuf>,
    /// Middleware domain (overrides the network file's).
    #[arg(long)]
    domain: Option<String>,
    /// Namespace of the items, e.g. rover1 (overrides the network file's).
    #[arg(long)]
    namespace: Option<String>,
    /// The stations whose manual control is obeyed, comma-separated node names or item
    /// prefixes (`ground-fmo,base/fmo`); default: any.
    #[arg(long)]
    manual_stations: Option<String>,
    /// Also forward MAVLink to and from this endpoint (another ground station, like
    /// mavlink-router); repeatable; added to the file's `<forward>` elements.
    #[arg(long)]
    forward: Vec<String>,
    /// The autopilot's MAVLink system id, where several vehicles share one link.
    #[arg(long)]
    target_system: Option<u8>,
    /// After an autopilot reboot, put it back in the commanded state (re-arming it) and
    /// raise an alarm saying so; default: follow the autopilot and ask the operator.
    #[arg(long)]
    resume_after_reboot: bool,
    /// The autopilot's MAVLink component id, where several components share the link.
    #[arg(long)]
    target_component: Option<u8>,
    /// MAVLink 2 signing key file (64 hex digits, mode 600): sign every frame and accept only
    /// correctly signed ones (replaces the file's `<signing>`, keeping its linkId).
    #[arg(long)]
    signing_key: Option<std::path::PathBuf>,
    /// The vehicle's fence: a file whose root is `<fence>` (as in the configuration file, which
    /// it replaces): on the autopilot before the vehicle may start, kept for the whole flight.
    #[arg(long)]
    fence: Option<std::path::PathBuf>,
    /// A parameter file (Mission Planner's `NAME,VALUE` or QGroundControl's format) set on
    /// the autopilot at start-up, before the vehicle is parked; each value is verified and
    /// each refusal raised as an alarm.
    #[arg(long)]
    params: Option<std::path::PathBuf>,
    /// Keep the air-side log in this directory (`vas-air.jsonl`, rotated): states, commands
    /// received with who sent them and the answers, mission traffic, failsafes, alarms.
    #[arg(long)]
    air_log: Option<std::path::PathBuf>,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "vas=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let mut cfg = match &args.config {
        Some(p) => VasConfig::load(p).with_context(|| format!("loading {}", p.display()))?,
        None => VasConfig::default(),
    };
    if let Some(v) = args.endpoint {
        cfg.endpoint = v;
    }
    if args.resume_after_reboot {
        cfg.resume_after_reboot = true;
    }
    if let Some(v) = args.vehicle {
        cfg.vehicle = v;
    }
    if let Some(a) = args.autopilot {
        cfg.autopilot = a;
    }
    if let Some(v) = args.queue_size {
        cfg.queue_size = v;
    }
    if let Some(v) = args.telemetry_hz {
        cfg.telemetry_hz = v;
    }
    if let Some(v) = args.status_hz {
        cfg.status_hz = v;
    }
    if let Some(v) = args.heartbeat_timeout_ms {
        cfg.heartbeat_timeout_ms = v;
    }
    if let Some(v) = args.request_timeout_ms {
        cfg.request_timeout_ms = v;
    }
    if let Some(v) = args.retries {
        cfg.retries = v;
    }
    if args.network.is_some() {
        cfg.network = args.network;
    }
    if args.domain.is_some() {
        cfg.domain = args.domain;
    }
    if args.namespace.is_some() {
        cfg.namespace = args.namespace;
    }
    if args.manual_stations.is_some() {
        cfg.manual_stations = args.manual_stations;
    }
    if args.target_system.is_some() {
        cfg.target_system = args.target_system;
    }
    if args.target_component.is_some() {
        cfg.target_component = args.target_component;
    }
    if args.air_log.is_some() {
        cfg.air_log = args.air_log;
    }
    if args.params.is_some() {
        cfg.params = args.params;
    }
    if let Some(path) = &args.fence {
        cfg.fence = Some(
            vas::config::FenceSettings::load(path)
                .with_context(|| format!("loading the fence {}", path.display()))?,
        );
    }
    if let Some(key_file) = args.signing_key {
        let link_id = cfg.signing.as_ref().map_or(0, |s| s.link_id);
        cfg.signing = Some(vas::config::SigningSettings { key_file, link_id });
    }
    cfg.forward.extend(
        args.forward
            .into_iter()
            .map(|endpoint| vas::config::ForwardConfig { endpoint }),
    );
    let shutdown = marea::process::cancelled_on_signal();
    vas::run(cfg, shutdown).await
}

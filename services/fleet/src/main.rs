//! The `fleet` binary: arguments, tracing, the fleet plan, then [`fleet::run`] until Ctrl-C or
//! SIGTERM.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

/// USAL fleet mission layer: runs a fleet plan (SEQ/PAR blocks, waits, loops, sync points,
/// the Broz search) over several vehicles' FPMa and VAS, keeping them apart. Prints
/// FLEET_DONE=<status JSON> (or FLEET_FAILED=) when the plan ends, then keeps serving its
/// status until stopped.
#[derive(Parser)]
#[command(name = "fleet", version)]
struct Cli {
    /// The fleet plan (format: services/fleet/README.md).
    #[arg(long)]
    plan: PathBuf,
    /// A network.xml; default Ethernet on loopback.
    #[arg(long)]
    network: Option<PathBuf>,
    /// Node name.
    #[arg(long, default_value = "fleet")]
    node: String,
    /// Discovery domain.
    #[arg(long)]
    domain: Option<String>,
    /// Namespace of the service's items (`gcs` → `gcs/fleet/status`).
    #[arg(long)]
    namespace: Option<String>,
    /// Only check the plan (exit 2 with FILE:LINE:COL: <element>: what, when it is wrong).
    #[arg(long)]
    check: bool,
}

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "fleet=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let plan = match fleet::plan::load(&cli.plan) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("fleet: {e}");
            return ExitCode::from(2);
        }
    };
    if cli.check {
        println!(
            "{}: fleet plan `{}` is valid",
            cli.plan.display(),
            plan.name
        );
        return ExitCode::SUCCESS;
    }
    let mut config = fleet::FleetConfig::new(plan);
    config.network = cli.network;
    config.node = cli.node;
    config.domain = cli.domain;
    config.namespace = cli.namespace;
    let shutdown = marea::process::cancelled_on_signal();
    match fleet::run(config, shutdown).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fleet: {e:#}");
            ExitCode::FAILURE
        }
    }
}

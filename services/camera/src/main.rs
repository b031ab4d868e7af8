//! The `camera` binary: arguments, tracing, then [`camera::run`] until Ctrl-C or SIGTERM.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

/// USAL camera service: reads a camera's frame stream (mavsim's --camera) and publishes the
/// frames over marea: `raw` (uncompressed, for services on board), `frame` (JPEG, for the
/// stations) and `snapshot` (a small JPEG on request, for a radio).
#[derive(Parser)]
#[command(name = "camera", version)]
struct Cli {
    /// The camera's stream, HOST:PORT (mavsim prints it as MAVSIM_CAMERA=).
    #[arg(long)]
    source: String,
    /// JPEG quality, 1-100.
    #[arg(long, default_value_t = 75, value_parser = clap::value_parser!(u8).range(1..=100))]
    quality: u8,
    /// A network.xml; default Ethernet on loopback.
    #[arg(long)]
    network: Option<PathBuf>,
    /// Node name.
    #[arg(long, default_value = "camera")]
    node: String,
    /// Discovery domain.
    #[arg(long)]
    domain: Option<String>,
    /// Namespace of the service's items (`uav1` → `uav1/camera/frame`).
    #[arg(long)]
    namespace: Option<String>,
}

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "camera=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let config = camera::CameraConfig {
        source: cli.source,
        quality: cli.quality,
        network: cli.network,
        node: cli.node,
        domain: cli.domain,
        namespace: cli.namespace,
    };
    match camera::run(config, marea::process::cancelled_on_signal()).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("camera: {e:#}");
            ExitCode::FAILURE
        }
    }
}

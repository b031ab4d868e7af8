//! The `fmo` binary: arguments, tracing, then [`fmo::run`] until Ctrl-C or SIGTERM.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;

/// USAL Flight Monitor: the pilot's station as a web page (state, telemetry, alarms, state
/// changes, manual control). Prints FMO_URL=http://ADDR/ when listening.
#[derive(Parser)]
#[command(name = "fmo", version)]
struct Cli {
    /// Address of the HTTP server (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:8081")]
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
    #[arg(long, default_value = "fmo")]
    node: String,
    /// The VASes to follow, as a pattern of their item prefix: `**/vas` (a fleet) or
    /// `rover1/vas` (one vehicle).
    #[arg(long, default_value = "**/vas")]
    vas: String,
    /// Values older than this many milliseconds are shown as stale.
    #[arg(long, default_value_t = 2000)]
    stale_ms: u64,
    /// Time limit of each call to a VAS, milliseconds.
    #[arg(long, default_value_t = 5000)]
    call_timeout_ms: u64,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "fmo=info,marea=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let config = fmo::FmoConfig {
        network: cli.network,
        domain: cli.domain,
        namespace: cli.namespace,
        node: cli.node,
        listen: cli.listen,
        vas: cli.vas,
        stale_after: Duration::from_millis(cli.stale_ms.max(100)),
        call_timeout: Duration::from_millis(cli.call_timeout_ms.max(100)),
    };
    let shutdown = marea::process::cancelled_on_signal();
    fmo::run(config, shutdown).await.context("fmo")
}

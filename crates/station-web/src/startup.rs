//! Starting and stopping a station: the options every station takes, tracing, the HTTP
//! listener and the `NAME=http://ADDR/` line, the middleware node, and the orderly stop.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::access::Access;

/// The command-line options every station takes (flattened into each binary's own; the
/// listening address and node name stay there, their defaults differ).
#[derive(clap::Args, Clone, Debug)]
pub struct StationArgs {
    /// The middleware's network.xml (default: Ethernet on loopback).
    #[arg(long)]
    pub network: Option<PathBuf>,
    /// Middleware domain (overrides the network file's).
    #[arg(long)]
    pub domain: Option<String>,
    /// Namespace of the station's own items (overrides the network file's).
    #[arg(long)]
    pub namespace: Option<String>,
    /// Values older than this many milliseconds are shown as stale.
    #[arg(long, default_value_t = 2000)]
    pub stale_ms: u64,
    /// Time limit of each call to a vehicle's service (VAS, FPMa), milliseconds.
    #[arg(long, default_value_t = 5000)]
    pub call_timeout_ms: u64,
    /// Map tiles under the map: `osm` (OpenStreetMap's tile server, the default), `none` (a
    /// metric grid alone), an http(s):// URL template `https://tiles.example/{z}/{x}/{y}.png`
    /// the browser loads, a local MBTiles file or a local path template `/maps/{z}/{x}/{y}.png`
    /// (served by the station, so the page works offline). Where tiles cannot be loaded the
    /// page draws the grid and says so.
    #[arg(long, default_value = crate::tiles::CHOICE_OSM)]
    pub tiles: String,
    /// The credit shown under the map tiles (OpenStreetMap's carry theirs).
    #[arg(long)]
    pub tiles_attribution: Option<String>,
}

impl StationArgs {
    /// The configuration these options give a station listening on `listen` as node `node`
    /// (both times at least 100 ms).
    pub fn config(self, listen: SocketAddr, node: String) -> StationConfig {
        StationConfig {
            network: self.network,
            domain: self.domain,
            namespace: self.namespace,
            node,
            listen,
            stale_after: Duration::from_millis(self.stale_ms.max(100)),
            call_timeout: Duration::from_millis(self.call_timeout_ms.max(100)),
            tiles: self.tiles,
            tiles_attribution: self.tiles_attribution,
        }
    }
}

/// What every station needs besides its own options.
#[derive(Clone, Debug)]
pub struct StationConfig {
    /// The middleware's network.xml; none: Ethernet on loopback.
    pub network: Option<PathBuf>,
    /// Overrides the network file's domain.
    pub domain: Option<String>,
    /// Overrides the network file's namespace (the station's own items' prefix).
    pub namespace: Option<String>,
    /// Node name when no network file is given.
    pub node: String,
    /// Where the HTTP server listens (`127.0.0.1:0`: any free port).
    pub listen: SocketAddr,
    /// Values older than this are shown as stale.
    pub stale_after: Duration,
    /// Time limit of each call to a vehicle's service.
    pub call_timeout: Duration,
    /// The map tiles, as `--tiles` names them ([`crate::tiles::Tiles::choose`]).
    pub tiles: String,
    /// The credit shown under the tiles, when given.
    pub tiles_attribution: Option<String>,
}

impl StationConfig {
    /// The map tiles this configuration names (none: the page's grid alone).
    ///
    /// # Errors
    /// A template missing a placeholder, an MBTiles file that cannot be used.
    pub fn open_tiles(&self) -> anyhow::Result<Option<Arc<crate::tiles::Tiles>>> {
        let t = crate::tiles::Tiles::choose(&self.tiles, self.tiles_attribution.as_deref())
            .with_context(|| format!("--tiles {}", self.tiles))?;
        Ok(t.map(Arc::new))
    }
}

impl StationConfig {
    /// The defaults of a station named `node` listening on `127.0.0.1:port`.
    pub fn new(node: &str, port: u16) -> Self {
        Self {
            network: None,
            domain: None,
            namespace: None,
            node: node.into(),
            listen: SocketAddr::from(([127, 0, 0, 1], port)),
            stale_after: Duration::from_secs(2),
            call_timeout: Duration::from_secs(5),
            tiles: crate::tiles::CHOICE_OSM.into(),
            tiles_attribution: None,
        }
    }
}

/// Logs to stderr, filtered by `RUST_LOG` or else by `default_filter` (`fmo=info,marea=warn`).
pub fn init_tracing(default_filter: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| default_filter.into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// A bound station listener and the access rules (token, allowed hosts) it will serve with.
#[derive(Debug)]
pub struct Listener {
    /// The bound socket.
    pub tcp: tokio::net::TcpListener,
    /// What [`serve_and_shut_down`] requires of every request.
    pub access: Arc<Access>,
}

/// Binds the station's HTTP listener, makes its random token and prints
/// `url_var=http://ADDR/?token=TOKEN` on stdout (the line tests and the launcher read, with the
/// port actually bound).
///
/// # Errors
/// The address cannot be bound.
pub async fn bind(listen: SocketAddr, url_var: &str) -> anyhow::Result<(Listener, SocketAddr)> {
    let tcp = tokio::net::TcpListener::bind(listen)
        .await
        .with_context(|| format!("listening on {listen}"))?;
    let addr = tcp.local_addr().context("local address")?;
    let access = Arc::new(Access::generate(addr));
    print_url(url_var, &access.url(addr));
    Ok((Listener { tcp, access }, addr))
}

/// Prints `NAME=URL` on stdout.
fn print_url(name: &str, url: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{name}={url}");
    let _ = out.flush();
}

/// Opens the middleware node the configuration describes.
///
/// # Errors
/// Unreadable network file, a node that cannot open.
pub async fn open_node(config: &StationConfig) -> anyhow::Result<marea::Node> {
    let net = marea::NetworkConfig::for_service(
        config.network.as_deref(),
        &config.node,
        config.domain.as_deref(),
        config.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    marea::Node::open(&net)
        .await
        .context("opening the middleware node")
}

/// A call error as the operator reads it: the vehicle's own reason when it refused.
pub fn call_error(e: marea::CallError) -> String {
    match e {
        marea::CallError::Remote { message, .. } => message,
        e => e.to_string(),
    }
}

/// Serves `router` on `listener` until `cancel`, every request checked by the listener's
/// [`Access`] first, then stops the station in order: cancels its
/// tasks and waits for them, drops `state` (what holds the node's handles) and shuts `node`
/// down. Returns how serving ended.
///
/// # Errors
/// The server failed (accepting connections).
pub async fn serve_and_shut_down<S>(
    listener: Listener,
    router: Router,
    cancel: CancellationToken,
    tasks: TaskTracker,
    state: S,
    node: marea::Node,
) -> anyhow::Result<()> {
    let router = listener.access.clone().guard(router);
    let served = crate::http::serve(listener.tcp, router, cancel.clone()).await;
    cancel.cancel();
    tasks.close();
    tasks.wait().await;
    drop(state);
    node.shutdown().await;
    served
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        station: StationArgs,
    }

    #[test]
    fn options_give_the_configuration_with_floors_on_the_times() {
        let cli = Cli::try_parse_from(["x", "--domain", "d", "--stale-ms", "5"]).unwrap();
        let c = cli
            .station
            .config("127.0.0.1:0".parse().unwrap(), "n".into());
        assert_eq!(c.domain.as_deref(), Some("d"));
        assert_eq!(c.node, "n");
        assert_eq!(c.stale_after, Duration::from_millis(100));
        assert_eq!(c.call_timeout, Duration::from_millis(5000));
        assert!(c.network.is_none() && c.namespace.is_none());
    }

    #[test]
    fn a_remote_refusal_reads_as_its_reason() {
        let e = marea::CallError::Remote {
            node: "vehicle".into(),
            message: "not now".into(),
        };
        assert_eq!(call_error(e), "not now");
    }
}

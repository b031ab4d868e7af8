//! `usal-router`: a Zenoh router for USAL systems that outgrow one LAN. Nodes with a `<zenoh>`
//! link in their network.xml connect to it (over TCP or TLS, no multicast needed) and meet the
//! nodes of their domain behind other routers or links; any Zenoh client connects to it too.
//!
//! It is the `zenoh` crate in router mode, so it interoperates with a stock `zenohd` (a router
//! may connect to the other) and takes a `zenohd` configuration file as it is. With a
//! network.xml (`--bridge`) it also joins that domain as a marea node and shows every item of
//! it to any Zenoh client ([`bridge`]).

pub mod bridge;
pub mod identity;
pub mod tls;

use std::path::PathBuf;

use anyhow::Context;

/// Default listening endpoint: Zenoh's well-known port, on every interface.
pub const DEFAULT_LISTEN: &str = "tcp/0.0.0.0:7447";

/// How the router is set up.
#[derive(Debug, Clone, Default)]
pub struct RouterOptions {
    /// Endpoints to listen on (`tcp/0.0.0.0:7447` when none is given, here or in the file).
    pub listen: Vec<String>,
    /// Routers to connect to (another site's router, a `zenohd`).
    pub connect: Vec<String>,
    /// A Zenoh configuration file (JSON5, as `zenohd` takes): TLS, users, access control.
    /// `listen` and `connect` given here override its own.
    pub config_file: Option<PathBuf>,
}

/// The Zenoh configuration of a router with `options`. Without a file multicast scouting is
/// off: nodes and clients reach the router at its endpoints, as across a WAN.
///
/// # Errors
/// The file cannot be read or parsed, or Zenoh refuses an endpoint.
pub fn router_config(options: &RouterOptions) -> anyhow::Result<zenoh::Config> {
    let mut config = match &options.config_file {
        Some(path) => zenoh::Config::from_file(path)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("reading Zenoh configuration {}", path.display()))?,
        None => zenoh::Config::default(),
    };
    let mut set = |key: &str, value: &str| {
        config
            .insert_json5(key, value)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("Zenoh refused {key} = {value}"))
    };
    set("mode", "\"router\"")?;
    let listen = if options.listen.is_empty() && options.config_file.is_none() {
        vec![DEFAULT_LISTEN.to_owned()]
    } else {
        options.listen.clone()
    };
    if !listen.is_empty() {
        set("listen/endpoints", &json_list(&listen))?;
    }
    if !options.connect.is_empty() {
        set("connect/endpoints", &json_list(&options.connect))?;
    }
    if options.config_file.is_none() {
        set("scouting/multicast/enabled", "false")?;
    }
    Ok(config)
}

/// The endpoints a router with `config` listens on, as configured.
pub fn listen_endpoints(config: &zenoh::Config) -> Vec<String> {
    config
        .get_json("listen/endpoints")
        .ok()
        .and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
        .map(|v| endpoint_strings(&v))
        .unwrap_or_default()
}

/// Endpoint strings in a `listen/endpoints` value: a list, or a list per mode.
fn endpoint_strings(v: &serde_json::Value) -> Vec<String> {
    match v {
        serde_json::Value::Array(a) => a
            .iter()
            .filter_map(|e| e.as_str().map(str::to_owned))
            .collect(),
        serde_json::Value::Object(m) => m.get("router").map(endpoint_strings).unwrap_or_default(),
        _ => Vec::new(),
    }
}

fn json_list(v: &[String]) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "[]".into())
}

/// How a USAL node's network.xml names a router at `endpoint`, with the client configuration
/// of its TLS folder (`client_config`) when it serves TLS.
pub fn network_xml_line(endpoint: &str, client_config: Option<&std::path::Path>) -> String {
    match client_config {
        Some(c) => format!(
            "<zenoh mode=\"client\" connect=\"{endpoint}\" config=\"{}\"/>",
            c.display()
        ),
        None => format!("<zenoh mode=\"client\" connect=\"{endpoint}\"/>"),
    }
}

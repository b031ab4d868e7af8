//! The Zenoh router USAL systems meet through beyond one LAN: `usal router` runs `usal-router`,
//! and a mission's `<router>` starts one with a gateway per node it joins. Both are binaries of
//! their own so that Zenoh stays out of `usal`'s build; like the services a mission starts,
//! they are built once, saying so, the first time they are needed.

use std::net::SocketAddr;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::ExitCode;

use anyhow::{anyhow, Context};
use serde_json::json;

use super::bins::Bins;
use super::lan::{free_port, gateway_xml, lan_xml, write};
use super::mission::{Mission, RouterSpec, WanSpec};
use super::supervisor::{ChildSpec, Restart, Supervisor};
use super::ui::Ui;

/// Runs `usal-router` with `args` in place of this process (signals reach it directly).
pub fn main(args: &[String], json: bool) -> ExitCode {
    let ui = Ui::new(json);
    let bins = match super::bins::find_or_build(&["usal-router"], &[], &ui) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("usal: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let mut cmd = std::process::Command::new(bins.path("usal-router"));
    cmd.args(args);
    if json {
        cmd.arg("--json");
    }
    let err = cmd.exec();
    eprintln!(
        "usal: cannot run {}: {err}",
        bins.path("usal-router").display()
    );
    ExitCode::FAILURE
}

/// Starts a mission's `<router>`: `usal-router` on its endpoint (a free port when it names
/// port 0), bridging the mission's domain to any Zenoh client (its node `bridge`), and for
/// each node it joins a LAN of its own and a gateway (`marea-gateway`, node `<node>-gateway`)
/// with that LAN and a `<zenoh>` link to the router; the node named by `wan` reaches the router
/// through `marea-wan`. Says where the router listens and how a Zenoh client joins and reads
/// the mission's items.
pub fn start(
    mission: &mut Mission,
    spec: &RouterSpec,
    domain: &str,
    bins: &Bins,
    scratch: &Path,
    sup: &mut Supervisor,
    ui: &Ui,
) -> anyhow::Result<()> {
    let tcp = endpoint_with_port(&spec.listen)?;
    // With TLS: the same address, and certificates made for this run before anyone connects.
    let (endpoint, client_config, mut args) = if spec.tls {
        let dir = scratch.join("tls");
        let made = std::process::Command::new(bins.path("usal-router"))
            .args(["--certs-only", "--tls-dir"])
            .arg(&dir)
            .stdout(std::process::Stdio::null())
            .status()
            .context("running usal-router to make the certificates")?;
        if !made.success() {
            anyhow::bail!(
                "usal-router could not make the certificates in {}",
                dir.display()
            );
        }
        let endpoint = format!("tls/{}", tcp.trim_start_matches("tcp/"));
        let args = vec!["--tls-dir".to_owned(), dir.display().to_string()];
        (endpoint, Some(dir.join("client.json5")), args)
    } else {
        (tcp.clone(), None, Vec::new())
    };
    args.extend(["--listen".to_owned(), endpoint.clone()]);
    let dir = scratch.join("network");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    // The bridge joins the domain through the router it runs in, as any node beyond it does.
    let bridge = write(
        &dir,
        "bridge.xml",
        &format!(
            "<network node=\"bridge\" namespace=\"bridge\" domain=\"{domain}\">\n  {}\n</network>\n",
            zenoh_link(&endpoint, client_config.as_deref())
        ),
    )?;
    args.extend(["--bridge".to_owned(), bridge.display().to_string()]);
    sup.start(ChildSpec {
        label: "router".into(),
        kind: "router",
        program: bins.path("usal-router"),
        args,
        announce: None,
        crash_after: spec.crash_after,
        env: Vec::new(),
        restart: Restart::Always,
        essential: true,
    });
    let joins = match &client_config {
        Some(c) => format!(
            "a Zenoh client joins by connecting to {endpoint} with the Zenoh configuration {} (it trusts the run's authority, ca.pem beside it)",
            c.display()
        ),
        None => format!(
            "a Zenoh client joins by connecting to {endpoint} (no TLS, no credentials)"
        ),
    };
    let joins = format!(
        "{joins}, and reads every item as JSON on usal/{domain}/<namespace>/<service>/<item> (docs/zenoh.md)"
    );
    ui.note(
        &format!(
            "router: usal-router on {endpoint} joins {} (each through a gateway; no LAN between them); {joins}",
            spec.nodes.join(", ")
        ),
        json!({"event": "router", "endpoint": endpoint, "nodes": spec.nodes, "client_config": client_config,
               "keys": format!("usal/{domain}/**")}),
    );
    if let Some(after) = spec.crash_after {
        ui.note(
            &format!("router: it will be killed {after:?} after its start, and restarted"),
            json!({"event": "router_crash_planned", "after_ms": after.as_millis() as u64}),
        );
    }
    let wan = match &spec.wan {
        Some(w) => {
            let proxy = start_wan(w, &tcp, bins, sup, ui)?;
            // The path is TCP either way; TLS runs through it.
            let proxy = match spec.tls {
                true => format!("tls/{}", proxy.trim_start_matches("tcp/")),
                false => proxy,
            };
            Some((w.node.as_str(), proxy))
        }
        None => None,
    };
    for name in &spec.nodes {
        let node = mission
            .nodes
            .iter_mut()
            .find(|n| n.name == *name)
            .ok_or_else(|| anyhow!("no node `{name}`"))?;
        let port = free_port()?;
        node.network = Some(write(
            &dir,
            &format!("{name}.xml"),
            &lan_xml(name, domain, port),
        )?);
        let namespace = node.namespace.clone().unwrap_or_default();
        let reach = match &wan {
            Some((n, proxy)) if n == name => proxy,
            _ => &endpoint,
        };
        let far = zenoh_link(reach, client_config.as_deref());
        let gw = write(
            &dir,
            &format!("{name}-gateway.xml"),
            &gateway_xml(name, &namespace, domain, port, &far),
        )?;
        sup.start(ChildSpec::gateway(
            format!("{name}/gateway"),
            bins.path("marea-gateway"),
            &gw,
        ));
    }
    Ok(())
}

/// The `<zenoh>` element of a node reaching the router at `endpoint`, with the run's client
/// configuration when it serves TLS.
fn zenoh_link(endpoint: &str, client_config: Option<&Path>) -> String {
    match client_config {
        Some(c) => format!(
            r#"<zenoh name="wan" mode="client" connect="{endpoint}" config="{}"/>"#,
            c.display()
        ),
        None => format!(r#"<zenoh name="wan" mode="client" connect="{endpoint}"/>"#),
    }
}

/// Starts `marea-wan` in front of the router at `router` with the shaping of `wan`; returns the
/// endpoint the node's gateway connects to instead.
fn start_wan(
    wan: &WanSpec,
    router: &str,
    bins: &Bins,
    sup: &mut Supervisor,
    ui: &Ui,
) -> anyhow::Result<String> {
    let to = router.strip_prefix("tcp/").unwrap_or(router);
    let listen = endpoint_with_port("tcp/127.0.0.1:0")?;
    let mut args = vec![
        "--listen".to_owned(),
        listen.trim_start_matches("tcp/").to_owned(),
        "--to".to_owned(),
        to.to_owned(),
        "--delay-ms".to_owned(),
        wan.delay_ms.to_string(),
        "--loss".to_owned(),
        wan.loss.to_string(),
        "--rate-kbps".to_owned(),
        wan.rate_kbps.to_string(),
    ];
    for (start, duration) in &wan.outages {
        args.extend(["--outage".to_owned(), format!("{start}:{duration}")]);
    }
    sup.start(ChildSpec {
        label: "wan".into(),
        kind: "wan",
        program: bins.path("marea-wan"),
        args,
        announce: None,
        crash_after: None,
        env: Vec::new(),
        restart: Restart::Always,
        essential: true,
    });
    let outages: Vec<String> = wan
        .outages
        .iter()
        .map(|(s, d)| format!("{d} ms at {s} ms"))
        .collect();
    ui.note(
        &format!(
            "wan: {} reaches the router through marea-wan ({listen}): {} ms round trip, {} % loss, {} kbit/s{}",
            wan.node,
            2 * wan.delay_ms,
            wan.loss * 100.0,
            wan.rate_kbps,
            if outages.is_empty() {
                String::new()
            } else {
                format!(", outages {}", outages.join(", "))
            }
        ),
        json!({"event": "wan", "node": wan.node, "endpoint": listen, "rtt_ms": 2 * wan.delay_ms,
               "loss": wan.loss, "rate_kbps": wan.rate_kbps, "outages": wan.outages}),
    );
    Ok(listen)
}

/// `tcp/IP:PORT` with a free port of that address in place of port 0.
fn endpoint_with_port(listen: &str) -> anyhow::Result<String> {
    let addr: SocketAddr = listen
        .strip_prefix("tcp/")
        .and_then(|a| a.parse().ok())
        .ok_or_else(|| anyhow!("router endpoint `{listen}` is not tcp/IP:PORT"))?;
    if addr.port() != 0 {
        return Ok(listen.to_owned());
    }
    let free = std::net::TcpListener::bind(addr)
        .and_then(|l| l.local_addr())
        .with_context(|| format!("finding a free TCP port on {}", addr.ip()))?;
    Ok(format!("tcp/{free}"))
}

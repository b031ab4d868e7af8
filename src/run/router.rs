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

use super::lan::{free_port, gateway_xml, lan_xml, write};
use super::mission::{Mission, RouterSpec};
use super::supervisor::{ChildSpec, Supervisor};
use super::ui::Ui;
use super::Bins;

/// Runs `usal-router` with `args` in place of this process (signals reach it directly).
pub fn main(args: &[String], json: bool) -> ExitCode {
    let ui = Ui::new(json);
    let bins = match super::find_or_build(&["usal-router"], &[], &ui) {
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
/// port 0), and for each node it joins a LAN of its own and a gateway (`marea-gateway`, node
/// `<node>-gateway`) with that LAN and a `<zenoh>` link to the router. Says where the router
/// listens and how a Zenoh client joins.
pub fn start(
    mission: &mut Mission,
    spec: &RouterSpec,
    domain: &str,
    bins: &Bins,
    scratch: &Path,
    sup: &mut Supervisor,
    ui: &Ui,
) -> anyhow::Result<()> {
    let endpoint = endpoint_with_port(&spec.listen)?;
    sup.start(ChildSpec {
        label: "router".into(),
        kind: "router",
        program: bins.path("usal-router"),
        args: vec!["--listen".into(), endpoint.clone()],
        announce: None,
    });
    ui.note(
        &format!(
            "router: usal-router on {endpoint} joins {} (each through a gateway; no LAN between them); a Zenoh client joins by connecting to {endpoint}",
            spec.nodes.join(", ")
        ),
        json!({"event": "router", "endpoint": endpoint, "nodes": spec.nodes}),
    );
    let dir = scratch.join("network");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let far = format!(r#"<zenoh name="wan" mode="client" connect="{endpoint}"/>"#);
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
        let gw = write(
            &dir,
            &format!("{name}-gateway.xml"),
            &gateway_xml(name, &namespace, domain, port, &far),
        )?;
        sup.start(ChildSpec {
            label: format!("{name}/gateway"),
            kind: "gateway",
            program: bins.path("marea-gateway"),
            args: vec!["--config".into(), gw.display().to_string()],
            announce: None,
        });
    }
    Ok(())
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

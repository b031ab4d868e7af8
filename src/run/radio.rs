//! A mission's `<radio>`: the two nodes it joins get a LAN each (their own discovery group on
//! this host, so they cannot meet directly), a `marea-radio` emulator carries a serial line
//! between them, and a gateway process on each side (`marea-gateway`, a node with the LAN and
//! the serial link) forwards between LAN and radio by interest.
//!
//! A fleet over radios has several `<radio>`s, each joining one vehicle's air node to the same
//! ground node: the ground node keeps one LAN (`lans` remembers it between calls) and gets one
//! gateway per radio (`<ground>/gateway` for the first, `<ground>/gateway-<air>` for the others).

use std::path::Path;
use std::process::Stdio;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use serde_json::json;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};

use super::bins::Bins;
use super::lan::{free_port, gateway_xml, lan_xml, write};
use super::mission::{Mission, RadioSpec};
use super::supervisor::{ChildSpec, Supervisor};
use super::ui::Ui;

/// How long marea-radio may take to print its ports.
const RADIO_READY: Duration = Duration::from_secs(10);

/// The running emulator; killed when dropped.
pub struct RadioLink {
    _child: Child,
}

/// Starts the emulator and both gateways, and points every process of the two nodes (and the
/// station, through the returned map) at its node's LAN. `lans`: the LAN port of every node
/// an earlier radio of this mission already gave one (the shared ground node).
#[allow(clippy::too_many_arguments)]
pub async fn start(
    mission: &mut Mission,
    spec: &RadioSpec,
    domain: &str,
    bins: &Bins,
    scratch: &Path,
    sup: &mut Supervisor,
    ui: &Arc<Ui>,
    lans: &mut std::collections::HashMap<String, u16>,
) -> anyhow::Result<RadioLink> {
    for name in [&spec.ground, &spec.air] {
        if !lans.contains_key(name.as_str())
            && mission
                .node(name)
                .and_then(|n| n.network.as_ref())
                .is_some()
        {
            bail!(
                "node `{name}` is joined by the <radio>: the launcher gives it its own LAN, so it must not name a network file"
            );
        }
    }
    let mut args = vec![
        "--loss".to_owned(),
        spec.loss.to_string(),
        "--corrupt".to_owned(),
        spec.corrupt.to_string(),
    ];
    if let Some(seed) = spec.seed {
        args.extend(["--seed".to_owned(), seed.to_string()]);
    }
    for (start, duration) in &spec.outages {
        args.extend(["--outage".to_owned(), format!("{start}:{duration}")]);
    }
    let program = bins.path("marea-radio");
    let mut child = Command::new(&program)
        .args(&args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .process_group(0)
        .kill_on_drop(true)
        .spawn()
        .with_context(|| format!("starting {}", program.display()))?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| anyhow!("marea-radio has no stdout"))?;
    let mut lines = BufReader::new(stdout).lines();
    let first = tokio::time::timeout(RADIO_READY, lines.next_line())
        .await
        .map_err(|_| anyhow!("marea-radio did not print its ports within {RADIO_READY:?}"))?
        .context("reading marea-radio's output")?
        .ok_or_else(|| anyhow!("marea-radio exited before printing its ports"))?;
    let ports: serde_json::Value = serde_json::from_str(&first)
        .with_context(|| format!("marea-radio printed {first:?}, not its ports"))?;
    let tty = |side: &str| {
        ports[side]
            .as_str()
            .map(str::to_owned)
            .ok_or_else(|| anyhow!("marea-radio did not name its {side} port: {first}"))
    };
    let (ground_tty, air_tty) = (tty("ground")?, tty("air")?);
    {
        let ui = ui.clone();
        tokio::spawn(async move {
            while let Ok(Some(line)) = lines.next_line().await {
                ui.child_line("radio", &line);
            }
        });
    }
    ui.note(
        &format!(
            "radio: marea-radio joins {} ({ground_tty}) and {} ({air_tty}) at {} baud, loss {}, corruption {}",
            spec.ground, spec.air, spec.baud, spec.loss, spec.corrupt
        ),
        json!({"event": "radio", "ground": ground_tty, "air": air_tty, "baud": spec.baud}),
    );

    let dir = scratch.join("network");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    for (name, tty) in [(&spec.ground, &ground_tty), (&spec.air, &air_tty)] {
        let node = mission
            .nodes
            .iter_mut()
            .find(|n| n.name == *name)
            .ok_or_else(|| anyhow!("no node `{name}`"))?;
        // A node an earlier radio joined keeps its LAN and gets a further gateway.
        let (port, gw_name, label) = match lans.get(name.as_str()) {
            Some(&port) => (
                port,
                format!("{name}-{}", spec.air),
                format!("{name}/gateway-{}", spec.air),
            ),
            None => {
                let port = free_port()?;
                let lan = write(&dir, &format!("{name}.xml"), &lan_xml(name, domain, port))?;
                node.network = Some(lan);
                lans.insert(name.clone(), port);
                (port, name.clone(), format!("{name}/gateway"))
            }
        };
        let namespace = node.namespace.clone().unwrap_or_default();
        let gw = write(
            &dir,
            &format!("{gw_name}-gateway.xml"),
            &gateway_xml(
                &gw_name,
                &namespace,
                domain,
                port,
                &format!(
                    r#"<serial name="radio" address="{tty}" baudRate="{}"/>"#,
                    spec.baud
                ),
            ),
        )?;
        sup.start(ChildSpec::gateway(label, bins.path("marea-gateway"), &gw));
    }
    Ok(RadioLink { _child: child })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_network_files_parse() {
        let lan = marea::NetworkConfig::parse(&lan_xml("air", "d", 40000), None).expect("lan");
        assert_eq!(lan.links.len(), 1);
        let gw = marea::NetworkConfig::parse(
            &gateway_xml(
                "air",
                "rover1",
                "d",
                40000,
                r#"<serial name="radio" address="/dev/pts/9" baudRate="57600"/>"#,
            ),
            None,
        )
        .expect("gateway");
        assert_eq!(gw.node, "air-gateway");
        assert_eq!(gw.namespace.as_deref(), Some("rover1"));
        assert_eq!(gw.gateway, Some(true));
        assert_eq!(gw.links.len(), 2);
    }
}

//! The network files of the nodes a `<radio>` or a `<router>` joins: each gets a LAN of its
//! own on this host (its own discovery group, so the nodes cannot meet directly) and a gateway
//! process with that LAN and its far link (its end of the radio, the router).

use std::path::{Path, PathBuf};

use anyhow::Context;

/// A free UDP port on the loopback interface (for a LAN's discovery group).
pub fn free_port() -> anyhow::Result<u16> {
    let s = std::net::UdpSocket::bind("127.0.0.1:0").context("finding a free UDP port")?;
    Ok(s.local_addr()?.port())
}

/// The Ethernet element of a node's LAN on this host.
fn ethernet(port: u16) -> String {
    format!(
        r#"  <ethernet name="lan" bind="127.0.0.1:0" multicast="239.255.77.1:{port}" interface="127.0.0.1"/>"#
    )
}

/// network.xml of a service on a joined node: its LAN only.
pub fn lan_xml(node: &str, domain: &str, port: u16) -> String {
    format!(
        "<network node=\"{node}\" domain=\"{domain}\">\n{}\n</network>\n",
        ethernet(port)
    )
}

/// network.xml of a node's gateway (node `<node>-gateway`): its LAN and `far_link`, the
/// element of the link beyond it.
pub fn gateway_xml(node: &str, namespace: &str, domain: &str, port: u16, far_link: &str) -> String {
    let ns = if namespace.is_empty() {
        String::new()
    } else {
        format!(" namespace=\"{namespace}\"")
    };
    format!(
        "<network node=\"{node}-gateway\"{ns} domain=\"{domain}\" gateway=\"true\">\n{}\n  {far_link}\n</network>\n",
        ethernet(port)
    )
}

/// Writes `text` to `dir/name`.
pub fn write(dir: &Path, name: &str, text: &str) -> anyhow::Result<PathBuf> {
    let path = dir.join(name);
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

//! `marea-gateway`: a marea node that only forwards between the links its network.xml names
//! (a LAN and a radio, a LAN and a Zenoh router), by interest: a subscription or a call crosses
//! only when someone on the other side wants it, and the last value of every variable it
//! forwards is kept for late subscribers on its side. `usal run` starts one per node a mission's
//! `<router>` joins. It prints JSON lines: `{"ready": node, "gateway": true, "links": [..]}`,
//! then, whenever what it forwards changes, `{"forwarded": N, "added": [..], "removed": [..]}`
//! (each item as `kind name from origin`).

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use serde_json::json;

#[derive(Parser)]
#[command(
    name = "marea-gateway",
    about = "A marea node that forwards between its links (network.xml with several links)"
)]
struct Args {
    /// The gateway's network.xml: two links or more (`gateway="true"` is implied).
    #[arg(long)]
    config: PathBuf,
}

#[tokio::main]
async fn main() -> ExitCode {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(args).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("marea-gateway: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mut config = marea::NetworkConfig::load(&args.config)?;
    if config.links.len() < 2 {
        anyhow::bail!(
            "{}: a gateway needs two links or more to forward between, found {}",
            args.config.display(),
            config.links.len()
        );
    }
    config.gateway = Some(true);
    let node = marea::Node::open(&config)
        .await
        .with_context(|| format!("opening the node of {}", args.config.display()))?;
    println!(
        "{}",
        json!({"ready": node.name(), "gateway": node.is_gateway(), "links": node.link_addrs()})
    );
    let mut shown: BTreeSet<String> = BTreeSet::new();
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    loop {
        tokio::select! {
            _ = marea::process::terminated() => break,
            _ = tick.tick() => {}
        }
        let now: BTreeSet<String> = node
            .forwarded()
            .into_iter()
            .map(|f| format!("{} {} from {}", f.kind.as_str(), f.name, f.origin))
            .collect();
        if now != shown {
            let added: Vec<&String> = now.difference(&shown).collect();
            let removed: Vec<&String> = shown.difference(&now).collect();
            println!(
                "{}",
                json!({"forwarded": now.len(), "added": added, "removed": removed})
            );
            shown = now;
        }
    }
    node.shutdown().await;
    Ok(())
}

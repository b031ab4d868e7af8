//! `usal`: the USAL-rs command-line tools. Introspection of a running system in the spirit of
//! `ros2 topic list/echo`: `usal list`, `usal echo NAME`, `usal call NAME ARGS`,
//! `usal send FILE --to SINK`; `usal run MISSION.xml`, the launcher (see `run/`); and
//! `usal replay LOG`, which plays a run's flight log back (see `run/replay.rs`).

mod run;
use usal_json as types;

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, Context};
use clap::{Args, Parser, Subcommand};
use marea::config::{EthernetConfig, LinkConfig};
use marea::protocol::ItemKind;
use marea::{NetworkConfig, Node, SendFileOptions};

#[derive(Parser)]
#[command(
    name = "usal",
    version,
    about = "USAL-rs tools: run a mission, replay its flight log; list, echo, call, send"
)]
struct Cli {
    #[command(flatten)]
    net: NetArgs,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Args)]
struct NetArgs {
    /// network.xml to join the system with (default: Ethernet on 127.0.0.1, domain "usal").
    #[arg(long, global = true)]
    config: Option<PathBuf>,
    /// Discovery domain (when no --config).
    #[arg(long, global = true, default_value = "usal")]
    domain: String,
    /// Multicast port for discovery (when no --config).
    #[arg(long, global = true, default_value_t = 7477)]
    mcast_port: u16,
    /// How long to wait for discovery before answering, in ms.
    #[arg(long, global = true, default_value_t = 1500)]
    wait_ms: u64,
    /// Print JSON lines instead of text.
    #[arg(long, global = true)]
    json: bool,
    /// Domain key file (from `usal keygen`) to join an authenticated system with, when the
    /// --config file has no <security> element.
    #[arg(long, global = true)]
    key_file: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Cmd {
    /// Start a mission's services (config/missions/*.xml), supervise them and follow the plan.
    Run(run::RunArgs),
    /// Play a flight log of `usal run` back into the system (for an FMo/FPMo to show).
    Replay(run::replay::ReplayArgs),
    /// Run a Zenoh router for nodes beyond one LAN (`<zenoh>` links) and any Zenoh client:
    /// `usal router --listen tcp/0.0.0.0:7447 [--connect ENDPOINT] [--config zenoh.json5]`
    /// (`usal router -- --help` for all options). Built once on first use.
    Router {
        /// Options of usal-router.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// List nodes, services and their items (published, subscribed, provided, called).
    List,
    /// Follow variables and events matching NAME (wildcards * and ** allowed), decoded.
    Echo {
        /// Full name or pattern, e.g. rover1/vas/position or */vas/*.
        name: String,
        /// Stop after this many values (0 = until Ctrl-C).
        #[arg(long, default_value_t = 0)]
        count: u64,
    },
    /// Call function NAME with ARGS given as JSON.
    Call {
        /// Full name, e.g. rover1/vas/change_state.
        name: String,
        /// Arguments as JSON, e.g. '{"to":"PARKING"}' or 21.
        #[arg(default_value = "null")]
        args: String,
        /// Deadline for the answer, in ms.
        #[arg(long, default_value_t = 5000)]
        timeout_ms: u64,
    },
    /// Send FILE to the file sink TO (e.g. `usal send plan.xml rover1/fpma/plans`); exit 0 once
    /// the sink stored it, 1 with its verdict or why nothing answered.
    Send {
        /// The file.
        file: PathBuf,
        /// Full name of the sink (positional, as `call` and `echo` take their names).
        #[arg(required_unless_present = "to_flag", conflicts_with = "to_flag")]
        to: Option<String>,
        /// The sink, as a flag (the form earlier versions wanted).
        #[arg(long = "to", value_name = "TO")]
        to_flag: Option<String>,
        /// How long to keep trying to reach the sink, in s.
        #[arg(long, default_value_t = 30)]
        retry_secs: u64,
    },
    /// Write a fresh random domain key to PATH (mode 0600; an existing file is never
    /// overwritten). Name it in network.xml with <security keyFile="PATH"/> on every node.
    /// With --identity: write a node identity key pair instead, the secret to PATH (0600) and
    /// the public key to PATH.pub, for <security identityFile="PATH"/> and the domain's
    /// identities.xml.
    Keygen {
        /// Where to write the key.
        path: PathBuf,
        /// Make a per-node identity key pair (Ed25519) instead of a domain key.
        #[arg(long)]
        identity: bool,
    },
}

fn network(net: &NetArgs) -> anyhow::Result<NetworkConfig> {
    let mut c = match &net.config {
        Some(p) => NetworkConfig::load(p)?,
        None => {
            let mut c = NetworkConfig::ethernet_loopback("usal-cli");
            c.domain = net.domain.clone();
            c.links = vec![LinkConfig::Ethernet(EthernetConfig {
                interface: std::net::Ipv4Addr::LOCALHOST,
                multicast: std::net::SocketAddrV4::new(
                    std::net::Ipv4Addr::new(239, 255, 77, 1),
                    net.mcast_port,
                ),
                ..EthernetConfig::default()
            })];
            c
        }
    };
    // The tool is its own node whatever the file says, so it never impersonates a service node.
    c.node = format!("usal-cli-{}", std::process::id());
    if let Some(key_file) = &net.key_file {
        c.security = Some(marea::config::SecurityConfig {
            key_file: key_file.clone(),
            encrypt_radio: c.security.as_ref().is_some_and(|s| s.encrypt_radio),
            identity_file: c.security.as_ref().and_then(|s| s.identity_file.clone()),
            identities: c.security.as_ref().and_then(|s| s.identities.clone()),
        });
    }
    Ok(c)
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            };
        }
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("error")),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Cmd::Run(args) = &cli.cmd {
        return run::main(args, cli.net.json);
    }
    if let Cmd::Router { args } = &cli.cmd {
        return run::router::main(args, cli.net.json);
    }
    if let Cmd::Keygen {
        path,
        identity: true,
    } = &cli.cmd
    {
        return match marea::identity::IdentityKey::create_files(path) {
            Ok(key) => {
                let public: String = key.public().iter().map(|b| format!("{b:02x}")).collect();
                println!(
                    "wrote an identity key to {} (mode 0600) and its public key to {}; list it in the domain's identities.xml as\n  <identity key=\"{public}\" namespaces=\"...\"/>\nand give the node <security keyFile=\"..\" identityFile=\"{}\" identities=\"identities.xml\"/>",
                    path.display(),
                    marea::identity::IdentityKey::public_path(path).display(),
                    path.display()
                );
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("usal keygen: {e}");
                ExitCode::FAILURE
            }
        };
    }
    if let Cmd::Keygen { path, .. } = &cli.cmd {
        return match marea::link::auth::DomainKey::create_file(path) {
            Ok(_) => {
                println!(
                    "wrote a new domain key to {} (mode 0600); copy it to every node of the domain and add <security keyFile=\"{}\"/> to their network.xml",
                    path.display(),
                    path.display()
                );
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("usal keygen: {e}");
                ExitCode::FAILURE
            }
        };
    }
    let rt = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("usal: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match rt.block_on(run(cli)) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("usal: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    let cfg = network(&cli.net)?;
    let node = Node::open(&cfg).await.context("joining the network")?;
    let svc = node.service("usal")?;
    let wait = Duration::from_millis(cli.net.wait_ms);
    let code = match &cli.cmd {
        // Dispatched in main before the tool joins the network.
        Cmd::Run(_) | Cmd::Router { .. } | Cmd::Keygen { .. } => ExitCode::from(2),
        Cmd::Replay(a) => run::replay::run(&node, a, wait, cli.net.json).await?,
        Cmd::List => {
            tokio::time::sleep(wait).await;
            list(&node, cli.net.json)?;
            ExitCode::SUCCESS
        }
        Cmd::Echo { name, count } => echo(&svc, name, *count, cli.net.json).await?,
        Cmd::Call {
            name,
            args,
            timeout_ms,
        } => {
            call(
                &node,
                &svc,
                name,
                args,
                Duration::from_millis(*timeout_ms),
                wait,
                cli.net.json,
            )
            .await?
        }
        Cmd::Send {
            file,
            to,
            to_flag,
            retry_secs,
        } => {
            // One of the two is there: clap requires it.
            let to = to.as_deref().or(to_flag.as_deref()).unwrap_or_default();
            send(
                &svc,
                file,
                to,
                Duration::from_secs(*retry_secs),
                &cfg.domain,
                cli.net.json,
            )
            .await?
        }
    };
    drop(svc);
    node.shutdown().await;
    Ok(code)
}

fn list(node: &Node, json: bool) -> anyhow::Result<()> {
    let catalog = node.catalog();
    let remote: Vec<_> = catalog.nodes.into_iter().filter(|n| !n.local).collect();
    let mut lines = Vec::new();
    if json {
        for n in &remote {
            lines.push(serde_json::to_string(n)?);
        }
    } else if remote.is_empty() {
        lines.push("no nodes found (is a system running in this domain?)".to_owned());
    }
    for n in remote.into_iter().filter(|_| !json) {
        let ns = if n.namespace.is_empty() {
            String::new()
        } else {
            format!(" (namespace {})", n.namespace)
        };
        lines.push(format!("node {}{ns}", n.name));
        for s in n.services {
            lines.push(format!("  service {}", s.name));
            for it in s.items {
                let verb = match (it.role, it.kind) {
                    (marea::ItemRole::Offer, ItemKind::Variable | ItemKind::Event) => "publishes",
                    (marea::ItemRole::Offer, ItemKind::Function) => "provides",
                    (marea::ItemRole::Offer, ItemKind::File) => "accepts files",
                    (marea::ItemRole::Interest, ItemKind::Function) => "calls",
                    (marea::ItemRole::Interest, _) => "subscribes",
                };
                // What the tools cannot decode is said where it is listed: `echo` and `call`
                // show such values as raw bytes.
                let raw = it.role == marea::ItemRole::Offer
                    && it.kind != ItemKind::File
                    && !types::knows(&it.type_name);
                lines.push(format!(
                    "    {verb:<13} {:<8} {:<36} {}{}",
                    it.kind.as_str(),
                    it.name,
                    it.type_name,
                    if raw {
                        "  (raw: a type usal does not know)"
                    } else {
                        ""
                    }
                ));
            }
        }
    }
    // `usal list | head`: a reader that stops early ends the listing, not a panic.
    for line in &lines {
        if !print_line(line)? {
            break;
        }
    }
    Ok(())
}

async fn echo(
    svc: &marea::Service,
    name: &str,
    count: u64,
    json: bool,
) -> anyhow::Result<ExitCode> {
    let vars = svc.subscribe_raw(ItemKind::Variable, name)?;
    let events = svc.subscribe_raw(ItemKind::Event, name)?;
    let mut n = 0u64;
    loop {
        let v = tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            v = vars.recv() => v?,
            v = events.recv() => v?,
        };
        let decoded = types::to_json(&v.type_name, &v.payload);
        let text = if json {
            let mut line =
                serde_json::json!({"name": v.name, "publisher": v.publisher, "type": v.type_name});
            match decoded {
                Some(Ok(value)) => line["value"] = value,
                Some(Err(e)) => line["error"] = e.into(),
                None => {
                    line["raw"] = hex(&v.payload).into();
                    line["note"] = "type unknown to usal; shown raw".into();
                }
            }
            line.to_string()
        } else {
            match decoded {
                Some(Ok(value)) => {
                    format!("{} [{}] from {}: {value}", v.name, v.type_name, v.publisher)
                }
                Some(Err(e)) => format!(
                    "{} [{}] from {}: cannot decode: {e}",
                    v.name, v.type_name, v.publisher
                ),
                None => format!(
                    "{} [{}] from {}: {} (type unknown to usal; shown raw)",
                    v.name,
                    v.type_name,
                    v.publisher,
                    hex(&v.payload)
                ),
            }
        };
        if !print_line(&text)? {
            // The reader went away (`usal echo … | head`): that ends the echo, not an error.
            break;
        }
        n += 1;
        if count > 0 && n >= count {
            break;
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Writes one line to stdout; `false` when stdout's reader has gone (a closed pipe), which
/// `println!` would turn into a panic.
fn print_line(text: &str) -> std::io::Result<bool> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match writeln!(out, "{text}").and_then(|()| out.flush()) {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(false),
        Err(e) => Err(e),
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

async fn call(
    node: &Node,
    svc: &marea::Service,
    name: &str,
    args: &str,
    timeout: Duration,
    wait: Duration,
    json: bool,
) -> anyhow::Result<ExitCode> {
    let args: serde_json::Value =
        serde_json::from_str(args).with_context(|| format!("ARGS is not JSON: {args}"))?;
    node.wait_until(wait, |n| n.is_offered(ItemKind::Function, name))
        .await;
    let Some(ty) = svc.function_type(name) else {
        eprintln!("usal: no provider for function '{name}'");
        return Ok(ExitCode::FAILURE);
    };
    let (a, r) =
        types::split_fn(&ty.name).ok_or_else(|| anyhow!("unexpected function type {}", ty.name))?;
    let bytes = match types::from_json(a, &args) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("usal: {e}");
            return Ok(ExitCode::from(2));
        }
    };
    match svc.call_raw(name, bytes, timeout).await {
        Ok(out) => {
            let value = match types::to_json(r, &out) {
                Some(Ok(v)) => v,
                Some(Err(e)) => anyhow::bail!("cannot decode the result as {r}: {e}"),
                None => {
                    serde_json::json!({"raw": hex(&out), "note": format!("type {r} unknown to usal")})
                }
            };
            if json {
                println!("{}", serde_json::json!({"ok": value}));
            } else {
                println!("{value}");
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => {
            if json {
                println!("{}", serde_json::json!({"error": e.to_string()}));
            } else {
                eprintln!("usal: {e}");
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

/// `usal send`: exit 0 once the sink stored the file (an FPMa's plans sink stores a plan once it
/// loaded it), 1 with the sink's verdict or why nothing answered, 2 for a file that cannot be
/// read here.
async fn send(
    svc: &marea::Service,
    file: &std::path::Path,
    to: &str,
    retry: Duration,
    domain: &str,
    json: bool,
) -> anyhow::Result<ExitCode> {
    if !file.is_file() {
        eprintln!("usal: {} is not a readable file", file.display());
        return Ok(ExitCode::from(2));
    }
    let t = svc.send_file(
        file,
        to,
        SendFileOptions {
            retry_for: retry,
            ..Default::default()
        },
    );
    let mut watch = t.watch_progress();
    let tty = std::io::stderr().is_terminal() && !json;
    let progress = async move {
        let mut last = u64::MAX;
        while watch.changed().await.is_ok() {
            let p = *watch.borrow();
            let pct = (p.acknowledged * 100).checked_div(p.total).unwrap_or(0);
            if tty {
                let bar = "#".repeat((pct / 5) as usize);
                eprint!(
                    "\r[{bar:<20}] {pct:>3}%  {}/{} bytes",
                    p.acknowledged, p.total
                );
            } else if pct / 10 != last / 10 {
                eprintln!(
                    "{pct}% ({} of {} bytes acknowledged)",
                    p.acknowledged, p.total
                );
            }
            last = pct;
        }
    };
    // Both run to their end: the progress ends when the transfer's task does, just before its
    // outcome is handed over, so neither may cut the other short.
    let (result, ()) = tokio::join!(t.wait(), progress);
    if tty {
        eprintln!();
    }
    match result {
        Ok(r) => {
            if json {
                println!(
                    "{}",
                    serde_json::json!({"sent": r.size, "to": r.receiver, "resumed_from": r.resumed_from, "ms": r.elapsed.as_millis() as u64})
                );
            } else {
                println!(
                    "sent {} ({} bytes) to {} in {:.2?}",
                    file.display(),
                    r.size,
                    r.receiver,
                    r.elapsed
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => {
            let why = match &e {
                marea::FileSendError::NoSink { .. } => format!("{e} in domain {domain}"),
                _ => e.to_string(),
            };
            if json {
                println!("{}", serde_json::json!({"error": why, "to": to}));
            } else {
                eprintln!("usal: {} not sent: {why}", file.display());
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

//! `usal-router`: parses the command line, opens the router, says where it listens and how to
//! join it, and runs until SIGINT or SIGTERM.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Parser;
use serde_json::json;
use usal_router::{listen_endpoints, network_xml_line, router_config, RouterOptions};

#[derive(Parser)]
#[command(
    name = "usal-router",
    about = "A Zenoh router for USAL systems beyond one LAN (compatible with zenohd)"
)]
struct Args {
    /// Endpoint to listen on, e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 (repeatable;
    /// default tcp/0.0.0.0:7447).
    #[arg(long)]
    listen: Vec<String>,
    /// Router to connect to, e.g. tcp/gs.example.org:7447 (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// Zenoh configuration file (JSON5, as zenohd takes) for TLS, users and access control.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Serve TLS with the deployment's certificates in DIR, made there when missing (an
    /// authority, the router's certificate for --tls-host, and client.json5 for the clients).
    /// Without --listen the router then listens on tls/0.0.0.0:7447.
    #[arg(long, value_name = "DIR")]
    tls_dir: Option<PathBuf>,
    /// A name or address the router is reached at, for its certificate (repeatable; default
    /// 127.0.0.1 and localhost).
    #[arg(long)]
    tls_host: Vec<String>,
    /// With --tls-dir: make the certificates and exit.
    #[arg(long)]
    certs_only: bool,
    /// With --tls-dir: a client certificate with this common name, in DIR/clients/NAME.pem
    /// with NAME.json5 to connect with it (repeatable). The router then asks every client for
    /// one (mutual TLS), and with --bridge NAME calls as itself under usal/<domain>/@as/NAME/.
    #[arg(long, value_name = "NAME")]
    tls_client: Vec<String>,
    /// Join the domain of this network.xml as a marea node and show its items to Zenoh
    /// clients: variables and events on usal/<domain>/<name> (JSON), functions as queryables.
    #[arg(long)]
    bridge: Option<PathBuf>,
    /// Zenoh users: a `user:password` a line (as zenohd's usrpwd dictionary_file). Every client
    /// must then log in, and with --bridge calls as itself under usal/<domain>/@as/<user>/,
    /// which marea's <access> rules see as zenoh/<user>.
    #[arg(long, value_name = "FILE")]
    users: Option<PathBuf>,
    /// With --bridge: a client whose mutual-TLS certificate has this common name calls as it
    /// under usal/<domain>/@as/<NAME>/ (repeatable; users of the dictionary need not be named).
    #[arg(long, value_name = "NAME")]
    identity: Vec<String>,
    /// Print JSON lines instead of text.
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    // Before any thread or Zenoh session exists: see `serialize_zenoh_io` (Zenoh's TLS link is
    // unsound on two threads, and a router serving TLS is where it crashed). A configuration
    // file may ask for TLS too.
    let tls = args.tls_dir.is_some()
        || args.config.is_some()
        || args
            .listen
            .iter()
            .chain(&args.connect)
            .any(|e| e.starts_with("tls/"));
    if tls {
        marea::link::zenoh::serialize_zenoh_io();
    }
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("usal-router: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(run_main(args))
}

async fn run_main(args: Args) -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(args).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("usal-router: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(args: Args) -> anyhow::Result<()> {
    let tls = match &args.tls_dir {
        Some(dir) => {
            let hosts = if args.tls_host.is_empty() {
                vec!["127.0.0.1".to_owned(), "localhost".to_owned()]
            } else {
                args.tls_host.clone()
            };
            Some(usal_router::tls::ensure(dir, &hosts)?)
        }
        None if args.certs_only => anyhow::bail!("--certs-only needs --tls-dir"),
        None if !args.tls_client.is_empty() => anyhow::bail!("--tls-client needs --tls-dir"),
        None => None,
    };
    let mut clients = Vec::new();
    if let Some(files) = &tls {
        for name in &args.tls_client {
            usal_router::identity::check(name)?;
            let config = usal_router::tls::ensure_client(files, name)?;
            say(
                args.json,
                &format!(
                    "usal-router: client certificate of {name}: a client connects with {}",
                    config.display()
                ),
                json!({"event": "client_certificate", "name": name, "client_config": config}),
            );
            clients.push(name.clone());
        }
    }
    if args.certs_only {
        if let Some(files) = &tls {
            say(
                args.json,
                &format!(
                    "usal-router: certificates in {}; clients trust {} (their Zenoh configuration: {})",
                    files.ca.parent().map_or_else(String::new, |d| d.display().to_string()),
                    files.ca.display(),
                    files.client_config.display()
                ),
                json!({"event": "certificates", "ca": files.ca, "client_config": files.client_config}),
            );
        }
        return Ok(());
    }
    let listen = if args.listen.is_empty() && tls.is_some() && args.config.is_none() {
        vec!["tls/0.0.0.0:7447".to_owned()]
    } else {
        args.listen
    };
    let options = RouterOptions {
        listen,
        connect: args.connect,
        config_file: args.config,
    };
    let mut config = router_config(&options)?;
    if let Some(files) = &tls {
        usal_router::tls::configure_router(&mut config, files, !clients.is_empty())?;
    }
    if let Some(users) = &args.users {
        let file = std::fs::canonicalize(users)
            .with_context(|| format!("the user dictionary {}", users.display()))?;
        config
            .insert_json5(
                "transport/auth/usrpwd/dictionary_file",
                &serde_json::to_string(&file).context("the user dictionary's path")?,
            )
            .map_err(|e| anyhow::anyhow!("{e}"))
            .context("Zenoh refused the user dictionary")?;
    }
    // The domain it bridges, joined once the router is up; the calls its clients make as
    // themselves kept to them from the start.
    let bridged = match &args.bridge {
        Some(path) => {
            let mut network = marea::NetworkConfig::load(path)?;
            // It relays calls for its Zenoh clients, as a gateway relays them for nodes.
            network.gateway = Some(true);
            let names: Vec<String> = args.identity.iter().chain(&clients).cloned().collect();
            let identities = usal_router::identity::identities(&config, &names)?;
            usal_router::identity::restrict_calls_as(&mut config, &network.domain, &identities)?;
            Some((path, network, identities))
        }
        None if !args.identity.is_empty() => anyhow::bail!("--identity needs --bridge"),
        None => None,
    };
    let endpoints = listen_endpoints(&config);
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
        .with_context(|| format!("opening the router on {}", endpoints.join(", ")))?;
    let zid = session.zid().to_string();
    // Under mutual TLS a client presents its own certificate: the configuration of one of them.
    let client_config = tls.as_ref().map(|f| match clients.first() {
        Some(_) => f.client_config.with_file_name("clients").join("NAME.json5"),
        None => f.client_config.clone(),
    });
    let client_config = client_config.as_deref();
    if args.json {
        println!(
            "{}",
            json!({"event": "listening", "zid": zid, "endpoints": endpoints,
                   "network_xml": endpoints.first().map(|e| network_xml_line(e, client_config))})
        );
    } else {
        println!(
            "usal-router: Zenoh router {zid} listening on {}",
            endpoints.join(", ")
        );
        if let Some(e) = endpoints.first() {
            println!(
                "usal-router: a USAL node joins with {} in its network.xml (from another machine, this machine's address instead of 0.0.0.0)",
                network_xml_line(e, client_config)
            );
            match &tls {
                Some(files) if !clients.is_empty() => println!(
                    "usal-router: a Zenoh client joins by connecting to {e} with the certificate of one of {} (mutual TLS; Zenoh configuration for each: {})",
                    clients.join(", "),
                    client_config.map_or_else(String::new, |c| c.display().to_string())
                ),
                Some(files) => println!(
                    "usal-router: any Zenoh client joins by connecting to {e} trusting {} (Zenoh configuration for clients: {})",
                    files.ca.display(),
                    files.client_config.display()
                ),
                None if options.config_file.is_none() => println!(
                    "usal-router: any Zenoh client joins by connecting to {e}; this router asks no credentials and does not encrypt (--tls-dir, users: docs/zenoh.md)"
                ),
                None => println!("usal-router: any Zenoh client joins by connecting to {e}"),
            }
        }
    }
    let cancel = tokio_util::sync::CancellationToken::new();
    match bridged {
        Some((path, network, identities)) => {
            let domain = network.domain.clone();
            let node = marea::Node::open(&network)
                .await
                .with_context(|| format!("joining the domain of {}", path.display()))?;
            if args.json {
                println!(
                    "{}",
                    json!({"event": "bridging", "domain": domain, "node": node.name(),
                           "keys": format!("usal/{domain}/**"), "identities": identities})
                );
            } else {
                println!(
                    "usal-router: bridging domain {domain} as node {}: its variables and events on usal/{domain}/<name> (JSON), its functions as queryables there",
                    node.name()
                );
                if identities.is_empty() {
                    println!("usal-router: Zenoh clients call as zenoh/anonymous (identities: --users, --identity)");
                } else {
                    println!(
                        "usal-router: a client logged in as one of {} calls as itself under usal/{domain}/@as/<name>/ (zenoh/<name> to <access> rules); others as zenoh/anonymous",
                        identities.join(", ")
                    );
                }
            }
            let bridged = tokio::select! {
                r = usal_router::bridge::run(session.clone(), &node, domain, identities, cancel.clone()) => r,
                _ = wait_for_stop() => Ok(()),
            };
            cancel.cancel();
            node.shutdown().await;
            bridged.context("bridge")?;
        }
        None => wait_for_stop().await,
    }
    session
        .close()
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("closing the router")?;
    Ok(())
}

/// Prints `text`, or `json` with --json.
fn say(json: bool, text: &str, value: serde_json::Value) {
    if json {
        println!("{value}");
    } else {
        println!("{text}");
    }
}

/// Resolves on SIGINT or SIGTERM.
async fn wait_for_stop() {
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = async {
            match term.as_mut() {
                Some(t) => { t.recv().await; }
                None => std::future::pending::<()>().await,
            }
        } => {}
    }
}

//! VAS: the USAL Virtual Autopilot System (003 ch. 3), the only service that talks to the
//! autopilot.
//!
//! Two layers, as the seed designed them (003 §3.1, figure 3.2):
//! - [`val`]: the Virtual Autopilot Layer, the USAL side, fixed: flight-state machine with a
//!   [transition table](val::transitions) per vehicle kind, telemetry variables, events, the
//!   waypoint queue the FPMa feeds, manual control from the FMo. [`val::Vas`] is the
//!   middleware service (`IService`).
//! - [`apl`]: the Autopilot Layer: the [`apl::IAutopilot`] trait and its MAVLink
//!   implementation [`apl::mavlink::MavlinkAutopilot`] (one layer; a family-specific
//!   [`apl::ApFamily`] each for ArduPilot and PX4), which keeps the autopilot fed
//!   through the [rolling waypoint queue](apl::queue) (003 §3.3.2), built on
//! - [`mavlink_cm`]: the MAVLink Communication Manager (003 §3.2.2), independent of USAL.
//!
//! [`run`] starts the whole service from a [`config::VasConfig`]; the `vas` binary is a thin
//! shell over it. Item names and types are listed in `services/vas/README.md`.

pub mod airlog;
pub mod apl;
pub mod config;
pub mod mavlink_cm;
pub mod params_file;
pub mod val;

use std::sync::Arc;

use anyhow::Context;
use tokio_util::sync::CancellationToken;

use crate::apl::mavlink::MavlinkAutopilot;
use crate::apl::IAutopilot;
use crate::config::VasConfig;

/// Runs the VAS until `shutdown` is cancelled: opens the middleware node and the autopilot
/// link, hosts the `vas` service, then shuts everything down.
///
/// # Errors
/// Bad configuration, unreadable network file, a node that cannot open.
pub async fn run(config: VasConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    config.validate()?;
    let net = marea::NetworkConfig::for_service(
        config.network.as_deref(),
        "vas",
        config.domain.as_deref(),
        config.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    let signing = config.signing().context("MAVLink signing")?;
    match &signing {
        Some(s) => tracing::info!(link_id = s.link_id, "MAVLink 2 signing on: every frame to and from the autopilot is signed"),
        None => tracing::warn!("MAVLink 2 signing off: anyone who can reach the autopilot's link can command it (give the VAS <signing keyFile=..> or --signing-key, and the autopilot the same key)"),
    }
    // The MAVLink layer with the family's modes the configuration names, or the heartbeat's
    // (`auto`).
    let mut ap = config.apl();
    ap.manager.signing = signing;
    let apl: Arc<dyn IAutopilot> = Arc::new(
        MavlinkAutopilot::open(&config.endpoint, ap)
            .await
            .with_context(|| format!("opening the autopilot at {}", config.endpoint))?,
    );
    // A bad parameter file stops the VAS before it flies anything, naming its line.
    let params = match &config.params {
        Some(path) => params_file::load(path).map_err(|e| anyhow::anyhow!("parameter file {e}"))?,
        None => Vec::new(),
    };
    if config.manual_stations.is_none() {
        tracing::warn!("manualStations not set: manual control is obeyed from any station");
    }
    let node = marea::Node::open(&net)
        .await
        .context("opening the middleware node")?;
    let mut val_config = config.val();
    val_config.params = params;
    node.add_service(Box::new(val::Vas::new(apl.clone(), val_config)))
        .await
        .context("starting the vas service")?;
    tracing::info!(
        "vas up: {} {} on {}",
        config.vehicle,
        config.autopilot.name(),
        config.endpoint
    );
    shutdown.cancelled().await;
    node.shutdown().await;
    apl.shutdown().await;
    Ok(())
}

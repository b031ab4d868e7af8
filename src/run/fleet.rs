//! `usal run` of a mission with a `<fleet>` and no `<station>`: the fleet service flies the
//! vehicles; the launcher follows its `status` variable from the fleet's node (so over a radio
//! it listens on the ground side like any station), shows progress, and with `--until-complete`
//! exits 0 once the fleet plan is done, with the fleet summary (`FleetStatus::text`, JSON
//! record `fleet_plan_summary` with `--json`).

use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use flightplan::fleet_api::items as fleet;
use flightplan::fleet_api::FleetStatus;
use marea::{NetworkConfig, Node};
use serde_json::json;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

use super::mission::Mission;
use super::supervisor::Notice;
use super::ui::Ui;
use super::{interrupted, time_limit, RunArgs};

/// Follows the fleet until its plan ends (with `--until-complete`), a child cannot be kept
/// running, the time limit, or a signal.
pub async fn supervise(
    mission: &Mission,
    domain: &str,
    args: &RunArgs,
    ui: &Arc<Ui>,
    mut notices: broadcast::Receiver<Notice>,
    stop: &CancellationToken,
) -> ExitCode {
    let limit = time_limit(args, mission);
    let Some((node, _)) = mission.fleet() else {
        return ExitCode::FAILURE;
    };
    let ns = node.namespace.clone();
    let fleet_at = match &ns {
        Some(ns) => format!("{ns}/fleet"),
        None => "fleet".to_owned(),
    };
    let mut cfg = match NetworkConfig::for_service(
        node.network.as_deref(),
        &format!("{}-usal", node.name),
        Some(domain),
        ns.as_deref(),
    )
    .context("loading the network configuration")
    {
        Ok(c) => c,
        Err(e) => {
            eprintln!("usal: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    cfg.node = format!("{}-usal", node.name);
    let net = match Node::open(&cfg).await.context("joining the network") {
        Ok(n) => n,
        Err(e) => {
            eprintln!("usal: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let code = follow(
        mission,
        &net,
        &fleet_at,
        args,
        ui,
        &mut notices,
        stop,
        limit,
    )
    .await;
    net.shutdown().await;
    code
}

#[allow(clippy::too_many_arguments)]
async fn follow(
    mission: &Mission,
    net: &Node,
    fleet_at: &str,
    args: &RunArgs,
    ui: &Arc<Ui>,
    notices: &mut broadcast::Receiver<Notice>,
    stop: &CancellationToken,
    limit: Duration,
) -> ExitCode {
    let sub = match net
        .service("usal")
        .and_then(|s| fleet::STATUS.subscribe(&s, fleet_at))
    {
        Ok(s) => s,
        Err(e) => {
            eprintln!("usal: following {}: {e}", fleet::STATUS.at(fleet_at));
            return ExitCode::FAILURE;
        }
    };
    let deadline = tokio::time::sleep(limit);
    tokio::pin!(deadline);
    let mut last: Option<FleetStatus> = None;
    let mut shown = (usize::MAX, usize::MAX, u32::MAX, Vec::<String>::new());
    let failure = loop {
        tokio::select! {
            () = stop.cancelled() => {
                if let Some(s) = &last {
                    if args.until_complete {
                        show(mission, ui, s);
                    }
                }
                return interrupted(args);
            }
            n = notices.recv() => {
                if let Ok(Notice::GaveUp { reason, essential: true }) = n {
                    break reason;
                }
            }
            () = &mut deadline, if args.until_complete => {
                break format!("the fleet plan did not complete within {limit:?}");
            }
            s = sub.recv() => {
                let s = match s {
                    Ok(s) => s.value,
                    Err(marea::RecvError::Closed) => break "the fleet status subscription ended".into(),
                    // A sample that does not decode (or of another type) is skipped, as stations do.
                    Err(e) => {
                        ui.note(&format!("fleet status: {e}"), json!({"event": "note", "text": e.to_string()}));
                        continue;
                    }
                };
                let visited = s.detections.iter().filter(|d| d.visited.is_some()).count();
                let now = (s.detections.len(), visited, s.separation.holds, s.doing.clone());
                let bar = format!(
                    "fleet {}: {} detections, {} visited, {} holds | {}",
                    s.plan,
                    s.detections.len(),
                    visited,
                    s.separation.holds,
                    s.doing.join("; ")
                );
                if now != shown {
                    ui.progress(
                        &bar,
                        Some(&bar),
                        Some(json!({"event": "fleet_progress", "detections": s.detections.len(), "visited": visited, "holds": s.separation.holds, "violations": s.separation.violations, "doing": s.doing})),
                    );
                    shown = now;
                }
                let ended = s.done || s.failed.is_some();
                last = Some(s);
                if ended {
                    let s = last.as_ref().expect("just set");
                    show(mission, ui, s);
                    if let Some(f) = &s.failed {
                        ui.clear_bar();
                        eprintln!("usal: the fleet plan failed: {f}");
                        return ExitCode::FAILURE;
                    }
                    if args.until_complete {
                        return ExitCode::SUCCESS;
                    }
                }
            }
        }
    };
    if let Some(s) = &last {
        show(mission, ui, s);
    }
    ui.clear_bar();
    eprintln!("usal: {failure}");
    ExitCode::FAILURE
}

fn show(mission: &Mission, ui: &Ui, s: &FleetStatus) {
    ui.result(
        s.text(&mission.name).trim_end(),
        json!({"event": "fleet_plan_summary", "summary": s, "visited_ratio": s.visited_ratio()}),
    );
}

//! `usal run MISSION.xml`: starts the services a mission file selects as supervised child
//! processes, runs the ground station in-process, shows the flight plan's progress and, with
//! `--until-complete`, exits with the plan's outcome and a summary.

mod bins;
mod failsafe;
mod fleet;
pub mod flightlog;
mod lan;
pub mod mission;
mod radio;
pub mod replay;
pub mod router;
mod seal;
mod station;
mod supervisor;
mod ui;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use serde_json::json;
use tokio::sync::{broadcast, watch};
use tokio_util::sync::CancellationToken;

use bins::{find_or_build, Bins};
use mission::{Mission, ServiceSpec};
use station::{Outcome, StationSetup};
use supervisor::{Announce, ChildSpec, Notice, Restart, Supervisor};
use ui::Ui;

/// Exit status for a mission or plan file at fault, or bad arguments.
const EXIT_USAGE: u8 = 2;
/// Exit status when interrupted before the plan completed with `--until-complete`.
const EXIT_INTERRUPTED: u8 = 130;
/// Default limit for `--until-complete` when neither the mission nor the command sets one.
pub(crate) const DEFAULT_TIMEOUT: Duration = Duration::from_secs(600);
/// How long mavsim may take to print its address.
const SIM_READY: Duration = Duration::from_secs(30);

/// `usal run` arguments.
#[derive(clap::Args)]
pub struct RunArgs {
    /// The mission file, e.g. config/missions/rover-demo.xml.
    pub mission: PathBuf,
    /// Exit when the flight plan completes (status 0, with a summary), or fails (non-zero).
    #[arg(long)]
    pub until_complete: bool,
    /// Simulated time factor for every mavsim (overrides the mission's).
    #[arg(long)]
    pub speedup: Option<f64>,
    /// Give up after this many seconds with --until-complete (default: the mission's timeoutS,
    /// else 600).
    #[arg(long)]
    pub timeout_s: Option<f64>,
    /// Write the flight log here (default: logs/<mission>-<UTC>.jsonl.gz; gzip when the name
    /// ends in .gz). Replay it with `usal replay LOG`.
    #[arg(long, conflicts_with = "no_log")]
    pub log: Option<PathBuf>,
    /// Write no flight log.
    #[arg(long)]
    pub no_log: bool,
    /// Show the children's routine output too (the gateways' tables of what they forward,
    /// rewritten whenever it changes); by default only what a pilot needs is printed.
    #[arg(long)]
    pub verbose: bool,
}

/// Runs `usal run`; `json` makes the launcher's notes JSON lines on stdout.
pub fn main(args: &RunArgs, json: bool) -> ExitCode {
    let mission = match Mission::load(&args.mission) {
        Ok(m) => m,
        Err(e) => {
            eprintln!("usal: {e}");
            return ExitCode::from(EXIT_USAGE);
        }
    };
    if let Some(x) = args.speedup {
        if !(x.is_finite() && x >= 0.01) {
            eprintln!("usal: --speedup must be at least 0.01");
            return ExitCode::from(EXIT_USAGE);
        }
    }
    if args.timeout_s.is_some_and(|t| run_limit(t).is_none()) {
        eprintln!("usal: --timeout-s must be a positive number of seconds a run can last");
        return ExitCode::from(EXIT_USAGE);
    }
    let fleet = mission.stations().len() > 1;
    let mut stations = Vec::new();
    for (node, st) in mission.stations() {
        match station_setup(&mission, node, st, fleet) {
            Ok(s) => stations.push(s),
            Err(e) => {
                eprintln!("usal: {e:#}");
                return ExitCode::from(EXIT_USAGE);
            }
        }
    }
    if stations.is_empty() && args.until_complete && mission.fleet().is_none() {
        eprintln!(
            "usal: --until-complete needs a <station> in {} to follow a plan",
            args.mission.display()
        );
        return ExitCode::from(EXIT_USAGE);
    }
    let ui = Arc::new(Ui::new(json).verbose(args.verbose));
    let bins = match find_or_build_bins(&mission, &ui) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("usal: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let rt = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("usal: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    rt.block_on(run(mission, stations, bins, args, ui))
}

/// Reads and expands the station's plan, so a bad plan stops the launch before anything starts.
/// In a `fleet` (several stations), the station is named after its vehicle.
fn station_setup(
    mission: &Mission,
    node: &mission::NodeSpec,
    st: &mission::StationSpec,
    fleet: bool,
) -> anyhow::Result<StationSetup> {
    use flightplan::vehicle::{VehicleKind, VehicleParams};
    let src = std::fs::read_to_string(&st.plan)
        .with_context(|| format!("reading {}", st.plan.display()))?;
    let kind = VehicleKind::from_name(&st.vehicle).unwrap_or(VehicleKind::Rover);
    let params = VehicleParams::for_kind(kind);
    let plan = flightplan::check::load(&src, &params)
        .map_err(|e| anyhow!("{}", e.in_file(&st.plan.display().to_string())))?;
    let name = plan.plan().name.clone();
    let wps = plan.nominal();
    let aircraft = (kind != VehicleKind::Rover)
        .then(|| flightplan::aircraft::AircraftPlan::of(plan.plan().altitude_reference(), wps));
    let warnings = sim_home(mission, &st.vas)
        .and_then(|home| far_from_home(wps, home, params.far_from_home_m()))
        .into_iter()
        .collect();
    let nominal: Vec<(String, f64, f64)> =
        wps.iter().map(|w| (w.leg.clone(), w.lat, w.lon)).collect();
    let nominal_m = wps
        .windows(2)
        .map(|w| {
            flightplan::geo::distance(
                flightplan::geo::GeoPoint::new(w[0].lat, w[0].lon),
                flightplan::geo::GeoPoint::new(w[1].lat, w[1].lon),
            )
        })
        .sum();
    // The vehicle: the FPMa's namespace (its whole prefix when it has none).
    let ns = st.fpma.rsplit_once('/').map_or("", |(ns, _)| ns);
    let vehicle = if ns.is_empty() {
        st.fpma.clone()
    } else {
        ns.replace('/', "-")
    };
    // The node running the VAS it follows, for that VAS's restarts.
    let vas_ns = st.vas.rsplit_once('/').map(|(ns, _)| ns);
    let vas_label = mission
        .nodes
        .iter()
        .find(|n| {
            n.namespace.as_deref() == vas_ns
                && n.services.iter().any(|s| matches!(s, ServiceSpec::Vas(_)))
        })
        .map(|n| format!("{}/vas", n.name));
    Ok(StationSetup {
        mission: mission.name.clone(),
        node: if fleet {
            format!("{}-{vehicle}", node.name)
        } else {
            node.name.clone()
        },
        service: if fleet {
            format!("station-{vehicle}")
        } else {
            "station".into()
        },
        vehicle: fleet.then_some(vehicle),
        vas_label,
        namespace: node.namespace.clone(),
        network: node.network.clone(),
        domain: String::new(),
        plan_file: st.plan.clone(),
        plan_name: name,
        fpma: st.fpma.clone(),
        vas: st.vas.clone(),
        nominal,
        nominal_m,
        refused_plan: st.refused_plan.clone(),
        log: None,
        start: st.start,
        aircraft,
        warnings,
    })
}

/// The home of the simulator flying the VAS at `vas` (`rover1/vas`): that node's `<mavsim>`.
fn sim_home(mission: &Mission, vas: &str) -> Option<(f64, f64)> {
    let ns = vas.rsplit_once('/').map(|(ns, _)| ns);
    mission
        .nodes
        .iter()
        .filter(|n| n.namespace.as_deref() == ns)
        .find_map(|n| mission::sim_home(&n.services))
}

/// A warning naming the plan's waypoint farthest from `home` when it lies beyond `limit_m`:
/// a coordinate typed wrong (a sign, a swapped pair) flies the vehicle away.
fn far_from_home(
    wps: &[flightplan::expand::Waypoint],
    home: (f64, f64),
    limit_m: f64,
) -> Option<String> {
    use flightplan::geo::{distance, GeoPoint};
    let from = GeoPoint::new(home.0, home.1);
    let (i, w, d) = wps
        .iter()
        .enumerate()
        .map(|(i, w)| (i, w, distance(from, GeoPoint::new(w.lat, w.lon))))
        .max_by(|a, b| a.2.total_cmp(&b.2))?;
    (d > limit_m).then(|| {
        format!(
            "waypoint {} (leg {}, {:.6},{:.6}) is {:.1} km from home ({:.6},{:.6}), beyond the {:.0} km a plan for this vehicle usually stays within: check its coordinates",
            i + 1,
            w.leg,
            w.lat,
            w.lon,
            d / 1000.0,
            home.0,
            home.1,
            limit_m / 1000.0
        )
    })
}

/// The service binaries sit next to `usal` in the same target directory; when some are
/// missing and this is a source checkout with cargo at hand, they are built once, with the
/// profile `usal` was built with.
fn find_or_build_bins(mission: &Mission, ui: &Ui) -> anyhow::Result<Bins> {
    let mut needed: Vec<&str> = Vec::new();
    for n in &mission.nodes {
        for s in &n.services {
            let name = match s {
                ServiceSpec::Station(_) | ServiceSpec::Autopilot(_) => continue,
                ServiceSpec::Custom(c) => match &c.program {
                    mission::Program::Package(p) => p.as_str(),
                    mission::Program::File(_) | mission::Program::OnPath(_) => continue,
                },
                other => other.kind(),
            };
            if !needed.contains(&name) {
                needed.push(name);
            }
        }
    }
    // A radio needs the emulator (a binary of this package) and a gateway on each side; an
    // emulated wide-area link, marea-wan (one too).
    let mut own: Vec<&str> = Vec::new();
    if mission.radio.is_some() {
        own.push("marea-radio");
    }
    if mission.router.as_ref().is_some_and(|r| r.wan.is_some()) {
        own.push("marea-wan");
    }
    if mission.radio.is_some() || mission.router.is_some() {
        needed.push("marea-gateway");
    }
    // A router needs the router (its gateways have Zenoh too: every marea-gateway has).
    if mission.router.is_some() {
        needed.push("usal-router");
    }
    find_or_build(&needed, &own, ui)
}

async fn run(
    mut mission: Mission,
    mut stations: Vec<StationSetup>,
    bins: Bins,
    args: &RunArgs,
    ui: Arc<Ui>,
) -> ExitCode {
    let domain = mission
        .domain
        .clone()
        .unwrap_or_else(|| format!("{}-{}", mission.name, std::process::id()));
    // The mission's generated files (network files, the camera's obstacles): a directory only
    // this user may enter, under a name nobody can guess or take first (a fixed name in the
    // shared temporary directory could be made in advance by another user). Removed when
    // `scratch_dir` is dropped, on every way out of this function.
    let scratch_dir = match tempfile::Builder::new()
        .prefix(&format!("usal-run-{domain}-"))
        .permissions(std::os::unix::fs::PermissionsExt::from_mode(0o700))
        .tempdir()
    {
        Ok(d) => d,
        Err(e) => {
            eprintln!(
                "usal: creating the mission's scratch directory in {}: {e}",
                std::env::temp_dir().display()
            );
            return ExitCode::FAILURE;
        }
    };
    let scratch = scratch_dir.path().to_owned();
    ui.note(
        &format!(
            "mission {} from {}, discovery domain {domain} (look inside: usal list --domain {domain})",
            mission.name,
            args.mission.display()
        ),
        json!({"event": "mission", "name": mission.name, "domain": domain, "scratch": scratch}),
    );
    let sealed = if mission.sealed {
        match seal::seal(&mission, &domain) {
            Ok(s) => {
                ui.note(
                    &format!(
                        "sealed: domain key, node identities, access rules and MAVLink signing from {} (this user's tools join with --domain {domain}; nobody else can)",
                        s.dir.display()
                    ),
                    json!({"event": "sealed", "key": s.key().display().to_string(), "dir": s.dir.display().to_string()}),
                );
                Some(s)
            }
            Err(e) => {
                eprintln!("usal: the mission's seal: {e:#}");
                return ExitCode::FAILURE;
            }
        }
    } else {
        ui.note(
            &format!(
                "WARNING: mission {} runs with security=\"off\": NOT sealed. Any host on its networks can read every item and command its vehicles.",
                mission.name
            ),
            json!({"event": "unsealed", "mission": mission.name}),
        );
        None
    };
    let log = if args.no_log {
        None
    } else {
        let created = match &args.log {
            Some(path) => flightlog::FlightLog::create(path, &mission.name, &args.mission, &domain),
            None => {
                flightlog::create_default(Path::new("logs"), &mission.name, &args.mission, &domain)
            }
        };
        match created {
            Ok(l) => {
                let path = l.path().to_owned();
                ui.set_log(l.clone());
                ui.note(
                    &format!("flight log: {}", path.display()),
                    json!({"event": "flight_log", "path": path.display().to_string()}),
                );
                Some(l)
            }
            Err(e) => {
                eprintln!("usal: {e}");
                return ExitCode::from(EXIT_USAGE);
            }
        }
    };
    let stop = CancellationToken::new();
    let signals = tokio::spawn(wait_for_signal(stop.clone(), ui.clone()));
    let mut sup = Supervisor::new(ui.clone());
    let mut notices = sup.subscribe();
    let station_notices: Vec<_> = stations.iter().map(|_| sup.subscribe()).collect();

    // A radio first: it gives the nodes it joins their networks.
    let mut lans = std::collections::HashMap::new();
    let mut radio = match mission.radio.clone() {
        None => Ok(None),
        Some(spec) => radio::start(
            &mut mission,
            &spec,
            &domain,
            &bins,
            &scratch,
            &mut sup,
            &ui,
            &mut lans,
        )
        .await
        .map(|r| Some(vec![r])),
    };
    // A fleet's further radios, one per vehicle, to the same ground LAN.
    for spec in mission.extra_radios.clone() {
        let Ok(Some(links)) = &mut radio else { break };
        match radio::start(
            &mut mission,
            &spec,
            &domain,
            &bins,
            &scratch,
            &mut sup,
            &ui,
            &mut lans,
        )
        .await
        {
            Ok(r) => links.push(r),
            Err(e) => radio = Err(e),
        }
    }
    // A router: it gives the nodes it joins their networks too.
    let radio = match (radio, mission.router.clone()) {
        (Ok(r), Some(spec)) => {
            router::start(&mut mission, &spec, &domain, &bins, &scratch, &mut sup, &ui).map(|()| r)
        }
        (r, _) => r,
    };
    let _radio = match radio {
        Ok(r) => r,
        Err(e) => {
            ui.clear_bar();
            eprintln!("usal: {e:#}");
            sup.shutdown().await;
            signals.abort();
            return ExitCode::FAILURE;
        }
    };
    for (st, (node, _)) in stations.iter_mut().zip(mission.stations()) {
        st.network = node.network.clone();
        st.log.clone_from(&log);
    }
    let log_stop = CancellationToken::new();
    let recorder = log
        .as_ref()
        .map(|l| start_recorder(l, &stations, &mission, &domain, &log_stop, &ui));
    let mavlink_key = sealed.as_ref().map(seal::Sealed::mavlink_key);
    let air_logs = log.as_ref().map(|l| flightlog::air_dir(l.path()));
    let code = match start_services(
        &mission,
        &domain,
        &bins,
        args,
        mavlink_key.as_deref(),
        air_logs.as_deref(),
        &scratch,
        &mut sup,
        &mut notices,
        &stop,
    )
    .await
    {
        Err(e) => {
            ui.clear_bar();
            eprintln!("usal: {e:#}");
            ExitCode::FAILURE
        }
        Ok(()) if stop.is_cancelled() => interrupted(args),
        // A fleet mission without stations: the fleet layer's status is followed instead.
        Ok(()) if stations.is_empty() && mission.fleet().is_some() => {
            fleet::supervise(&mission, &domain, args, &ui, notices, &stop).await
        }
        Ok(()) => {
            supervise(
                &mission,
                stations,
                &domain,
                args,
                &ui,
                notices,
                station_notices,
                &stop,
            )
            .await
        }
    };
    ui.clear_bar();
    log_stop.cancel();
    if let Some(Ok(Err(e))) = match recorder {
        Some(r) => Some(r.await),
        None => None,
    } {
        ui.note(
            &format!("{e:#}"),
            json!({"event": "flight_log_error", "error": format!("{e:#}")}),
        );
    }
    if let Some(l) = &log {
        finish_log(l, &ui);
    }
    sup.shutdown().await;
    signals.abort();
    code
}

/// Starts recording what the stations follow into the flight log, from a node of its own on
/// the first station's network (the ground side of a radio).
fn start_recorder(
    log: &Arc<flightlog::FlightLog>,
    stations: &[StationSetup],
    mission: &Mission,
    domain: &str,
    stop: &CancellationToken,
    ui: &Ui,
) -> tokio::task::JoinHandle<anyhow::Result<()>> {
    let first = stations.first();
    let node = first.map_or_else(
        || format!("usal-flightlog-{}", std::process::id()),
        |s| format!("{}-flightlog", s.node),
    );
    // Without a station: the ground side of a radio, where a station would be.
    let ground = mission.radio.as_ref().and_then(|r| mission.node(&r.ground));
    let (network, namespace) = match (first, ground) {
        (Some(s), _) => (s.network.as_deref(), s.namespace.as_deref()),
        (None, Some(g)) => (g.network.as_deref(), g.namespace.as_deref()),
        (None, None) => (None, None),
    };
    let config =
        marea::NetworkConfig::for_service(network, &node, Some(domain), namespace).map(|mut c| {
            c.node.clone_from(&node);
            c
        });
    let mut prefixes: Vec<String> = stations
        .iter()
        .flat_map(|s| [s.vas.clone(), s.fpma.clone()])
        .collect();
    if prefixes.is_empty() {
        // No station: every VAS and FPMa of the mission.
        for n in &mission.nodes {
            for svc in &n.services {
                if matches!(svc, ServiceSpec::Vas(_) | ServiceSpec::Fpma(_)) {
                    prefixes.push(match &n.namespace {
                        Some(ns) => format!("{ns}/{}", svc.kind()),
                        None => svc.kind().to_owned(),
                    });
                }
            }
        }
    }
    let interests = flightlog::interests(&prefixes, mission.radio.is_some());
    match config {
        Ok(c) => tokio::spawn(flightlog::record_items(
            log.clone(),
            c,
            interests,
            stop.clone(),
        )),
        Err(e) => {
            ui.note(
                &format!("flight log: no telemetry recorded: {e}"),
                json!({"event": "flight_log_error", "error": e.to_string()}),
            );
            tokio::spawn(async { Ok(()) })
        }
    }
}

/// Closes the flight log and says where it is, after the summary.
fn finish_log(log: &flightlog::FlightLog, ui: &Ui) {
    let path = log.path().display().to_string();
    match log.finish() {
        Ok(n) => ui.result(
            &format!("flight log: {path} ({n} records; review it with `usal replay {path}`)"),
            json!({"event": "flight_log_written", "path": path, "records": n}),
        ),
        Err(e) => ui.result(
            &format!("flight log: {e}"),
            json!({"event": "flight_log_error", "path": path, "error": e}),
        ),
    }
}

pub(crate) fn interrupted(args: &RunArgs) -> ExitCode {
    if args.until_complete {
        eprintln!("usal: interrupted before the plan completed");
        ExitCode::from(EXIT_INTERRUPTED)
    } else {
        ExitCode::SUCCESS
    }
}

/// Starts every child of the mission, in file order; a VAS waits for its node's mavsim to say
/// where it listens.
#[allow(clippy::too_many_arguments)]
async fn start_services(
    mission: &Mission,
    domain: &str,
    bins: &Bins,
    args: &RunArgs,
    signing_key: Option<&Path>,
    air_logs: Option<&Path>,
    scratch: &Path,
    sup: &mut Supervisor,
    notices: &mut broadcast::Receiver<Notice>,
    stop: &CancellationToken,
) -> anyhow::Result<()> {
    let manual_stations = manual_stations(mission);
    // What the cameras see standing on the ground: the fleet plan's obstacles.
    let obstacles = camera_obstacles(mission, scratch)?;
    for node in &mission.nodes {
        let mut sim_addr: Option<watch::Receiver<Option<String>>> = None;
        let common = |v: &mut Vec<String>| {
            v.extend(["--domain".into(), domain.to_owned()]);
            if let Some(ns) = &node.namespace {
                v.extend(["--namespace".into(), ns.clone()]);
            }
            if let Some(n) = &node.network {
                v.extend(["--network".into(), n.display().to_string()]);
            }
        };
        // The node's camera: its mavsim serves the frames here, the camera service reads them.
        let camera = node.services.iter().find_map(|s| match s {
            ServiceSpec::Camera(c) => Some(c),
            _ => None,
        });
        let camera_at = camera
            .map(|_| free_local_port().map(|p| format!("127.0.0.1:{p}")))
            .transpose()?;
        for svc in &node.services {
            let label = format!("{}/{}", node.name, svc.name());
            let mut a: Vec<String> = Vec::new();
            let mut announce = None;
            match svc {
                ServiceSpec::Station(_) | ServiceSpec::Autopilot(_) => continue,
                ServiceSpec::Custom(c) => {
                    sup.start(custom_child(c, node, domain, bins, label));
                    continue;
                }
                ServiceSpec::Mavsim(m) => {
                    let speedup = args.speedup.or(m.speedup).unwrap_or(1.0);
                    a.extend([
                        "--vehicle".into(),
                        m.vehicle.clone(),
                        "--udp".into(),
                        "127.0.0.1:0".into(),
                        "--speedup".into(),
                        speedup.to_string(),
                    ]);
                    if let Some(h) = &m.home {
                        a.extend(["--home".into(), h.clone()]);
                    }
                    if let Some(l) = &m.log {
                        a.extend(["--log".into(), l.display().to_string()]);
                    }
                    if let Some(c) = m.battery_capacity_mah {
                        a.extend(["--battery-capacity-mah".into(), c.to_string()]);
                    }
                    if let Some(w) = m.battery_wh_per_km {
                        a.extend(["--battery-wh-per-km".into(), w.to_string()]);
                    }
                    if let Some(p) = &m.poi_file {
                        a.extend(["--poi-file".into(), p.display().to_string()]);
                    }
                    if let Some(r) = m.sensor_radius {
                        a.extend(["--sensor-radius".into(), r.to_string()]);
                    }
                    if let Some((speed, from)) = m.wind {
                        a.extend(["--wind".into(), format!("{speed},{from}")]);
                    }
                    if let (Some(c), Some(at)) = (camera, &camera_at) {
                        a.extend([
                            "--camera".into(),
                            format!("{}x{}", c.size.0, c.size.1),
                            "--camera-fps".into(),
                            c.fps.to_string(),
                            "--camera-hfov".into(),
                            c.hfov_deg.to_string(),
                            "--camera-listen".into(),
                            at.clone(),
                        ]);
                        if let Some(file) = &obstacles {
                            a.extend(["--obstacles".into(), file.display().to_string()]);
                        }
                    }
                    if let Some(key) = signing_key.filter(|_| vas_uses_sim(node)) {
                        a.extend(["--signing-key".into(), key.display().to_string()]);
                    }
                    let (tx, rx) = watch::channel(None);
                    sim_addr = Some(rx);
                    announce = Some(Announce {
                        prefix: "MAVSIM_UDP=",
                        rebind_flag: "--udp",
                        tx,
                    });
                }
                ServiceSpec::Vas(v) => {
                    // An autopilot the mission did not start (SITL, a flight controller).
                    let autopilot = node.services.iter().find_map(|s| match s {
                        ServiceSpec::Autopilot(ap) => Some(ap),
                        _ => None,
                    });
                    if let Some(ap) = autopilot {
                        a.extend(["--autopilot".into(), ap.family.clone()]);
                    }
                    let endpoint = match (&v.endpoint, &mut sim_addr) {
                        (Some(e), _) => Some(e.clone()),
                        (None, _) if autopilot.is_some() => autopilot.map(|ap| ap.endpoint.clone()),
                        (None, Some(rx)) => {
                            if let Some(key) = signing_key {
                                a.extend(["--signing-key".into(), key.display().to_string()]);
                            }
                            Some(format!("udpout:{}", wait_sim(rx, notices, stop).await?))
                        }
                        // A config file names the endpoint.
                        (None, None) => None,
                    };
                    if stop.is_cancelled() {
                        return Ok(());
                    }
                    if let Some(c) = &v.config {
                        a.extend(["-c".into(), c.display().to_string()]);
                    }
                    if let Some(p) = &v.params {
                        a.extend(["--params".into(), p.display().to_string()]);
                    }
                    if let Some(dir) = air_logs {
                        a.extend([
                            "--air-log".into(),
                            dir.join(&node.name).display().to_string(),
                        ]);
                    }
                    if let Some(f) = &v.fence {
                        let dir = scratch.join(&node.name);
                        let file = dir.join("vehicle-fence.xml");
                        std::fs::create_dir_all(&dir)
                            .and_then(|()| std::fs::write(&file, mission::fence_xml(f)))
                            .with_context(|| format!("writing {}", file.display()))?;
                        a.extend(["--fence".into(), file.display().to_string()]);
                    }
                    if let Some(e) = endpoint {
                        a.extend(["--endpoint".into(), e]);
                    }
                    a.extend(["--vehicle".into(), v.vehicle.clone()]);
                    if let Some(q) = v.queue_size {
                        a.extend(["--queue-size".into(), q.to_string()]);
                    }
                    if let Some(h) = v.telemetry_hz {
                        a.extend(["--telemetry-hz".into(), h.to_string()]);
                    }
                    if !manual_stations.is_empty() {
                        a.extend(["--manual-stations".into(), manual_stations.clone()]);
                    }
                    common(&mut a);
                }
                ServiceSpec::Fpma(f) => {
                    a.push("run".into());
                    if let Some(c) = &f.config {
                        a.extend(["-c".into(), c.display().to_string()]);
                    }
                    a.extend(["--vehicle".into(), f.vehicle.clone()]);
                    if let Some(l) = f.lookahead {
                        a.extend(["--lookahead".into(), l.to_string()]);
                    }
                    if let Some(v) = &f.vas {
                        a.extend(["--vas".into(), v.clone()]);
                    }
                    let plans = scratch.join(&node.name).join("plans");
                    a.extend(["--plans-dir".into(), plans.display().to_string()]);
                    // Per run: a supervised restart resumes the plan, a new run starts clean.
                    let state = scratch.join(&node.name).join("fpma-state");
                    a.extend(["--state-dir".into(), state.display().to_string()]);
                    common(&mut a);
                }
                ServiceSpec::Camera(c) => {
                    let Some(at) = &camera_at else { continue };
                    a.extend([
                        "--source".into(),
                        at.clone(),
                        "--quality".into(),
                        c.quality.to_string(),
                        "--node".into(),
                        format!("{}-camera", node.name),
                    ]);
                    common(&mut a);
                }
                // The fleet layer: a service of the ground node.
                ServiceSpec::Fleet { plan } => {
                    a.extend([
                        "--plan".into(),
                        plan.display().to_string(),
                        "--node".into(),
                        format!("{}-fleet", node.name),
                    ]);
                    common(&mut a);
                }
                // The web stations print `FMO_URL=` / `FPMO_URL=` first; the merged log shows it.
                ServiceSpec::Fmo { listen, tiles } | ServiceSpec::Fpmo { listen, tiles } => {
                    a.extend([
                        "--listen".into(),
                        listen.clone(),
                        "--node".into(),
                        format!("{}-{}", node.name, svc.kind()),
                    ]);
                    if let Some(t) = tiles {
                        a.extend(["--tiles".into(), t.clone()]);
                    }
                    common(&mut a);
                }
            }
            sup.start(ChildSpec {
                label,
                kind: svc.kind(),
                program: bins.path(svc.kind()),
                args: a,
                announce,
                crash_after: None,
                env: Vec::new(),
                restart: Restart::Always,
                essential: true,
            });
        }
    }
    Ok(())
}

/// A user's `<service>` as a supervised child: its program, arguments and environment, and
/// the node's network as `marea::NetworkConfig::from_env` reads it (node `NODE-NAME`, the
/// mission's domain, the node's namespace and network file). Not essential: if it cannot be
/// kept running, the mission flies on.
fn custom_child(
    c: &mission::CustomSpec,
    node: &mission::NodeSpec,
    domain: &str,
    bins: &Bins,
    label: String,
) -> ChildSpec {
    use marea::config::env;
    let program = match &c.program {
        mission::Program::Package(p) => bins.path(p),
        mission::Program::File(p) | mission::Program::OnPath(p) => p.clone(),
    };
    let mut vars = c.env.clone();
    vars.push((env::NODE.into(), format!("{}-{}", node.name, c.name)));
    vars.push((env::DOMAIN.into(), domain.to_owned()));
    if let Some(ns) = &node.namespace {
        vars.push((env::NAMESPACE.into(), ns.clone()));
    }
    if let Some(n) = &node.network {
        vars.push((env::NETWORK.into(), n.display().to_string()));
    }
    ChildSpec {
        label,
        kind: "service",
        program,
        args: c.args.clone(),
        announce: None,
        crash_after: None,
        env: vars,
        restart: c.restart,
        essential: false,
    }
}

/// Whether `node`'s VAS flies `node`'s mavsim (it names no endpoint of its own): the link
/// the mission's MAVLink signing covers.
fn vas_uses_sim(node: &mission::NodeSpec) -> bool {
    node.services
        .iter()
        .any(|s| matches!(s, ServiceSpec::Vas(v) if v.endpoint.is_none()))
}

/// The mission's FMo stations as the VAS's `--manual-stations` list (the VAS obeys manual
/// control only from them): each FMo's node name (`NODE-fmo`, as started below) and, with a
/// namespace, its item prefix (`NS/fmo`). Empty without an FMo.
fn manual_stations(mission: &Mission) -> String {
    let mut out: Vec<String> = Vec::new();
    for node in &mission.nodes {
        for svc in &node.services {
            if matches!(svc, ServiceSpec::Fmo { .. }) {
                out.push(format!("{}-{}", node.name, svc.kind()));
                if let Some(ns) = &node.namespace {
                    out.push(format!("{ns}/fmo"));
                }
            }
        }
    }
    out.join(",")
}

/// The fleet plan's obstacles as mavsim's `--obstacles` file (in `scratch`), when a node has
/// a camera and the fleet plan obstacles.
fn camera_obstacles(mission: &Mission, scratch: &Path) -> anyhow::Result<Option<PathBuf>> {
    let filming = mission.nodes.iter().any(|n| {
        n.services
            .iter()
            .any(|s| matches!(s, ServiceSpec::Camera(_)))
    });
    let Some((_, plan)) = mission.fleet().filter(|_| filming) else {
        return Ok(None);
    };
    let plan = ::fleet::plan::load(plan).map_err(|e| anyhow!("fleet plan {e}"))?;
    if plan.obstacles.is_empty() {
        return Ok(None);
    }
    let mut text =
        String::from("# The fleet plan's obstacles, for the cameras: NAME HEIGHT LAT,LON ...\n");
    for o in &plan.obstacles {
        let corners: Vec<String> = o
            .polygon
            .iter()
            .map(|(la, lo)| format!("{la:.8},{lo:.8}"))
            .collect();
        // Names are the fleet plan's: one word each here.
        let name: String = o.name.split_whitespace().collect::<Vec<_>>().join("_");
        text += &format!("{name} {} {}\n", o.height_m, corners.join(" "));
    }
    std::fs::create_dir_all(scratch).with_context(|| format!("creating {}", scratch.display()))?;
    let file = scratch.join("camera-obstacles.txt");
    std::fs::write(&file, text).with_context(|| format!("writing {}", file.display()))?;
    Ok(Some(file))
}

/// A TCP port free on this host now (the kernel's pick, released for a child to take).
fn free_local_port() -> anyhow::Result<u16> {
    let l = std::net::TcpListener::bind("127.0.0.1:0").context("finding a free TCP port")?;
    Ok(l.local_addr()?.port())
}

/// Waits for mavsim's `MAVSIM_UDP=` line.
async fn wait_sim(
    rx: &mut watch::Receiver<Option<String>>,
    notices: &mut broadcast::Receiver<Notice>,
    stop: &CancellationToken,
) -> anyhow::Result<String> {
    let deadline = tokio::time::sleep(SIM_READY);
    tokio::pin!(deadline);
    loop {
        if let Some(a) = rx.borrow_and_update().clone() {
            return Ok(a);
        }
        tokio::select! {
            r = rx.changed() => if r.is_err() { bail!("mavsim's supervisor ended") },
            n = notices.recv() => if let Ok(Notice::GaveUp { reason, essential: true }) = n { bail!(reason) },
            () = stop.cancelled() => return Ok(String::new()),
            () = &mut deadline => bail!("mavsim did not print MAVSIM_UDP= within {SIM_READY:?}"),
        }
    }
}

/// `--timeout-s` as a duration: positive and representable (a huge value made
/// `Duration::from_secs_f64` panic), else `None`.
pub(crate) fn run_limit(seconds: f64) -> Option<Duration> {
    (seconds > 0.0)
        .then(|| Duration::try_from_secs_f64(seconds).ok())
        .flatten()
}

/// How long a run may last: `--timeout-s`, else the mission's `timeout`, else
/// [`DEFAULT_TIMEOUT`].
pub(crate) fn time_limit(args: &RunArgs, mission: &Mission) -> Duration {
    args.timeout_s
        .and_then(run_limit)
        .or(mission.timeout)
        .unwrap_or(DEFAULT_TIMEOUT)
}

/// Runs until every station's plan completes (with `--until-complete`), a station fails, a
/// child cannot be kept running, the time limit, or a signal.
#[allow(clippy::too_many_arguments)]
async fn supervise(
    mission: &Mission,
    stations: Vec<StationSetup>,
    domain: &str,
    args: &RunArgs,
    ui: &Arc<Ui>,
    mut notices: broadcast::Receiver<Notice>,
    station_notices: Vec<broadcast::Receiver<Notice>>,
    stop: &CancellationToken,
) -> ExitCode {
    let limit = time_limit(args, mission);
    let deadline = tokio::time::sleep(limit);
    tokio::pin!(deadline);
    let station_stop = stop.child_token();
    // Every station at once; one failing stops the others (they report how far they got).
    let follow = async {
        if stations.is_empty() {
            station_stop.cancelled().await;
            return Vec::new();
        }
        let mut set = tokio::task::JoinSet::new();
        for (i, (mut s, n)) in stations.into_iter().zip(station_notices).enumerate() {
            s.domain = domain.to_owned();
            let (ui, stop) = (ui.clone(), station_stop.clone());
            let until_complete = args.until_complete;
            set.spawn(async move {
                let out = station::run(s, ui, n, stop.clone(), until_complete).await;
                if matches!(out, Outcome::Failed(_)) {
                    stop.cancel();
                }
                (i, out)
            });
        }
        let mut outs: Vec<(usize, Outcome)> = Vec::new();
        while let Some(r) = set.join_next().await {
            match r {
                Ok(o) => outs.push(o),
                Err(e) => {
                    station_stop.cancel();
                    outs.push((usize::MAX, Outcome::Failed(format!("station task: {e}"))));
                }
            }
        }
        outs.sort_by_key(|(i, _)| *i);
        outs.into_iter().map(|(_, o)| o).collect::<Vec<Outcome>>()
    };
    tokio::pin!(follow);
    let failure = loop {
        tokio::select! {
            outs = &mut follow => return conclude(mission, args, ui, outs),
            n = notices.recv() => {
                if let Ok(Notice::GaveUp { reason, essential: true }) = n {
                    break reason;
                }
            }
            () = &mut deadline, if args.until_complete => {
                break format!("the plan did not complete within {limit:?}");
            }
        }
    };
    // Let the stations print what they have, then report the failure.
    station_stop.cancel();
    let outs = follow.await;
    let fleet = outs.len() > 1;
    for out in &outs {
        if let Outcome::Stopped(summary) | Outcome::Completed(summary) = out {
            show_summary(mission, ui, summary);
        }
    }
    if fleet {
        show_fleet(mission, ui, &outs);
    }
    ui.clear_bar();
    eprintln!("usal: {failure}");
    ExitCode::FAILURE
}

/// The exit status and summaries once every station has returned.
fn conclude(mission: &Mission, args: &RunArgs, ui: &Ui, outs: Vec<Outcome>) -> ExitCode {
    let fleet = outs.len() > 1;
    let failures: Vec<&str> = outs
        .iter()
        .filter_map(|o| match o {
            Outcome::Failed(r) => Some(r.as_str()),
            _ => None,
        })
        .collect();
    let all_completed = !outs.is_empty() && outs.iter().all(|o| matches!(o, Outcome::Completed(_)));
    for out in &outs {
        match out {
            Outcome::Completed(summary) => show_summary(mission, ui, summary),
            Outcome::Stopped(summary) if args.until_complete => {
                show_summary(mission, ui, summary);
            }
            _ => {}
        }
    }
    if fleet && (args.until_complete || !failures.is_empty()) {
        show_fleet(mission, ui, &outs);
    }
    if !failures.is_empty() {
        ui.clear_bar();
        for reason in failures {
            eprintln!("usal: {reason}");
        }
        return ExitCode::FAILURE;
    }
    if !all_completed {
        return interrupted(args);
    }
    let off_plan: Vec<String> = outs
        .iter()
        .filter_map(|o| match o {
            Outcome::Completed(s) if !s.as_planned() => {
                Some(s.vehicle.clone().unwrap_or_else(|| "the vehicle".into()))
            }
            _ => None,
        })
        .collect();
    if off_plan.is_empty() {
        ExitCode::SUCCESS
    } else if fleet {
        eprintln!(
            "usal: the plans completed, but not as planned for {} (see the summaries)",
            off_plan.join(", ")
        );
        ExitCode::FAILURE
    } else {
        eprintln!("usal: the plan completed, but not as planned (see the summary)");
        ExitCode::FAILURE
    }
}

fn show_summary(mission: &Mission, ui: &Ui, summary: &station::Summary) {
    ui.result(
        &summary.text(&mission.name),
        json!({"event": "summary", "summary": summary}),
    );
}

/// The fleet's line: how many vehicles completed their plans.
fn show_fleet(mission: &Mission, ui: &Ui, outs: &[Outcome]) {
    let completed: Vec<&str> = outs
        .iter()
        .filter_map(|o| match o {
            Outcome::Completed(s) => Some(s.vehicle.as_deref().unwrap_or("-")),
            _ => None,
        })
        .collect();
    ui.result(
        &format!(
            "mission {}: {} of {} vehicles completed their plans",
            mission.name,
            completed.len(),
            outs.len()
        ),
        json!({"event": "fleet_summary", "vehicles": outs.len(), "completed": completed}),
    );
}

/// Ctrl-C or SIGTERM: stop everything.
async fn wait_for_signal(stop: CancellationToken, ui: Arc<Ui>) {
    marea::process::terminated().await;
    ui.note(
        "stopping: SIGTERM to every service, SIGKILL after 5 s",
        json!({"event": "stopping"}),
    );
    stop.cancel();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_demo_vas_obeys_manual_control_only_from_the_demo_fmo() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/missions/rover-demo.xml");
        let mission = Mission::load(&path).expect("the demo mission parses");
        assert_eq!(manual_stations(&mission), "ground-fmo,gcs/fmo");
    }

    #[test]
    fn a_waypoint_far_from_home_is_named_before_the_upload() {
        let wp = |lat: f64, lon: f64| flightplan::expand::Waypoint {
            lat,
            lon,
            alt: 0.0,
            speed: 2.0,
            fly_over: false,
            leg: "east".into(),
            tag: Default::default(),
            waits: false,
            land_start: false,
            fix_crossing: false,
            seq: 0,
            version: 0,
        };
        let home = (41.275, 1.987);
        let near = [wp(41.275, 1.987), wp(41.276, 1.988)];
        assert_eq!(far_from_home(&near, home, 5_000.0), None);
        // One latitude with its sign lost: 9,000 km away.
        let typo = [wp(41.275, 1.987), wp(-41.276, 1.988), wp(41.276, 1.989)];
        let w = far_from_home(&typo, home, 5_000.0).expect("a warning");
        assert!(
            w.starts_with("waypoint 2 (leg east, -41.276000,1.988000) is 9142.3 km from home")
                && w.contains("check its coordinates"),
            "{w}"
        );
    }

    #[test]
    fn a_timeout_must_be_positive_and_representable() {
        assert_eq!(run_limit(1.5), Some(Duration::from_millis(1500)));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e30] {
            assert_eq!(run_limit(bad), None, "{bad}");
        }
    }
}

//! `mavsim`: command-line front end of the simulator (argument parsing, tracing, signals).

use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::{Parser, ValueEnum};
use mavsim::battery::BatteryConfig;
use mavsim::detector::Detector;
use mavsim::kinematics::{GeoPoint, VehicleKind};
use mavsim::link::{LinkConfig, LinkInfo};
use mavsim::profile::Profile;
use mavsim::sim::{SimConfig, Simulator};
use mavsim::vehicle::VehicleConfig;
use tokio_util::sync::CancellationToken;

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Kind {
    Rover,
    Copter,
    Plane,
}

/// ArduPilot-compatible MAVLink vehicle simulator.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Vehicle kind.
    #[arg(long, value_enum, default_value = "rover")]
    vehicle: Kind,
    /// MAVLink system id.
    #[arg(long, default_value_t = 1)]
    sysid: u8,
    /// Home position: LAT,LON,ALT (degrees, degrees, metres AMSL).
    #[arg(long, default_value = "41.2757,1.9881,10", allow_hyphen_values = true)]
    home: String,
    /// Simulated seconds per wall second.
    #[arg(long, default_value_t = 1.0)]
    speedup: f64,
    /// UDP address to bind (port 0 picks one); replies go to the last sender.
    #[arg(long, default_value = "127.0.0.1:14560")]
    udp: SocketAddr,
    /// Also send everything to this UDP address, as `udp:HOST:PORT` (like SITL --out).
    #[arg(long)]
    out: Option<String>,
    /// Speak on this serial device instead of UDP.
    #[arg(long, conflicts_with = "pty")]
    serial: Option<String>,
    /// Baud rate of --serial.
    #[arg(long, default_value_t = 57_600)]
    baud: u32,
    /// Create a pty pair and speak on it instead of UDP; prints `MAVSIM_PTY=<slave path>`.
    #[arg(long)]
    pty: bool,
    /// Write JSON lines of mission/mode/arming events to this file.
    #[arg(long)]
    log: Option<PathBuf>,
    /// Report no mission progress (no MISSION_ITEM_REACHED, no "Reached" text, MISSION_CURRENT
    /// only in answer to a set-current), like autopilots whose ground station must infer it.
    #[arg(long)]
    quiet_progress: bool,
    /// For this many simulated seconds after start, answer mode changes and arming with
    /// MAV_RESULT_TEMPORARILY_REJECTED, as an autopilot whose pre-flight checks are still
    /// running does (PX4, MAVSDK-built vehicles).
    #[arg(long, default_value_t = 0.0)]
    not_ready_s: f64,
    /// Move the current mission item on this many wall-clock milliseconds after reporting a
    /// waypoint reached, to the item after the one reached whatever was set meanwhile, as
    /// MAVSDK's mission server does (for testing ground stations: a set-current sent before it
    /// is overridden).
    #[arg(long, default_value_t = 0)]
    late_advance_ms: u64,
    /// A steady wind, SPEED,FROM: metres per second and the direction it blows from (degrees
    /// clockwise from north, as a forecast gives it). Aircraft drift with it and fly against
    /// it (a plane crabs, a copter leans); a rover does not feel it.
    #[arg(long, value_parser = parse_wind, default_value = "0,0")]
    wind: (f64, f64),
    /// MAVLink 2 signing key file (64 hex digits, mode 600): sign every frame and accept only
    /// frames signed with this key.
    #[arg(long)]
    signing_key: Option<PathBuf>,
    /// Link id put in our signatures (with --signing-key).
    #[arg(long, default_value_t = 0)]
    signing_link_id: u8,
    /// Whose conventions to follow: ArduPilot's (default), PX4's (PX4 custom modes, item 0
    /// ordinary, no partial writes, current item reset to 0 by an upload, MISSION_CURRENT only
    /// on change) or a generic autopilot's (ArduPilot modes, PX4's mission conventions);
    /// ardupilot-resetting says it is ArduPilot but resets its current item after a whole
    /// upload and answers no partial write.
    #[arg(long, value_enum, default_value = "ardupilot")]
    autopilot: AutopilotArg,
    /// Battery capacity, mAh.
    #[arg(long, default_value_t = 5000.0)]
    battery_capacity_mah: f64,
    /// Battery energy spent per kilometre covered, Wh/km.
    #[arg(long, default_value_t = 5.0)]
    battery_wh_per_km: f64,
    /// Battery current drawn while armed, moving or not, A.
    #[arg(long, default_value_t = 0.5)]
    battery_idle_a: f64,
    /// Points of interest (one `LAT,LON` a line, `#` comments) this vehicle's detector reports,
    /// each once, as a STATUSTEXT `POI <id> <lat> <lon>` when it comes within --sensor-radius.
    #[arg(long)]
    poi_file: Option<PathBuf>,
    /// Sensor footprint radius of the detector, metres (with --poi-file).
    #[arg(long, default_value_t = 10.0)]
    sensor_radius: f64,
    /// Most items one fence transfer may have (polygon vertices and circles); a larger
    /// MISSION_COUNT for the fence is answered MAV_MISSION_NO_SPACE, as a board with little
    /// storage does.
    #[arg(long, default_value_t = mavsim::fence::DEFAULT_CAPACITY)]
    fence_capacity: u16,
    /// A downward camera of WIDTHxHEIGHT pixels (e.g. 320x240): frames of the ground, the
    /// points of interest and home, served over TCP (--camera-listen; its address is printed as
    /// `MAVSIM_CAMERA=ADDR` after the link's line) to the camera service.
    #[arg(long, value_parser = usal_types::camera::parse_size)]
    camera: Option<(u32, u32)>,
    /// Camera frames a second.
    #[arg(long, default_value_t = 5.0, value_parser = parse_fps)]
    camera_fps: f64,
    /// Camera horizontal field of view, degrees.
    #[arg(long, default_value_t = 70.0, value_parser = parse_hfov)]
    camera_hfov: f64,
    /// Where the camera's frames are served (port 0: any; printed).
    #[arg(long, default_value = "127.0.0.1:0")]
    camera_listen: SocketAddr,
    /// Obstacles the camera sees (grey roofs): one a line, `NAME HEIGHT LAT,LON LAT,LON
    /// LAT,LON ...`, `#` comments.
    #[arg(long)]
    obstacles: Option<PathBuf>,
}

fn parse_fps(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|f| (0.1..=60.0).contains(f))
        .ok_or_else(|| format!("`{s}` is not a frame rate from 0.1 to 60 a second"))
}

fn parse_hfov(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|f| (5.0..=150.0).contains(f))
        .ok_or_else(|| format!("`{s}` is not a field of view from 5 to 150 degrees"))
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum AutopilotArg {
    Ardupilot,
    Px4,
    Generic,
    /// Says it is ArduPilot but resets its current item after a whole upload and answers no
    /// partial write (for testing ground stations).
    ArdupilotResetting,
}

fn parse_wind(s: &str) -> Result<(f64, f64), String> {
    let parsed: Option<Vec<f64>> = s.split(',').map(|x| x.trim().parse().ok()).collect();
    match parsed.as_deref() {
        Some(&[speed, from]) if (0.0..=60.0).contains(&speed) && (0.0..=360.0).contains(&from) => {
            Ok((speed, from))
        }
        Some(&[_, _]) => Err(format!(
            "`{s}`: the speed must be 0..60 m/s and the direction 0..360 degrees"
        )),
        _ => Err(format!("`{s}` is not SPEED,FROM (m/s, degrees)")),
    }
}

fn parse_home(s: &str) -> anyhow::Result<GeoPoint> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [lat, lon, alt] = parts[..] else {
        bail!("--home wants LAT,LON,ALT, got {s:?}");
    };
    let home = GeoPoint {
        lat_deg: lat
            .parse()
            .with_context(|| format!("bad latitude {lat:?}"))?,
        lon_deg: lon
            .parse()
            .with_context(|| format!("bad longitude {lon:?}"))?,
        alt_m: alt
            .parse()
            .with_context(|| format!("bad altitude {alt:?}"))?,
    };
    if !(-90.0..=90.0).contains(&home.lat_deg) || !(-180.0..=180.0).contains(&home.lon_deg) {
        bail!("--home out of range: {s:?}");
    }
    Ok(home)
}

fn parse_out(s: &str) -> anyhow::Result<SocketAddr> {
    let addr = s.strip_prefix("udp:").unwrap_or(s);
    addr.parse()
        .with_context(|| format!("--out wants udp:HOST:PORT, got {s:?}"))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "mavsim=info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    if !(args.speedup.is_finite() && args.speedup >= 0.01) {
        bail!("--speedup must be at least 0.01");
    }
    let link = if args.pty {
        LinkConfig::Pty
    } else if let Some(path) = args.serial.clone() {
        LinkConfig::Serial {
            path,
            baud: args.baud,
        }
    } else {
        LinkConfig::Udp {
            bind: args.udp,
            out: args.out.as_deref().map(parse_out).transpose()?,
        }
    };
    let battery = BatteryConfig {
        capacity_mah: args.battery_capacity_mah,
        wh_per_km: args.battery_wh_per_km,
        idle_a: args.battery_idle_a,
        ..BatteryConfig::default()
    };
    battery.validate().context("--battery-*")?;
    let cfg = SimConfig {
        vehicle: VehicleConfig {
            kind: match args.vehicle {
                Kind::Rover => VehicleKind::Rover,
                Kind::Copter => VehicleKind::Copter,
                Kind::Plane => VehicleKind::Plane,
            },
            sysid: args.sysid,
            home: parse_home(&args.home)?,
        },
        link,
        speedup: args.speedup,
        log: args.log,
        quiet_progress: args.quiet_progress,
        not_ready_s: args.not_ready_s,
        late_advance_s: args.late_advance_ms as f64 / 1000.0 * args.speedup,
        wind: args.wind,
        signing: args
            .signing_key
            .as_deref()
            .map(|path| -> anyhow::Result<mavconn::Signing> {
                Ok(mavconn::Signing {
                    key: mavconn::SigningKey::load(path)?,
                    link_id: args.signing_link_id,
                })
            })
            .transpose()
            .context("--signing-key")?,
        autopilot: match args.autopilot {
            AutopilotArg::Ardupilot => Profile::ArduPilot,
            AutopilotArg::Px4 => Profile::Px4,
            AutopilotArg::Generic => Profile::Generic,
            AutopilotArg::ArdupilotResetting => Profile::ArduPilotResetting,
        },
        battery,
        fence_capacity: args.fence_capacity,
    };
    let pois = args
        .poi_file
        .as_deref()
        .map(mavsim::detector::load_pois)
        .transpose()
        .context("--poi-file")?
        .unwrap_or_default();
    let detector = args
        .poi_file
        .is_some()
        .then(|| Detector::new(cfg.vehicle.home, &pois, args.sensor_radius))
        .transpose()
        .context("--poi-file")?;
    let home = cfg.vehicle.home;
    let mut sim = Simulator::open(cfg).await.context("starting mavsim")?;
    if let Some(d) = detector {
        sim.set_detector(d);
    }
    let camera = match args.camera {
        Some((width, height)) => {
            let listener = tokio::net::TcpListener::bind(args.camera_listen)
                .await
                .with_context(|| format!("--camera-listen {}", args.camera_listen))?;
            let cfg = mavsim::camera::CameraConfig {
                width,
                height,
                fps: args.camera_fps,
                hfov_deg: args.camera_hfov,
            };
            let frame = mavsim::kinematics::LocalFrame::new(home);
            let local = |(lat, lon): (f64, f64)| {
                let n = frame.to_local(GeoPoint {
                    lat_deg: lat,
                    lon_deg: lon,
                    alt_m: home.alt_m,
                });
                (n.north, n.east)
            };
            let obstacles = match &args.obstacles {
                Some(path) => {
                    let src = std::fs::read_to_string(path)
                        .with_context(|| format!("--obstacles {}", path.display()))?;
                    mavsim::camera::parse_obstacles(&src, &path.display().to_string())
                        .map_err(|e| anyhow::anyhow!("--obstacles: {e}"))?
                }
                None => Vec::new(),
            };
            let scene = mavsim::camera::Scene {
                pois: pois.iter().map(|p| local((p.lat, p.lon))).collect(),
                obstacles: obstacles
                    .into_iter()
                    .map(|o| o.into_iter().map(local).collect())
                    .collect(),
            };
            Some((cfg, listener, sim.camera_view(cfg.hfov_deg), scene))
        }
        None => None,
    };
    // One machine-readable line on stdout so scripts and tests find the endpoint.
    let line = match sim.link_info() {
        LinkInfo::Udp(addr) => format!("MAVSIM_UDP={addr}"),
        LinkInfo::Serial(path) => format!("MAVSIM_SERIAL={path}"),
        LinkInfo::Pty(path) => format!("MAVSIM_PTY={path}"),
    };
    {
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "{line}")?;
        stdout.flush()?;
    }
    tracing::info!("{line}");
    let shutdown = CancellationToken::new();
    if let Some((cfg, listener, view, scene)) = camera {
        let line = format!("MAVSIM_CAMERA={}", listener.local_addr()?);
        {
            // A reader that took only the link's line may have closed our stdout: the address
            // is in the log too, and the simulator goes on.
            let mut stdout = std::io::stdout().lock();
            let _ = writeln!(stdout, "{line}").and_then(|()| stdout.flush());
        }
        tracing::info!(
            "{line} ({}x{} at {} frames a second; {} points of interest, {} obstacles)",
            cfg.width,
            cfg.height,
            cfg.fps,
            scene.pois.len(),
            scene.obstacles.len()
        );
        tokio::spawn(mavsim::camera::serve(
            cfg,
            listener,
            view,
            scene,
            shutdown.clone(),
        ));
    }

    let signal_token = shutdown.clone();
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("installing the SIGTERM handler")?;
    tokio::spawn(async move {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = sigterm.recv() => {}
        }
        signal_token.cancel();
    });
    sim.run(shutdown).await.context("mavsim failed")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fence_capacity_defaults_to_500_and_is_read() {
        let args = Args::try_parse_from(["mavsim"]).unwrap();
        assert_eq!(args.fence_capacity, 500);
        let args = Args::try_parse_from(["mavsim", "--fence-capacity", "16"]).unwrap();
        assert_eq!(args.fence_capacity, 16);
        // A MISSION_COUNT is a u16: more could never be asked for.
        assert!(Args::try_parse_from(["mavsim", "--fence-capacity", "70000"]).is_err());
        assert!(Args::try_parse_from(["mavsim", "--fence-capacity", "-1"]).is_err());
    }
}

//! A simulated downward camera (`--camera WxH`): what a camera under the vehicle would see of a
//! synthetic ground (a grass chequer of 5 m squares, darker lines every 25 m), the points of
//! interest (red discs), the obstacles (grey roofs, `--obstacles`) and home (a white cross),
//! rendered at a configured size and rate and
//! served to whoever connects over TCP (`--camera-listen`), as an IP camera would. The camera
//! service (`services/camera`) reads it and publishes the frames over marea.
//!
//! The geometry is [`usal_types::camera::CameraPose`]'s: nadir, the picture's top along the
//! heading, so a station's click on a pixel lands where the simulator drew it.
//!
//! Stream: each frame is `"MCF1"`, a u32 LE header length, the header (JSON:
//! `{"seq", "taken_unix_ms", "width", "height", "pose"}`), a u32 LE data length and the
//! picture (RGB, 3 bytes a pixel, rows top to bottom). A reader slower than the camera misses
//! frames, never stalls the simulator.

use std::sync::Arc;
use std::time::Duration;

use tokio::io::AsyncWriteExt;
use tokio::net::TcpListener;
use tokio::sync::{broadcast, watch};
use tokio_util::sync::CancellationToken;
use usal_types::camera::CameraPose;

use crate::kinematics::Ned;

/// Stream magic: one frame follows.
pub const MAGIC: &[u8; 4] = b"MCF1";
/// Radius of a point of interest's disc on the ground, metres.
const POI_RADIUS_M: f64 = 1.5;

/// How the camera is set up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraConfig {
    /// Picture width, pixels.
    pub width: u32,
    /// Picture height, pixels.
    pub height: u32,
    /// Frames a second (wall clock).
    pub fps: f64,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
}

/// The vehicle as the camera sees it: where it is (local and geographic) and its heading.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CameraView {
    /// Position in the local frame.
    pub at: Ned,
    /// The pose a frame carries (geographic position, height, heading, field of view).
    pub pose: CameraPose,
}

/// What stands on the ground, in the local frame (metres north and east of home).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    /// Points of interest.
    pub pois: Vec<(f64, f64)>,
    /// Obstacles' outlines.
    pub obstacles: Vec<Vec<(f64, f64)>>,
}

/// Reads an obstacles file: one obstacle a line, `NAME HEIGHT LAT,LON LAT,LON LAT,LON ...`
/// (at least three corners); blank lines and `#` comments skipped. Returns the outlines,
/// `(lat, lon)`.
///
/// # Errors
/// `FILE:LINE: what` for a line that is not one.
pub fn parse_obstacles(src: &str, name: &str) -> Result<Vec<Vec<(f64, f64)>>, String> {
    let mut out = Vec::new();
    for (i, raw) in src.lines().enumerate() {
        let text = raw.split('#').next().unwrap_or("").trim();
        if text.is_empty() {
            continue;
        }
        let bad = |what: &str| format!("{name}:{}: {what} in `{text}`", i + 1);
        let mut words = text.split_whitespace();
        let _obstacle = words.next();
        // A camera looking down sees the roof, whatever the height.
        words
            .next()
            .and_then(|h| h.parse::<f64>().ok())
            .filter(|h| h.is_finite() && *h >= 0.0)
            .ok_or_else(|| bad("no height (metres) after the name"))?;
        let corners: Option<Vec<(f64, f64)>> = words
            .map(|w| {
                let (la, lo) = w.split_once(',')?;
                let (la, lo): (f64, f64) = (la.parse().ok()?, lo.parse().ok()?);
                ((-90.0..=90.0).contains(&la) && (-180.0..=180.0).contains(&lo)).then_some((la, lo))
            })
            .collect();
        let corners = corners.ok_or_else(|| bad("a corner is not LAT,LON in range"))?;
        if corners.len() < 3 {
            return Err(bad("fewer than three corners"));
        }
        out.push(corners);
    }
    Ok(out)
}

/// Whether `p` is inside polygon `w` (even-odd rule).
fn inside(p: (f64, f64), w: &[(f64, f64)]) -> bool {
    let mut c = false;
    for (k, a) in w.iter().enumerate() {
        let b = w[(k + 1) % w.len()];
        if (a.0 > p.0) != (b.0 > p.0) && p.1 < (b.1 - a.1) * (p.0 - a.0) / (b.0 - a.0) + a.1 {
            c = !c;
        }
    }
    c
}

/// Renders the picture seen from `view`: RGB, rows top to bottom.
pub fn render(cfg: &CameraConfig, view: &CameraView, scene: &Scene) -> Vec<u8> {
    let (w, h) = (cfg.width, cfg.height);
    let mut out = Vec::with_capacity((w * h * 3) as usize);
    // The pixel's ground offset is linear in x and y: two steps and an origin.
    let o = view.pose.ground_offset(0.0, 0.0, w, h);
    let dx = view.pose.ground_offset(1.0, 0.0, w, h);
    let dy = view.pose.ground_offset(0.0, 1.0, w, h);
    let (sx, sy) = ((dx.0 - o.0, dx.1 - o.1), (dy.0 - o.0, dy.1 - o.1));
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (f64::from(x), f64::from(y));
            let n = view.at.north + o.0 + sx.0 * fx + sy.0 * fy;
            let e = view.at.east + o.1 + sx.1 * fx + sy.1 * fy;
            out.extend_from_slice(&ground(n, e, scene));
        }
    }
    out
}

/// The colour of the ground at `(north, east)` metres from home.
fn ground(n: f64, e: f64, scene: &Scene) -> [u8; 3] {
    if scene.obstacles.iter().any(|o| inside((n, e), o)) {
        return [120, 120, 125];
    }
    if scene
        .pois
        .iter()
        .any(|p| (p.0 - n).powi(2) + (p.1 - e).powi(2) <= POI_RADIUS_M * POI_RADIUS_M)
    {
        return [220, 30, 30];
    }
    if (n.abs() < 3.0 && e.abs() < 0.4) || (e.abs() < 3.0 && n.abs() < 0.4) {
        return [245, 245, 245];
    }
    let line = |v: f64| (v.rem_euclid(25.0)).min(25.0 - v.rem_euclid(25.0)) < 0.3;
    if line(n) || line(e) {
        return [70, 100, 60];
    }
    if ((n / 5.0).floor() + (e / 5.0).floor()).rem_euclid(2.0) < 1.0 {
        [110, 160, 80]
    } else {
        [95, 140, 70]
    }
}

/// One frame on the stream (see the module's documentation).
pub fn encode_frame(
    seq: u64,
    taken_unix_ms: u64,
    cfg: &CameraConfig,
    pose: &CameraPose,
    rgb: &[u8],
) -> Vec<u8> {
    let header = serde_json::json!({
        "seq": seq,
        "taken_unix_ms": taken_unix_ms,
        "width": cfg.width,
        "height": cfg.height,
        "pose": pose,
    })
    .to_string();
    let mut out = Vec::with_capacity(12 + header.len() + rgb.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&(rgb.len() as u32).to_le_bytes());
    out.extend_from_slice(rgb);
    out
}

/// The camera: renders from the latest `view` at the configured rate while someone watches,
/// and serves the frames on `listener` until `shutdown`.
pub async fn serve(
    cfg: CameraConfig,
    listener: TcpListener,
    mut view: watch::Receiver<CameraView>,
    scene: Scene,
    shutdown: CancellationToken,
) {
    let (tx, _) = broadcast::channel::<Arc<Vec<u8>>>(2);
    let accept = {
        let tx = tx.clone();
        let shutdown = shutdown.clone();
        async move {
            loop {
                let (mut sock, peer) = tokio::select! {
                    () = shutdown.cancelled() => return,
                    r = listener.accept() => match r {
                        Ok(x) => x,
                        Err(e) => {
                            tracing::warn!("camera: accepting a viewer: {e}");
                            tokio::time::sleep(Duration::from_millis(200)).await;
                            continue;
                        }
                    },
                };
                tracing::info!("camera: viewer {peer} connected");
                let _ = sock.set_nodelay(true);
                let mut rx = tx.subscribe();
                let shutdown = shutdown.clone();
                tokio::spawn(async move {
                    loop {
                        let frame = tokio::select! {
                            () = shutdown.cancelled() => return,
                            f = rx.recv() => match f {
                                Ok(f) => f,
                                // Slower than the camera: the next frame, not the old ones.
                                Err(broadcast::error::RecvError::Lagged(_)) => continue,
                                Err(broadcast::error::RecvError::Closed) => return,
                            },
                        };
                        if let Err(e) = sock.write_all(&frame).await {
                            tracing::info!("camera: viewer {peer} gone: {e}");
                            return;
                        }
                    }
                });
            }
        }
    };
    tokio::spawn(accept);
    let period = Duration::from_secs_f64(1.0 / cfg.fps.clamp(0.1, 60.0));
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut seq = 0u64;
    loop {
        tokio::select! {
            () = shutdown.cancelled() => return,
            _ = tick.tick() => {}
        }
        if tx.receiver_count() == 0 {
            continue;
        }
        let v = *view.borrow_and_update();
        let rgb = render(&cfg, &v, &scene);
        let taken = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        let _ = tx.send(Arc::new(encode_frame(seq, taken, &cfg, &v.pose, &rgb)));
        seq += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CFG: CameraConfig = CameraConfig {
        width: 80,
        height: 60,
        fps: 5.0,
        hfov_deg: 90.0,
    };

    fn view(north: f64, east: f64, height_m: f64, heading_deg: f64) -> CameraView {
        CameraView {
            at: Ned {
                north,
                east,
                up: height_m,
            },
            pose: CameraPose {
                lat: 41.0,
                lon: 2.0,
                height_m,
                heading_deg,
                hfov_deg: CFG.hfov_deg,
            },
        }
    }

    fn pixel(rgb: &[u8], x: u32, y: u32) -> [u8; 3] {
        let i = ((y * CFG.width + x) * 3) as usize;
        [rgb[i], rgb[i + 1], rgb[i + 2]]
    }

    const RED: [u8; 3] = [220, 30, 30];

    fn scene(pois: &[(f64, f64)]) -> Scene {
        Scene {
            pois: pois.to_vec(),
            obstacles: vec![],
        }
    }

    #[test]
    fn an_obstacle_shows_as_a_grey_roof_where_it_stands() {
        // A shed 10-15 m north of the vehicle, 5 m wide.
        let scene = Scene {
            pois: vec![],
            obstacles: vec![vec![
                (110.0, 47.5),
                (110.0, 52.5),
                (115.0, 52.5),
                (115.0, 47.5),
            ]],
        };
        let rgb = render(&CFG, &view(100.0, 50.0, 20.0, 0.0), &scene);
        // 20 m up, 90°: 30 m along 60 rows, 2 rows a metre: 12.5 m ahead is 25 rows up.
        assert_eq!(pixel(&rgb, 40, 5), [120, 120, 125]);
        assert_ne!(pixel(&rgb, 40, 30), [120, 120, 125]);
    }

    #[test]
    fn an_obstacles_file_is_read_or_its_fault_named() {
        let src = "# sheds\nshed 6 41.0,2.0 41.0,2.001 41.001,2.001\n\nbarn 4 41.1,2.1 41.1,2.2 41.2,2.2 41.2,2.1\n";
        let o = parse_obstacles(src, "o.txt").unwrap();
        assert_eq!(o.len(), 2);
        assert_eq!(o[1].len(), 4);
        let e = parse_obstacles("shed 6 41.0,2.0 41.0,2.1", "o.txt").unwrap_err();
        assert!(e.starts_with("o.txt:1: fewer than three corners"), "{e}");
        let e = parse_obstacles("shed tall 41.0,2.0", "o.txt").unwrap_err();
        assert!(e.contains("no height"), "{e}");
        let e = parse_obstacles("\nshed 6 41.0,2.0 95.0,2.1 41.0,2.2", "o.txt").unwrap_err();
        assert!(e.starts_with("o.txt:2: a corner is not LAT,LON"), "{e}");
    }

    #[test]
    fn a_point_below_is_at_the_centre_and_one_ahead_above_it() {
        // 20 m up with a 90° field: 40 m across, 30 m along; a point 10 m north of the
        // vehicle heading north is a third of the way up from the centre.
        let pois = [(100.0, 50.0), (110.0, 50.0)];
        let rgb = render(&CFG, &view(100.0, 50.0, 20.0, 0.0), &scene(&pois));
        assert_eq!(rgb.len(), (80 * 60 * 3) as usize);
        assert_eq!(pixel(&rgb, 40, 30), RED);
        assert_eq!(pixel(&rgb, 40, 10), RED, "10 m ahead: 20 rows up");
        assert_ne!(pixel(&rgb, 40, 20), RED);
        // Heading east, the point north is to the left.
        let rgb = render(&CFG, &view(100.0, 50.0, 20.0, 90.0), &scene(&pois));
        assert_eq!(pixel(&rgb, 20, 30), RED, "north is left when heading east");
    }

    #[test]
    fn higher_up_the_same_point_is_smaller_and_nearer_the_centre() {
        let pois = [(105.0, 50.0)];
        let reds = |h| {
            render(&CFG, &view(100.0, 50.0, h, 0.0), &scene(&pois))
                .chunks(3)
                .filter(|p| *p == RED)
                .count()
        };
        assert!(reds(10.0) > reds(40.0) && reds(40.0) > 0);
        // Out of the picture when it is farther than the footprint's half.
        let rgb = render(&CFG, &view(100.0, 50.0, 3.0, 0.0), &scene(&pois));
        assert!(!rgb.chunks(3).any(|p| p == RED));
    }

    #[test]
    fn a_frame_carries_its_header_and_picture() {
        let v = view(0.0, 0.0, 20.0, 0.0);
        let rgb = render(&CFG, &v, &Scene::default());
        let f = encode_frame(7, 1234, &CFG, &v.pose, &rgb);
        assert_eq!(&f[..4], MAGIC);
        let hl = u32::from_le_bytes(f[4..8].try_into().unwrap()) as usize;
        let header: serde_json::Value = serde_json::from_slice(&f[8..8 + hl]).unwrap();
        assert_eq!(
            (header["seq"].as_u64(), header["width"].as_u64()),
            (Some(7), Some(80))
        );
        assert_eq!(header["pose"]["height_m"].as_f64(), Some(20.0));
        let dl = u32::from_le_bytes(f[8 + hl..12 + hl].try_into().unwrap()) as usize;
        assert_eq!(dl, rgb.len());
        assert_eq!(&f[12 + hl..], &rgb[..]);
    }
}

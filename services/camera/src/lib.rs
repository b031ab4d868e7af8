//! The camera service: a vehicle's camera frames over marea (seeds 000 and 002: the search's
//! video to the operator). It reads a camera's stream (mavsim's `--camera`, see [`stream`]) and
//! publishes each frame three ways, as the links it crosses want it:
//!
//! | kind | item | type | what for |
//! |---|---|---|---|
//! | variable | `raw` | `usal_types::camera::CameraFrame` (`rgb8`) | services on board, over shared memory (no compression to undo) |
//! | variable | `frame` | `CameraFrame` (`jpeg`) | the stations, over Ethernet or a router |
//! | function | `snapshot` | `u32` (most pixels wide) → `CameraFrame` (`jpeg`) | a small picture on request, over a radio |
//!
//! Variables go only to the nodes that subscribe, newest value first: a station that cannot
//! keep up gets the latest frame, not a backlog. Each frame carries the camera's pose, so a
//! station puts any pixel on the map ([`usal_types::camera::CameraFrame::ground_point`]).

pub mod stream;

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use marea::{NetworkConfig, Node};
use tokio_util::sync::CancellationToken;
use usal_types::camera::CameraFrame;
use usal_types::items::camera as items;

use crate::stream::RawFrame;

/// How the service runs.
#[derive(Clone, Debug)]
pub struct CameraConfig {
    /// The camera's stream, `HOST:PORT` (mavsim's `MAVSIM_CAMERA=`).
    pub source: String,
    /// JPEG quality, 1-100.
    pub quality: u8,
    /// A network.xml; default Ethernet on loopback.
    pub network: Option<PathBuf>,
    /// Node name.
    pub node: String,
    /// Discovery domain (overrides the network file's).
    pub domain: Option<String>,
    /// Namespace of the items (`uav1` → `uav1/camera/frame`).
    pub namespace: Option<String>,
}

/// A frame as JPEG of `quality`, at most `max_width` pixels wide (scaled down, nearest pixel).
///
/// # Errors
/// The encoder's, for a picture it cannot take (over 65,535 pixels a side).
pub fn to_jpeg(f: &RawFrame, quality: u8, max_width: u32) -> anyhow::Result<CameraFrame> {
    let (w, h) = if f.width > max_width.max(16) {
        let w = max_width.max(16);
        (
            w,
            (u64::from(f.height) * u64::from(w) / u64::from(f.width)).max(1) as u32,
        )
    } else {
        (f.width, f.height)
    };
    let scaled;
    let pixels: &[u8] = if (w, h) == (f.width, f.height) {
        &f.rgb
    } else {
        scaled = scale(&f.rgb, f.width, f.height, w, h);
        &scaled
    };
    let mut data = Vec::new();
    jpeg_encoder::Encoder::new(&mut data, quality.clamp(1, 100))
        .encode(
            pixels,
            u16::try_from(w).context("width")?,
            u16::try_from(h).context("height")?,
            jpeg_encoder::ColorType::Rgb,
        )
        .context("encoding JPEG")?;
    Ok(CameraFrame {
        seq: f.seq,
        taken_unix_ms: f.taken_unix_ms,
        width: w,
        height: h,
        format: "jpeg".into(),
        data,
        pose: f.pose,
    })
}

/// `rgb` (`w` × `h`) scaled to `nw` × `nh`, nearest pixel.
fn scale(rgb: &[u8], w: u32, h: u32, nw: u32, nh: u32) -> Vec<u8> {
    let mut out = Vec::with_capacity((nw * nh * 3) as usize);
    for y in 0..nh {
        let sy = (u64::from(y) * u64::from(h) / u64::from(nh)) as usize;
        for x in 0..nw {
            let sx = (u64::from(x) * u64::from(w) / u64::from(nw)) as usize;
            let i = (sy * w as usize + sx) * 3;
            out.extend_from_slice(&rgb[i..i + 3]);
        }
    }
    out
}

/// Runs the service until `shutdown`: joins the network, then follows the camera, connecting
/// again (every second) whenever it is not there or its stream breaks.
///
/// # Errors
/// When the node cannot be opened or its items declared.
pub async fn run(config: CameraConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    let mut net = NetworkConfig::for_service(
        config.network.as_deref(),
        &config.node,
        config.domain.as_deref(),
        config.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    net.node.clone_from(&config.node);
    let node = Node::open(&net).await.context("joining the network")?;
    let svc = node.service("camera")?;
    let frame_var = items::FRAME.publish(&svc)?;
    let raw_var = items::RAW.publish(&svc)?;
    let latest: Arc<Mutex<Option<RawFrame>>> = Arc::new(Mutex::new(None));
    let _snapshot = {
        let latest = latest.clone();
        let quality = config.quality;
        items::SNAPSHOT.provide(&svc, move |max_width: u32| {
            let f = marea::sync::lock(&latest).clone();
            async move {
                let f = f.ok_or("no frame from the camera yet")?;
                to_jpeg(&f, quality, max_width).map_err(|e| format!("{e:#}"))
            }
        })?
    };
    tracing::info!(source = %config.source, "camera service started");
    let mut said_down = false;
    loop {
        let sock = tokio::select! {
            () = shutdown.cancelled() => break,
            s = tokio::net::TcpStream::connect(&config.source) => s,
        };
        let mut sock = match sock {
            Ok(s) => {
                tracing::info!("camera {} connected", config.source);
                said_down = false;
                s
            }
            Err(e) => {
                if !said_down {
                    tracing::warn!("camera {}: {e}; trying again every second", config.source);
                    said_down = true;
                }
                tokio::select! {
                    () = shutdown.cancelled() => break,
                    () = tokio::time::sleep(Duration::from_secs(1)) => continue,
                }
            }
        };
        loop {
            let f = tokio::select! {
                () = shutdown.cancelled() => break,
                f = stream::read_frame(&mut sock) => f,
            };
            let f = match f {
                Ok(Some(f)) => f,
                Ok(None) => {
                    tracing::warn!("camera {}: stream ended; reconnecting", config.source);
                    break;
                }
                Err(e) => {
                    tracing::warn!("camera {}: {e}; reconnecting", config.source);
                    break;
                }
            };
            publish(&f, config.quality, &frame_var, &raw_var);
            *marea::sync::lock(&latest) = Some(f);
        }
        if shutdown.is_cancelled() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    node.shutdown().await;
    Ok(())
}

/// Publishes `f` raw and as JPEG.
fn publish(
    f: &RawFrame,
    quality: u8,
    frame_var: &marea::Variable<CameraFrame>,
    raw_var: &marea::Variable<CameraFrame>,
) {
    match to_jpeg(f, quality, u32::MAX) {
        Ok(j) => {
            if let Err(e) = frame_var.set(&j) {
                tracing::warn!("publishing frame {}: {e}", f.seq);
            }
        }
        Err(e) => tracing::warn!("frame {}: {e:#}", f.seq),
    }
    let raw = CameraFrame {
        seq: f.seq,
        taken_unix_ms: f.taken_unix_ms,
        width: f.width,
        height: f.height,
        format: "rgb8".into(),
        data: f.rgb.clone(),
        pose: f.pose,
    };
    if let Err(e) = raw_var.set(&raw) {
        tracing::warn!("publishing raw frame {}: {e}", f.seq);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(w: u32, h: u32) -> RawFrame {
        let rgb = (0..w * h)
            .flat_map(|i| [(i % 251) as u8, 100, 50])
            .collect();
        RawFrame {
            seq: 1,
            taken_unix_ms: 5,
            width: w,
            height: h,
            pose: usal_types::camera::CameraPose::default(),
            rgb,
        }
    }

    #[test]
    fn a_frame_becomes_a_jpeg_and_a_snapshot_a_smaller_one() {
        let f = raw(320, 240);
        let full = to_jpeg(&f, 75, u32::MAX).unwrap();
        assert_eq!(
            (full.width, full.height, full.format.as_str()),
            (320, 240, "jpeg")
        );
        assert_eq!(&full.data[..2], &[0xFF, 0xD8], "a JPEG starts with SOI");
        assert!(full.data.len() < f.rgb.len());
        let small = to_jpeg(&f, 50, 80).unwrap();
        assert_eq!((small.width, small.height), (80, 60));
        assert!(small.data.len() < full.data.len());
        assert_eq!(small.seq, 1);
    }

    #[test]
    fn scaling_takes_the_nearest_pixel() {
        let rgb: Vec<u8> = (0..16u8).flat_map(|i| [i, i, i]).collect();
        let out = scale(&rgb, 4, 4, 2, 2);
        assert_eq!(out, vec![0, 0, 0, 2, 2, 2, 8, 8, 8, 10, 10, 10]);
    }
}

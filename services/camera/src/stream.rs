//! Reading a camera's frame stream (mavsim's `--camera`, see `mavsim::camera`): `"MCF1"`, a
//! u32 LE header length, a JSON header, a u32 LE data length, RGB pixels. Bytes from outside:
//! anything malformed is an error naming what, and the reader reconnects.

use tokio::io::{AsyncRead, AsyncReadExt};
use usal_types::camera::CameraPose;

/// Stream magic: one frame follows.
const MAGIC: &[u8; 4] = b"MCF1";
/// The largest header taken, bytes.
const MAX_HEADER: usize = 64 << 10;
/// The largest picture taken: 1920 × 1920 RGB.
const MAX_PIXELS: usize = 1920 * 1920;

/// A frame as the camera sent it.
#[derive(Clone, Debug, PartialEq)]
pub struct RawFrame {
    /// Its number.
    pub seq: u64,
    /// When it was taken, ms since the Unix epoch.
    pub taken_unix_ms: u64,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Where the camera was.
    pub pose: CameraPose,
    /// RGB, rows top to bottom.
    pub rgb: Vec<u8>,
}

#[derive(serde::Deserialize)]
struct Header {
    seq: u64,
    taken_unix_ms: u64,
    width: u32,
    height: u32,
    pose: CameraPose,
}

/// What is wrong with a stream.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// Reading failed (the camera went away).
    #[error("reading the camera: {0}")]
    Io(#[from] std::io::Error),
    /// Not a frame where one should start.
    #[error("not a camera stream: expected MCF1, got {0:02x?}")]
    BadMagic([u8; 4]),
    /// A header or picture larger than taken.
    #[error("a frame's {what} of {size} bytes is larger than the {max} taken")]
    TooLarge {
        /// Which part.
        what: &'static str,
        /// Its size.
        size: usize,
        /// The most taken.
        max: usize,
    },
    /// The header is not the JSON expected.
    #[error("a frame's header: {0}")]
    Header(#[from] serde_json::Error),
    /// The picture's size does not match its header.
    #[error("a {width}x{height} frame carries {got} bytes, not {want}")]
    Size {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Bytes received.
        got: usize,
        /// Bytes a picture of that size has.
        want: usize,
    },
}

async fn read_len(
    r: &mut (impl AsyncRead + Unpin),
    what: &'static str,
    max: usize,
) -> Result<usize, StreamError> {
    let size = r.read_u32_le().await? as usize;
    if size > max {
        return Err(StreamError::TooLarge { what, size, max });
    }
    Ok(size)
}

/// Reads the next frame; `None` at the end of the stream.
///
/// # Errors
/// [`StreamError`] naming what is wrong.
pub async fn read_frame(r: &mut (impl AsyncRead + Unpin)) -> Result<Option<RawFrame>, StreamError> {
    let mut magic = [0u8; 4];
    match r.read_exact(&mut magic).await {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e.into()),
    }
    if &magic != MAGIC {
        return Err(StreamError::BadMagic(magic));
    }
    let hl = read_len(r, "header", MAX_HEADER).await?;
    let mut header = vec![0u8; hl];
    r.read_exact(&mut header).await?;
    let h: Header = serde_json::from_slice(&header)?;
    let dl = read_len(r, "picture", MAX_PIXELS * 3).await?;
    let want = h.width as usize * h.height as usize * 3;
    if dl != want {
        return Err(StreamError::Size {
            width: h.width,
            height: h.height,
            got: dl,
            want,
        });
    }
    let mut rgb = vec![0u8; dl];
    r.read_exact(&mut rgb).await?;
    Ok(Some(RawFrame {
        seq: h.seq,
        taken_unix_ms: h.taken_unix_ms,
        width: h.width,
        height: h.height,
        pose: h.pose,
        rgb,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(width: u32, height: u32, data: usize) -> Vec<u8> {
        let header = serde_json::json!({
            "seq": 3, "taken_unix_ms": 10, "width": width, "height": height,
            "pose": {"lat": 41.0, "lon": 2.0, "height_m": 20.0, "heading_deg": 0.0, "hfov_deg": 70.0},
        })
        .to_string();
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(&(data as u32).to_le_bytes());
        out.extend(std::iter::repeat_n(7u8, data));
        out
    }

    #[tokio::test]
    async fn frames_are_read_one_after_the_other_to_the_end() {
        let mut bytes = frame(4, 2, 24);
        bytes.extend(frame(4, 2, 24));
        let mut r = &bytes[..];
        let f = read_frame(&mut r).await.unwrap().expect("a frame");
        assert_eq!((f.seq, f.width, f.height, f.rgb.len()), (3, 4, 2, 24));
        assert_eq!(f.pose.height_m, 20.0);
        assert!(read_frame(&mut r).await.unwrap().is_some());
        assert!(read_frame(&mut r).await.unwrap().is_none());
    }

    #[tokio::test]
    async fn a_malformed_stream_is_an_error_naming_what() {
        let mut r = &b"JUNKJUNK"[..];
        let e = read_frame(&mut r).await.unwrap_err();
        assert!(e.to_string().contains("expected MCF1"), "{e}");
        let bytes = frame(4, 2, 23);
        let e = read_frame(&mut &bytes[..]).await.unwrap_err();
        assert!(
            e.to_string().contains("4x2 frame carries 23 bytes, not 24"),
            "{e}"
        );
        let mut huge = MAGIC.to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = read_frame(&mut &huge[..]).await.unwrap_err();
        assert!(
            matches!(e, StreamError::TooLarge { what: "header", .. }),
            "{e}"
        );
        let mut bad = frame(4, 2, 24);
        bad[10] = b'!';
        assert!(matches!(
            read_frame(&mut &bad[..]).await,
            Err(StreamError::Header(_))
        ));
    }
}

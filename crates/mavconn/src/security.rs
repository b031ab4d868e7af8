//! What a [`crate::Connection`] may be told to trust: MAVLink 2 signing ([`Signing`], the
//! `mavlink` crate's implementation of the MAVLink signing protocol with a 32-byte secret key
//! read from a private file) and pinning ([`Pin`]: only one system, component and, on UDP, one
//! address is listened to once it has been seen).
//!
//! Both are checked in the connection's reader, before a frame reaches the owner; what they
//! refuse is counted ([`crate::Counters::rejected_signatures`], [`crate::Counters::foreign`]),
//! never delivered.

use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use zeroize::{Zeroize, Zeroizing};

/// The MAVLink 2 secret key: 32 bytes, wiped from memory when dropped.
#[derive(Clone, PartialEq, Eq)]
pub struct SigningKey([u8; 32]);

impl Drop for SigningKey {
    fn drop(&mut self) {
        self.0.zeroize();
    }
}

impl fmt::Debug for SigningKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Never print the secret, not even in a debug dump of a configuration.
        f.write_str("SigningKey(..)")
    }
}

/// Errors loading a signing key file.
#[derive(Debug, thiserror::Error)]
pub enum SigningKeyLoadError {
    /// The file cannot be read (or its metadata cannot).
    #[error("cannot read signing key file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Group or others may read or write the file: the key may already be known.
    #[error(
        "signing key file {path} has mode {mode:03o}: group/world may access it (chmod 600 it)"
    )]
    TooOpen {
        /// The file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// The content is neither 64 hex digits nor 32 raw bytes.
    #[error("signing key file {path}: expected 64 hex digits (or 32 raw bytes), got {len} bytes")]
    BadFormat {
        /// The file.
        path: PathBuf,
        /// Its length after trimming.
        len: usize,
    },
}

impl SigningKey {
    /// A key from its bytes.
    pub fn from_bytes(bytes: [u8; 32]) -> Self {
        Self(bytes)
    }

    /// The key's bytes.
    pub fn bytes(&self) -> &[u8; 32] {
        &self.0
    }

    /// Reads a key file: 64 hex digits (surrounding whitespace ignored) or exactly 32 raw
    /// bytes. The file must not be accessible to group or others: the mode checked is the
    /// opened file's, so swapping the path between the check and the read changes nothing.
    ///
    /// # Errors
    /// Unreadable file, group/world permissions, bad content.
    pub fn load(path: &Path) -> Result<Self, SigningKeyLoadError> {
        use std::io::Read;
        use std::os::unix::fs::MetadataExt;
        let read_err = |source| SigningKeyLoadError::Read {
            path: path.to_owned(),
            source,
        };
        let f = std::fs::File::open(path).map_err(read_err)?;
        let mode = f.metadata().map_err(read_err)?.mode() & 0o777;
        if mode & 0o077 != 0 {
            return Err(SigningKeyLoadError::TooOpen {
                path: path.to_owned(),
                mode,
            });
        }
        // A key is 64 digits and some whitespace: a larger file is not one (and is not read
        // whole).
        let mut raw = Zeroizing::new(Vec::with_capacity(256));
        f.take(4096).read_to_end(&mut raw).map_err(read_err)?;
        Self::parse(&raw).ok_or_else(|| SigningKeyLoadError::BadFormat {
            path: path.to_owned(),
            len: raw.trim_ascii().len(),
        })
    }

    fn parse(raw: &[u8]) -> Option<Self> {
        let text = raw.trim_ascii();
        if text.len() == 64 && text.iter().all(u8::is_ascii_hexdigit) {
            let mut key = Self([0u8; 32]);
            for (i, pair) in text.chunks_exact(2).enumerate() {
                let s = std::str::from_utf8(pair).ok()?;
                key.0[i] = u8::from_str_radix(s, 16).ok()?;
            }
            return Some(key);
        }
        <[u8; 32]>::try_from(raw).ok().map(Self)
    }
}

/// MAVLink 2 signing of a connection: every frame sent is signed, only correctly signed
/// frames with a fresh timestamp are accepted (unsigned and MAVLink 1 frames are refused).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Signing {
    /// The shared secret.
    pub key: SigningKey,
    /// The link id put in our signatures (one per link of a system, 0-255).
    pub link_id: u8,
}

impl Signing {
    pub(crate) fn data(&self) -> mavlink::SigningData {
        mavlink::SigningData::from_config(mavlink::SigningConfig::new(
            *self.key.bytes(),
            self.link_id,
            true,
            false,
        ))
    }
}

/// Pinning of the other end: the first HEARTBEAT that matches (system id, and on UDP the
/// configured address if any) fixes the system id, component id and (UDP) source address;
/// afterwards frames from any other system, component or address are dropped and counted, and
/// a `udpin` connection keeps answering the pinned address, not the last sender. Until then
/// nothing but that heartbeat is delivered.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Pin {
    /// The system id to pin to; `None`: the first autopilot heartbeat's.
    pub system_id: Option<u8>,
    /// The component id to pin to; `None`: the first autopilot heartbeat's (a camera's or a
    /// gimbal's never pins: see [`is_autopilot_heartbeat`]).
    pub component_id: Option<u8>,
    /// The UDP address to pin to (`peer="ip:port"`); `None`: the first heartbeat's sender.
    /// A `udpin` connection answers it from the start.
    pub peer: Option<SocketAddr>,
    /// A pinned peer silent for longer than this is released: the next matching heartbeat
    /// pins again (an autopilot restarted from another port). `None`: pinned for good.
    pub release_after: Option<std::time::Duration>,
}

/// Whether a heartbeat may be an autopilot's: it names an autopilot and a vehicle type, not
/// a ground station nor a peripheral component (camera, gimbal, companion computer...), which
/// may also fill in the autopilot field.
pub fn is_autopilot_heartbeat(hb: &mavlink::dialects::ardupilotmega::HEARTBEAT_DATA) -> bool {
    use mavlink::dialects::ardupilotmega::{MavAutopilot, MavType::*};
    hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
        && !matches!(
            hb.mavtype,
            MAV_TYPE_GCS
                | MAV_TYPE_CAMERA
                | MAV_TYPE_GIMBAL
                | MAV_TYPE_ONBOARD_CONTROLLER
                | MAV_TYPE_ADSB
                | MAV_TYPE_ANTENNA_TRACKER
                | MAV_TYPE_FLARM
                | MAV_TYPE_SERVO
                | MAV_TYPE_ODID
                | MAV_TYPE_BATTERY
                | MAV_TYPE_CHARGING_STATION
                | MAV_TYPE_LOG
                | MAV_TYPE_OSD
                | MAV_TYPE_IMU
                | MAV_TYPE_GPS
                | MAV_TYPE_WINCH
                | MAV_TYPE_PARACHUTE
        )
}

/// What was pinned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pinned {
    /// System id of the other end.
    pub system_id: u32,
    /// Component id of the other end.
    pub component_id: u8,
    /// Its UDP address (`None` on byte streams).
    pub addr: Option<SocketAddr>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    #[test]
    fn key_files_parse_as_hex_or_raw_and_must_be_private() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("key");
        std::fs::write(&p, format!("{}\n", "0a".repeat(32))).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert_eq!(SigningKey::load(&p).unwrap().bytes(), &[0x0a; 32]);

        std::fs::write(&p, [7u8; 32]).unwrap();
        assert_eq!(SigningKey::load(&p).unwrap().bytes(), &[7; 32]);

        std::fs::write(&p, "abc").unwrap();
        assert!(matches!(
            SigningKey::load(&p),
            Err(SigningKeyLoadError::BadFormat { len: 3, .. })
        ));

        std::fs::write(&p, "0a".repeat(32)).unwrap();
        for mode in [0o640, 0o604, 0o660] {
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
            let e = SigningKey::load(&p).unwrap_err();
            assert!(matches!(e, SigningKeyLoadError::TooOpen { .. }), "{e}");
            assert!(e.to_string().contains("chmod 600"), "{e}");
        }
        assert!(matches!(
            SigningKey::load(&dir.path().join("none")),
            Err(SigningKeyLoadError::Read { .. })
        ));
        assert_eq!(
            format!("{:?}", SigningKey::from_bytes([1; 32])),
            "SigningKey(..)"
        );
    }
}

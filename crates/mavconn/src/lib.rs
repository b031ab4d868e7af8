//! `mavconn`: MAVLink connections shared by the VAS (ground-station side) and mavsim (vehicle
//! side), independent of the marea middleware so the simulator never depends on it.
//!
//! - [`endpoint`]: the endpoint strings `udpout:HOST:PORT`, `udpin:ADDR:PORT` (also `udp:`),
//!   `tcpout:HOST:PORT` (also `tcp:`) and `serial:PATH[:BAUD]`, as pymavlink and MAVProxy
//!   spell them;
//! - [`connection`]: [`Connection`] opens an endpoint (or creates a pty pair) and runs the
//!   `mavlink` crate's MAVLink 2 framing on it. A reader task decodes frames into a channel, so
//!   [`Connection::recv`] is cancel-safe inside `tokio::select!`; [`Connection::send`] never
//!   waits (a congested output drops and counts, like a radio). UDP-in answers the last
//!   sender and can copy everything to an extra address; frames that pass the CRC but do not
//!   parse are counted.
//! - [`security`]: MAVLink 2 signing ([`Signing`]) and pinning of the other end ([`Pin`]),
//!   both optional in [`OpenOptions`]; refused frames are counted, never delivered.
//!
//! ```no_run
//! # async fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use mavconn::{Connection, Endpoint, OpenOptions};
//! let endpoint: Endpoint = "udpin:127.0.0.1:14550".parse()?;
//! let mut conn = Connection::open(&endpoint, OpenOptions::default()).await?;
//! while let Some(frame) = conn.recv().await {
//!     let frame = frame?;
//!     println!("{:?} from {:?}", frame.msg, frame.peer);
//!     conn.send(frame.header, &frame.msg)?; // echo
//! }
//! # Ok(()) }
//! ```

#![warn(missing_docs)]

pub mod connection;
pub mod endpoint;
pub mod security;

pub use connection::{
    Connection, ConnectionOpenError, Counters, Frame, OpenOptions, SendError, RESYNC_BYTES,
};
pub use endpoint::{Endpoint, EndpointParseError};
pub use security::{is_autopilot_heartbeat, Pin, Pinned, Signing, SigningKey, SigningKeyLoadError};

//! What the request side hands the driver to put on the wire.

use mavlink::dialects::ardupilotmega::MavMessage;

/// What the driver puts on the wire for the requests.
// Messages travel by value as before; boxing them would cost an allocation per message to
// shrink a variant that is sent only before a resend.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub(crate) enum Outbound {
    /// A MAVLink message.
    Message(MavMessage),
    /// Filler bytes for a byte-stream link. A MAVLink parser that read a corrupted length
    /// field waits for that many bytes (up to 280) before the CRC tells it the frame is bad
    /// and it rescans; on a quiet uplink that takes seconds, and every resend in between is
    /// swallowed. Zero bytes complete the bogus frame and are skipped while looking for the
    /// next start marker.
    Resync,
    /// A frame from another ground station (a forward endpoint), sent with its own header.
    Raw(mavlink::MavHeader, MavMessage),
}

//! MAVLink endpoint strings (`udpout:`, `udpin:`, `tcpout:`, `serial:`), as pymavlink and MAVProxy spell them.

use std::fmt;
use std::str::FromStr;

/// Where a MAVLink connection goes: the `vas --endpoint` syntax.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Endpoint {
    /// Send to `HOST:PORT` from an ephemeral port (`udpout:HOST:PORT`); the
    /// autopilot answers to whoever sent last, as ArduPilot SITL and mavsim do.
    /// The destination stays fixed whoever answers.
    UdpOut(String),
    /// Listen on `ADDR:PORT` (`udpin:ADDR:PORT`, also `udp:`); reply to the last sender.
    UdpIn(String),
    /// Connect to a TCP server (`tcpout:HOST:PORT`, also `tcp:`).
    TcpOut(String),
    /// A serial device (`serial:/dev/ttyUSB0:57600`; the baud rate defaults to 57600).
    Serial {
        /// Device path.
        path: String,
        /// Baud rate.
        baud: u32,
    },
}

/// Errors parsing an endpoint string.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EndpointParseError {
    /// The scheme before the first `:` is not one we know.
    #[error("unknown endpoint scheme in {0:?} (expected udpout:, udpin:, tcpout: or serial:)")]
    UnknownScheme(String),
    /// The address part is missing or has no port.
    #[error("endpoint {0:?} needs HOST:PORT")]
    MissingPort(String),
    /// The serial baud rate is not a number.
    #[error("bad baud rate in {0:?}")]
    BadBaud(String),
}

fn host_port(full: &str, rest: &str) -> Result<String, EndpointParseError> {
    match rest.rsplit_once(':') {
        Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => {
            Ok(rest.to_owned())
        }
        _ => Err(EndpointParseError::MissingPort(full.to_owned())),
    }
}

impl FromStr for Endpoint {
    type Err = EndpointParseError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (scheme, rest) = s
            .split_once(':')
            .ok_or_else(|| EndpointParseError::UnknownScheme(s.to_owned()))?;
        match scheme {
            "udpout" => Ok(Self::UdpOut(host_port(s, rest)?)),
            "udpin" | "udp" => Ok(Self::UdpIn(host_port(s, rest)?)),
            "tcpout" | "tcp" => Ok(Self::TcpOut(host_port(s, rest)?)),
            "serial" => {
                if rest.is_empty() {
                    return Err(EndpointParseError::MissingPort(s.to_owned()));
                }
                match rest.rsplit_once(':') {
                    Some((path, baud)) if !path.is_empty() => Ok(Self::Serial {
                        path: path.to_owned(),
                        baud: baud
                            .parse()
                            .map_err(|_| EndpointParseError::BadBaud(s.to_owned()))?,
                    }),
                    _ => Ok(Self::Serial {
                        path: rest.to_owned(),
                        baud: 57_600,
                    }),
                }
            }
            _ => Err(EndpointParseError::UnknownScheme(s.to_owned())),
        }
    }
}

impl fmt::Display for Endpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UdpOut(a) => write!(f, "udpout:{a}"),
            Self::UdpIn(a) => write!(f, "udpin:{a}"),
            Self::TcpOut(a) => write!(f, "tcpout:{a}"),
            Self::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_documented_forms() {
        assert_eq!(
            "udpout:127.0.0.1:14550".parse(),
            Ok(Endpoint::UdpOut("127.0.0.1:14550".into()))
        );
        assert_eq!(
            "udpin:0.0.0.0:14550".parse(),
            Ok(Endpoint::UdpIn("0.0.0.0:14550".into()))
        );
        assert_eq!(
            "tcpout:localhost:5760".parse(),
            Ok(Endpoint::TcpOut("localhost:5760".into()))
        );
        assert_eq!(
            "serial:/dev/ttyUSB0:57600".parse(),
            Ok(Endpoint::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 57_600
            })
        );
        assert_eq!(
            "serial:/dev/pts/3".parse(),
            Ok(Endpoint::Serial {
                path: "/dev/pts/3".into(),
                baud: 57_600
            })
        );
        let e: Endpoint = "udpout:127.0.0.1:14550".parse().unwrap();
        assert_eq!(e.to_string(), "udpout:127.0.0.1:14550");
    }

    #[test]
    fn rejects_bad_strings() {
        assert!(matches!(
            "ftp:x:1".parse::<Endpoint>(),
            Err(EndpointParseError::UnknownScheme(_))
        ));
        assert!(matches!(
            "udpout:127.0.0.1".parse::<Endpoint>(),
            Err(EndpointParseError::MissingPort(_))
        ));
        assert!(matches!(
            "udpout::99".parse::<Endpoint>(),
            Err(EndpointParseError::MissingPort(_))
        ));
        assert!(matches!(
            "serial:/dev/x:fast".parse::<Endpoint>(),
            Err(EndpointParseError::BadBaud(_))
        ));
        assert!(matches!(
            "nothing".parse::<Endpoint>(),
            Err(EndpointParseError::UnknownScheme(_))
        ));
    }
}

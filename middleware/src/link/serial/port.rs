//! Opening serial ports (tokio-serial: any tty or pty path), one bidirectional port or a
//! `serialduo` pair (one port for Tx, one for Rx), and reopening a vanished port with backoff.

use std::io;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite};

/// A port's reading half.
pub type BoxRead = Box<dyn AsyncRead + Send + Unpin>;
/// A port's writing half.
pub type BoxWrite = Box<dyn AsyncWrite + Send + Unpin>;

/// First wait before reopening a port.
pub const REOPEN_MIN: Duration = Duration::from_millis(100);
/// Longest wait between reopening attempts.
pub const REOPEN_MAX: Duration = Duration::from_secs(5);

/// Opens (and reopens) the byte streams of a link.
pub trait PortOpener: Send + Sync + 'static {
    /// Opens the ports.
    ///
    /// # Errors
    /// The OS error of the port that failed.
    fn open(&self) -> io::Result<(BoxRead, BoxWrite)>;
    /// The port paths, for logs.
    fn describe(&self) -> String;
}

/// Which serial devices a link uses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SerialPorts {
    /// One bidirectional port (`<serial>`).
    Single {
        /// Path.
        path: String,
        /// Baud rate.
        baud: u32,
    },
    /// Two one-way ports (`<serialduo>`).
    Duo {
        /// Transmit port path.
        tx_path: String,
        /// Transmit baud rate.
        tx_baud: u32,
        /// Receive port path.
        rx_path: String,
        /// Receive baud rate.
        rx_baud: u32,
    },
}

fn open_tty(path: &str, baud: u32) -> io::Result<tokio_serial::SerialStream> {
    use tokio_serial::SerialPortBuilderExt;
    tokio_serial::new(path, baud)
        .timeout(Duration::from_millis(100))
        .open_native_async()
        .map_err(io::Error::from)
}

impl PortOpener for SerialPorts {
    fn open(&self) -> io::Result<(BoxRead, BoxWrite)> {
        match self {
            SerialPorts::Single { path, baud } => {
                let port = open_tty(path, *baud)?;
                let (r, w) = tokio::io::split(port);
                Ok((Box::new(r), Box::new(w)))
            }
            SerialPorts::Duo {
                tx_path,
                tx_baud,
                rx_path,
                rx_baud,
            } => {
                let tx = open_tty(tx_path, *tx_baud)?;
                let rx = open_tty(rx_path, *rx_baud)?;
                Ok((Box::new(rx), Box::new(tx)))
            }
        }
    }

    fn describe(&self) -> String {
        match self {
            SerialPorts::Single { path, baud } => format!("serial://{path}@{baud}"),
            SerialPorts::Duo {
                tx_path,
                tx_baud,
                rx_path,
                rx_baud,
            } => format!("serialduo://tx={tx_path}@{tx_baud},rx={rx_path}@{rx_baud}"),
        }
    }
}

/// The next reopening delay after `current` failed.
pub fn next_backoff(current: Duration) -> Duration {
    (current * 2).clamp(REOPEN_MIN, REOPEN_MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_up_to_the_ceiling() {
        let mut d = REOPEN_MIN;
        let mut seen = vec![d];
        for _ in 0..8 {
            d = next_backoff(d);
            seen.push(d);
        }
        assert_eq!(seen[1], Duration::from_millis(200));
        assert_eq!(*seen.last().unwrap(), REOPEN_MAX);
    }

    #[tokio::test]
    async fn a_missing_port_is_an_error_with_its_path() {
        let p = SerialPorts::Single {
            path: "/nonexistent/ttyX".into(),
            baud: 57600,
        };
        assert!(p.open().is_err());
        assert_eq!(p.describe(), "serial:///nonexistent/ttyX@57600");
    }
}

//! `marea-wan --udp` through real sockets and a real process: a datagram crosses it both ways
//! with the one-way delay asked for each way, none crosses during an outage, and a loss of 1
//! drops them all. (The TCP side is flown by the WAN missions' launcher tests; the path model
//! itself has unit tests in the binary.)

use std::io::BufRead;
use std::net::{SocketAddr, UdpSocket};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use serde_json::Value;

/// A `marea-wan` child and the JSON lines it prints.
struct Wan {
    child: Child,
    lines: mpsc::Receiver<Value>,
    listen: SocketAddr,
}

impl Wan {
    fn start(args: &[&str]) -> Wan {
        let mut child = Command::new(env!("CARGO_BIN_EXE_marea-wan"))
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start marea-wan");
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if let Ok(v) = serde_json::from_str::<Value>(&line) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
            }
        });
        let mut wan = Wan {
            child,
            lines,
            listen: "127.0.0.1:0".parse().expect("a literal address"),
        };
        let first = wan.line(|v| v["listen"].is_string(), "its listening address");
        wan.listen = first["listen"]
            .as_str()
            .and_then(|s| s.parse().ok())
            .expect("an address");
        wan
    }

    /// The next line satisfying `pred`, within 10 s.
    fn line(&mut self, pred: impl Fn(&Value) -> bool, what: &str) -> Value {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) if pred(&v) => return v,
                Ok(_) => {}
                Err(_) => panic!("marea-wan printed no line with {what}"),
            }
        }
    }
}

impl Drop for Wan {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A UDP echo server on loopback, stopped when dropped.
struct Echo {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
}

impl Echo {
    fn start() -> Echo {
        let socket = UdpSocket::bind("127.0.0.1:0").expect("bind the echo server");
        socket
            .set_read_timeout(Some(Duration::from_millis(50)))
            .expect("a read timeout");
        let addr = socket.local_addr().expect("its address");
        let stop = Arc::new(AtomicBool::new(false));
        let running = stop.clone();
        std::thread::spawn(move || {
            let mut buf = [0u8; 2048];
            while !running.load(Ordering::Relaxed) {
                if let Ok((n, from)) = socket.recv_from(&mut buf) {
                    let _ = socket.send_to(&buf[..n], from);
                }
            }
        });
        Echo { addr, stop }
    }
}

impl Drop for Echo {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

fn client() -> UdpSocket {
    UdpSocket::bind("127.0.0.1:0").expect("bind a client")
}

/// The first datagram `socket` receives within `within`.
fn receive(socket: &UdpSocket, within: Duration) -> Option<Vec<u8>> {
    socket
        .set_read_timeout(Some(within))
        .expect("a read timeout");
    let mut buf = [0u8; 2048];
    socket.recv(&mut buf).ok().map(|n| buf[..n].to_vec())
}

#[test]
fn udp_datagrams_cross_with_the_delay_each_way_and_none_during_an_outage() {
    let echo = Echo::start();
    let to = echo.addr.to_string();
    // An outage from 2 s on, for longer than the test.
    let mut wan = Wan::start(&[
        "--udp",
        "--to",
        &to,
        "--delay-ms",
        "60",
        "--outage",
        "2000:600000",
    ]);
    let c = client();
    let sent = Instant::now();
    c.send_to(b"ping", wan.listen).expect("send");
    let back = receive(&c, Duration::from_secs(5)).expect("the echo through the WAN");
    let rtt = sent.elapsed();
    assert_eq!(back, b"ping");
    assert!(
        rtt >= Duration::from_millis(120),
        "a round trip of {rtt:?} through two one-way delays of 60 ms"
    );

    wan.line(|v| v["outage"] == "start", "the outage starting");
    c.send_to(b"during the outage", wan.listen).expect("send");
    assert_eq!(
        receive(&c, Duration::from_secs(1)),
        None,
        "a datagram crossed during the outage"
    );
}

#[test]
fn udp_with_a_loss_of_one_drops_every_datagram() {
    let echo = Echo::start();
    let to = echo.addr.to_string();
    let wan = Wan::start(&["--udp", "--to", &to, "--loss", "1"]);
    let c = client();
    for i in 0..20u8 {
        c.send_to(&[i], wan.listen).expect("send");
    }
    assert_eq!(
        receive(&c, Duration::from_millis(500)),
        None,
        "a datagram crossed a path that loses all"
    );
}

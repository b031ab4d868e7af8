//! `marea-wan --udp` through real sockets and a real process: a datagram crosses it both ways
//! with the one-way delay asked for each way, none crosses during an outage, and a loss of 1
//! drops them all. (The TCP side is flown by the WAN missions' launcher tests; the path model
//! itself has unit tests in the binary.)

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

mod common;
use common::Proc;

/// Bound on marea-wan printing a line it owes.
const LINE: Duration = Duration::from_secs(10);

/// A `marea-wan` child (its JSON lines through [`Proc`]) and where it listens.
fn start_wan(args: &[&str]) -> (Proc, SocketAddr) {
    let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    let mut wan = Proc::spawn("marea-wan", env!("CARGO_BIN_EXE_marea-wan"), &args);
    let listen = wan.expect_key(LINE, "listen")["listen"]
        .as_str()
        .and_then(|s| s.parse().ok())
        .expect("an address");
    (wan, listen)
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
    let (mut wan, listen) = start_wan(&[
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
    c.send_to(b"ping", listen).expect("send");
    let back = receive(&c, Duration::from_secs(5)).expect("the echo through the WAN");
    let rtt = sent.elapsed();
    assert_eq!(back, b"ping");
    assert!(
        rtt >= Duration::from_millis(120),
        "a round trip of {rtt:?} through two one-way delays of 60 ms"
    );

    wan.expect(LINE, "the outage starting", |v| v["outage"] == "start");
    c.send_to(b"during the outage", listen).expect("send");
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
    let (_wan, listen) = start_wan(&["--udp", "--to", &to, "--loss", "1"]);
    let c = client();
    for i in 0..20u8 {
        c.send_to(&[i], listen).expect("send");
    }
    assert_eq!(
        receive(&c, Duration::from_millis(500)),
        None,
        "a datagram crossed a path that loses all"
    );
}

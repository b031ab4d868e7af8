//! Raw tokio UDP, one datagram per message: the floor every other peer is compared with.
//! Not reliable: the `pub` role sends as fast as the socket takes datagrams and the `sub` counts
//! what arrives (loss included).

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use peers_common::{finish_sub, payload, ready, seq, Args, Arrivals, Control, Rtts};
use tokio::net::UdpSocket;

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    let control = Control::start(true);
    let rt = tokio::runtime::Runtime::new().context("tokio runtime")?;
    rt.block_on(run(args, control))
}

async fn run(args: Args, control: Arc<Control>) -> anyhow::Result<()> {
    let sock = UdpSocket::bind("127.0.0.1:0").await.context("bind")?;
    let me = sock.local_addr()?;
    let mut buf = vec![0u8; 65536];
    match args.role.as_str() {
        "pong" => {
            ready(&me.to_string());
            loop {
                let (len, from) = sock.recv_from(&mut buf).await.context("pong recv")?;
                sock.send_to(&buf[..len], from).await.context("pong send")?;
            }
        }
        "ping" => {
            let to: std::net::SocketAddr = args
                .key
                .parse()
                .context("ping: KEY is the pong's address")?;
            ready("");
            let mut rtts = Rtts::new(args.param as usize);
            let mut i = 0u64;
            while i < rtts.total() as u64 {
                let msg = payload(args.size, i);
                let t = Instant::now();
                sock.send_to(&msg, to).await.context("ping send")?;
                // A lost datagram (rare on loopback) is sent again under a new number.
                while let Ok(r) =
                    tokio::time::timeout(Duration::from_secs(1), sock.recv_from(&mut buf)).await
                {
                    let (len, _) = r.context("ping recv")?;
                    if seq(&buf[..len]) == Some(i) {
                        rtts.push(t);
                        break;
                    }
                }
                i += 1;
            }
            rtts.finish();
            Ok(())
        }
        "sub" => {
            let arrivals = Arc::new(Arrivals::default());
            let a = arrivals.clone();
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65536];
                while sock.recv_from(&mut buf).await.is_ok() {
                    a.add();
                }
            });
            ready(&me.to_string());
            tokio::task::spawn_blocking(move || finish_sub(&arrivals, &control)).await?;
            Ok(())
        }
        "pub" => {
            let to: std::net::SocketAddr =
                args.key.parse().context("pub: KEY is the sub's address")?;
            ready("");
            let msg = payload(args.size, 0);
            let start = Instant::now();
            let mut sent = 0u64;
            while start.elapsed().as_secs_f64() < args.param {
                for _ in 0..64 {
                    if sock.send_to(&msg, to).await.is_ok() {
                        sent += 1;
                    }
                }
            }
            println!("result {sent} {}", start.elapsed().as_secs_f64());
            Ok(())
        }
        "idle" => {
            ready(&me.to_string());
            std::future::pending().await
        }
        other => anyhow::bail!("unknown role {other:?}"),
    }
}

//! `cargo bench --bench serial`: the serial link's figures as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`. Wire sizes come from the real encoders; rates,
//! ages and delivery come from two Serial Transport Protocol engines joined by simulated lines
//! (seeded byte loss and corruption, 8N1 line time) on a simulated clock, so every figure is
//! reproducible and a minute of radio traffic takes well under a second. The cross-process
//! tests in `tests/serial.rs` exercise the same engines through real ptys and `marea-radio`.

use std::time::{Duration, Instant};

use marea::codec::{encode_message, encode_payload};
use marea::link::serial::frame::Frame;
use marea::link::serial::sim::{Faults, Side, SimPair};
use marea::link::serial::stp::{StpConfig, StpEvent};
use marea::protocol::Message;

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

#[derive(serde::Serialize)]
struct Position {
    lat: f64,
    lon: f64,
    alt: f64,
    heading: f32,
    speed: f32,
}

fn position_message(id: u32) -> Vec<u8> {
    let payload = encode_payload(&Position {
        lat: 41.275_123,
        lon: 1.987_456,
        alt: 102.5,
        heading: 271.5,
        speed: 1.5,
    });
    encode_message(&Message::Var {
        id,
        payload: payload.unwrap_or_default(),
    })
}

fn faults(ber: f64) -> Faults {
    Faults {
        loss: ber / 2.0,
        corrupt: ber / 2.0,
    }
}

/// Bulk Safe goodput (payload bits per second delivered in order) over `secs` simulated seconds.
fn goodput(baud: u32, ber: f64, mps: usize, secs: u64) -> (f64, f64) {
    let cfg = StpConfig::new(baud, Duration::from_millis(1500), mps, 20);
    let mut p = SimPair::new(cfg, faults(ber), 42, Duration::from_millis(5));
    let until = p.now + Duration::from_secs(secs);
    let mut bytes = 0u64;
    let (mut sent, mut got) = (0u64, 0u64);
    p.run(
        until,
        Duration::from_millis(10),
        |p| {
            while p.a.stats().safe_queued < 64 {
                let now = p.now;
                p.a.push_safe(now, vec![0x5A; 1300], Some(sent));
                sent += 1;
            }
        },
        |side, _, e| {
            if let (Side::B, StpEvent::Message(m)) = (side, e) {
                bytes += m.len() as u64;
                got += 1;
            }
        },
    );
    let delivered_ratio = if got > 0 { 1.0 } else { 0.0 };
    (bytes as f64 * 8.0 / secs as f64, delivered_ratio)
}

fn main() {
    // Wire size of one position sample, framing included.
    let msg = position_message(3);
    let frame = Frame::Data {
        safe: false,
        seq: 0x0102,
        frag: 0,
        total: 1,
        data: msg.clone(),
    }
    .encode();
    metric("wire.position.serial_bytes", frame.len() as f64, "bytes");

    // Five 32-byte variables queued together share one frame.
    let cfg = StpConfig::new(57_600, Duration::from_millis(1500), 300, 20);
    let mut p = SimPair::new(cfg, Faults::default(), 1, Duration::ZERO);
    let now = p.now;
    for id in 0..5 {
        p.a.push_fast(now, Some(id), position_message(id));
    }
    let batch = p.a.poll_transmit(now).map_or(0, |f| f.len());
    let overhead = (batch as f64 - 5.0 * msg.len() as f64) / 5.0;
    metric("serial.batched.overhead_bytes_per_msg", overhead, "bytes");

    // Idle discovery: only heartbeats flow (default serial period 5 s). A node with 10 services
    // and 100 items has a declaration counter of 110.
    let hb = encode_message(&Message::Heartbeat {
        node_id: 0xD1B5_4A32_D192_ED03,
        domain_hash: 0x9E37_79B9,
        counter: 110,
    });
    let mut p = SimPair::new(cfg, Faults::default(), 1, Duration::ZERO);
    let start = p.now;
    let mut next = start;
    let secs = 600;
    p.run(
        start + Duration::from_secs(secs),
        Duration::from_millis(100),
        |p| {
            if p.now >= next {
                p.a.push_announce(hb.clone());
                p.b.push_announce(hb.clone());
                next += Duration::from_secs(5);
            }
        },
        |_, _, _| {},
    );
    let per_node = p.a.stats().link.bytes_out as f64 / secs as f64;
    metric("serial.discovery.idle_bytes_per_s", per_node, "bytes/s");
    metric(
        "serial.discovery.idle_bytes_per_s_both_directions",
        per_node + p.b.stats().link.bytes_out as f64 / secs as f64,
        "bytes/s",
    );

    // Bulk goodput; fragments sized for the error rate (MaxPacketSize).
    for (baud, label) in [(57_600u32, "57600"), (115_200, "115200")] {
        for (ber, tag, mps) in [
            (0.0, "ber0", 300usize),
            (0.001, "ber0_001", 150),
            (0.01, "ber0_01", 40),
        ] {
            let (bps, _) = goodput(baud, ber, mps, 60);
            metric(&format!("serial.goodput_{label}.{tag}_bps"), bps, "bit/s");
        }
    }
    let (duo, _) = goodput(115_200, 0.0, 300, 60);
    metric("serialduo.goodput_115200_bps", duo, "bit/s");

    // Events (Safe) at 1 % byte errors: delivery ratio, exactly once and in order.
    let cfg = StpConfig::new(57_600, Duration::from_millis(1500), 64, 20);
    let mut p = SimPair::new(cfg, faults(0.01), 9, Duration::from_millis(5));
    let n = 2000u64;
    for i in 0..n {
        let mut m = i.to_le_bytes().to_vec();
        m.resize(24, 0);
        p.a.push_safe(p.now, m, None);
    }
    let mut got = Vec::new();
    let until = p.now + Duration::from_secs(300);
    p.run(
        until,
        Duration::from_millis(10),
        |_| {},
        |side, _, e| {
            if let (Side::B, StpEvent::Message(m)) = (side, e) {
                got.push(u64::from_le_bytes(m[..8].try_into().unwrap_or([0; 8])));
            }
        },
    );
    let in_order_once = got == (0..n).collect::<Vec<_>>();
    metric(
        "serial.events.delivery_ratio",
        if in_order_once {
            got.len() as f64 / n as f64
        } else {
            0.0
        },
        "ratio",
    );

    // 20 Hz manual control while bulk Safe traffic saturates the 57600-baud line.
    let cfg = StpConfig::new(57_600, Duration::from_millis(1500), 300, 20);
    let mut p = SimPair::new(cfg, Faults::default(), 3, Duration::from_millis(5));
    let start: Instant = p.now;
    let mut next_ctl = start;
    let mut ages: Vec<f64> = Vec::new();
    p.run(
        start + Duration::from_secs(60),
        Duration::from_millis(5),
        |p| {
            while p.a.stats().safe_queued < 50 {
                let now = p.now;
                p.a.push_safe(now, vec![0x55; 1300], None);
            }
            if p.now >= next_ctl {
                let stamp = (p.now - start).as_micros() as u64;
                let mut m = stamp.to_le_bytes().to_vec();
                m.resize(20, 0);
                p.a.push_fast(p.now, Some(1), m);
                next_ctl += Duration::from_millis(50);
            }
        },
        |side, now, e| {
            if let (Side::B, StpEvent::Message(m)) = (side, e) {
                if m.len() == 20 {
                    let stamp = u64::from_le_bytes(m[..8].try_into().unwrap_or([0; 8]));
                    let age = (now - start).as_micros() as f64 - stamp as f64;
                    ages.push(age / 1000.0);
                }
            }
        },
    );
    ages.sort_by(f64::total_cmp);
    if !ages.is_empty() {
        metric(
            "serial.manual_control.age_p50_ms",
            ages[ages.len() / 2],
            "ms",
        );
        metric(
            "serial.manual_control.age_p99_ms",
            ages[ages.len() * 99 / 100],
            "ms",
        );
    }
}

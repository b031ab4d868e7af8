//! Raw iceoryx2 (0.10, the version the workspace uses) publish-subscribe of byte slices.
//! Round trips wait the way marea's shm link waits by default: each message is followed by a
//! notification and the receiver sleeps on its listener. One-way rates are reliable: the
//! service never overflows and the publisher retries until delivered, while the subscriber
//! busy-polls (iceoryx2's fastest configuration; marea's shm events are measured with the
//! link's default `wait="event"`). KEY is the service-name prefix.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use peers_common::{
    finish_sub, payload, ready, seq, subscribers, wait_until, Args, Arrivals, Control, Rtts,
};

/// The subscriber's buffer for one-way rates (and the service's limit).
const BUFFER: usize = 1024;
/// The same for large samples (every slot of the publisher's segment is the largest sample's
/// size: 1,024 of 4 MiB would not fit the host's shared memory); marea's bulk inbox holds 8.
const LARGE_BUFFER: usize = 8;

/// The subscriber's buffer for samples of `size` bytes.
fn buffer(size: usize) -> usize {
    if size > 64 << 10 {
        LARGE_BUFFER
    } else {
        BUFFER
    }
}

type Pub = Publisher<ipc::Service, [u8], ()>;
type Sub = Subscriber<ipc::Service, [u8], ()>;

struct Ports {
    node: iceoryx2::node::Node<ipc::Service>,
    /// The subscriber's buffer (and the service's limit).
    buffer: usize,
}

impl Ports {
    fn new(size: usize) -> anyhow::Result<Ports> {
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| anyhow!("iceoryx2 node: {e:?}"))?;
        Ok(Ports {
            node,
            buffer: buffer(size),
        })
    }

    fn service(
        &self,
        name: &str,
    ) -> anyhow::Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], ()>,
    > {
        self.node
            .service_builder(&ServiceName::new(name).map_err(|e| anyhow!("name {name}: {e:?}"))?)
            .publish_subscribe::<[u8]>()
            .subscriber_max_buffer_size(self.buffer)
            .enable_safe_overflow(false)
            .max_publishers(2)
            .max_subscribers(subscribers().max(2))
            .max_nodes(subscribers().max(2) + 2)
            .open_or_create()
            .map_err(|e| anyhow!("service {name}: {e:?}"))
    }

    fn publisher(&self, name: &str, size: usize) -> anyhow::Result<(Pub, usize)> {
        let s = self.service(name)?;
        let p = s
            .publisher_builder()
            .initial_max_slice_len(size)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .create()
            .map_err(|e| anyhow!("publisher {name}: {e:?}"))?;
        // Every subscriber of a fan-out (the runner starts them all before the publisher).
        let n = subscribers();
        wait_until("iceoryx2 subscribers", Duration::from_secs(15), || {
            s.dynamic_config().number_of_subscribers() >= n
        })?;
        Ok((p, s.dynamic_config().number_of_subscribers()))
    }

    fn subscriber(&self, name: &str) -> anyhow::Result<Sub> {
        self.service(name)?
            .subscriber_builder()
            .buffer_size(self.buffer)
            .create()
            .map_err(|e| anyhow!("subscriber {name}: {e:?}"))
    }

    fn event(
        &self,
        name: &str,
    ) -> anyhow::Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>> {
        self.node
            .service_builder(&ServiceName::new(name).map_err(|e| anyhow!("name {name}: {e:?}"))?)
            .event()
            .open_or_create()
            .map_err(|e| anyhow!("event {name}: {e:?}"))
    }
}

/// Sends one sample; returns to how many subscribers it went.
fn send(p: &Pub, msg: &[u8]) -> anyhow::Result<usize> {
    let s = p
        .loan_slice_uninit(msg.len())
        .map_err(|e| anyhow!("loan: {e:?}"))?
        .write_from_slice(msg);
    s.send().map_err(|e| anyhow!("send: {e:?}"))
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    set_log_level_from_env_or(LogLevel::Error);
    let control = Control::start(false);
    run(args, control)
}

/// One side of a round trip: receives on `rx`, sends on `tx`, each message with a wake-up.
fn rtt_side(
    args: &Args,
    control: &Control,
    (rx, tx): (&str, &str),
    initiator: bool,
) -> anyhow::Result<()> {
    let ports = Ports::new(args.size)?;
    let k = &args.key;
    let sub = ports.subscriber(&format!("{k}/{rx}"))?;
    let listener = ports
        .event(&format!("{k}/{rx}/wake"))?
        .listener_builder()
        .create()
        .map_err(|e| anyhow!("listener: {e:?}"))?;
    let notifier = ports
        .event(&format!("{k}/{tx}/wake"))?
        .notifier_builder()
        .create()
        .map_err(|e| anyhow!("notifier: {e:?}"))?;
    if !initiator {
        // The ping's subscriber appears once the ping starts, which waits for this.
        ready("");
    }
    let (publisher, _) = ports.publisher(&format!("{k}/{tx}"), args.size)?;
    if initiator {
        // The pong's subscriber existed before it said ready, so the first ping reaches it;
        // the pong answers once its publisher sees this side's subscriber.
        ready("");
    }
    let wait_one = |deadline: Duration| -> anyhow::Result<Option<Vec<u8>>> {
        let end = Instant::now() + deadline;
        loop {
            if let Some(s) = sub.receive().map_err(|e| anyhow!("receive: {e:?}"))? {
                return Ok(Some(s.payload().to_vec()));
            }
            if Instant::now() > end || control.closed() {
                return Ok(None);
            }
            listener
                .timed_wait(|_| {}, Duration::from_millis(100))
                .map_err(|e| anyhow!("wait: {e:?}"))?;
        }
    };
    if initiator {
        let mut rtts = Rtts::new(args.param as usize);
        for i in 0..rtts.total() as u64 {
            let t = Instant::now();
            send(&publisher, &payload(args.size, i))?;
            notifier.notify().map_err(|e| anyhow!("notify: {e:?}"))?;
            loop {
                let msg = wait_one(Duration::from_secs(5))?.context("no pong within 5 s")?;
                if seq(&msg) == Some(i) {
                    break;
                }
            }
            rtts.push(t);
        }
        rtts.finish();
    } else {
        while let Some(msg) = wait_one(Duration::from_secs(3600))? {
            send(&publisher, &msg)?;
            notifier.notify().map_err(|e| anyhow!("notify: {e:?}"))?;
        }
    }
    Ok(())
}

fn run(args: Args, control: Arc<Control>) -> anyhow::Result<()> {
    match args.role.as_str() {
        "pong" => rtt_side(&args, &control, ("ping", "pong"), false),
        "ping" => rtt_side(&args, &control, ("pong", "ping"), true),
        "sub" => {
            let ports = Ports::new(args.size)?;
            let sub = ports.subscriber(&format!("{}/data", args.key))?;
            let arrivals = Arc::new(Arrivals::default());
            let (a, c) = (arrivals.clone(), control.clone());
            let finisher = std::thread::spawn(move || finish_sub(&a, &c));
            let fanout = subscribers() > 1;
            ready("");
            while !finisher.is_finished() {
                match sub.receive() {
                    Ok(Some(_s)) => arrivals.add(),
                    // Busy-polling, as iceoryx2's own benchmarks do; the subscribers of a
                    // fan-out yield their core when empty (tens of spinning processes on two
                    // cores would otherwise starve the publisher).
                    Ok(None) if fanout => std::thread::yield_now(),
                    Ok(None) => std::hint::spin_loop(),
                    Err(e) => return Err(anyhow!("receive: {e:?}")),
                }
            }
            Ok(())
        }
        "pub" => {
            let ports = Ports::new(args.size)?;
            let (publisher, _) = ports.publisher(&format!("{}/data", args.key), args.size)?;
            ready("");
            let msg = payload(args.size, 0);
            let start = Instant::now();
            let (mut sent, mut to_nobody) = (0u64, 0u64);
            while start.elapsed().as_secs_f64() < args.param {
                for _ in 0..64 {
                    // Seen with iceoryx2 0.10: under load a send now and then reaches no
                    // subscriber although the strategy retries; a user wanting every sample
                    // sends it again.
                    let give_up = Instant::now() + Duration::from_secs(5);
                    while send(&publisher, &msg)? == 0 {
                        to_nobody += 1;
                        if Instant::now() > give_up {
                            anyhow::bail!("a sample reached no subscriber for 5 s");
                        }
                        std::thread::yield_now();
                    }
                    sent += 1;
                }
            }
            println!("result {sent} {}", start.elapsed().as_secs_f64());
            if to_nobody > 0 {
                eprintln!("peer-iceoryx2: {to_nobody} sends of {sent} samples reached no subscriber (sent again)");
            }
            // Samples still in the subscriber's buffer go with a publisher that leaves: stay
            // until the runner has the subscriber's count.
            while !control.closed() {
                std::thread::sleep(Duration::from_millis(5));
            }
            Ok(())
        }
        "idle" => {
            // A node with one service; the partner (KEY ending in /partner) publishes on it.
            let ports = Ports::new(args.size)?;
            let base = args.key.trim_end_matches("/partner");
            if args.key.ends_with("/partner") {
                let _p = ports.publisher(&format!("{base}/idle"), args.size)?;
                ready("");
                while !control.closed() {
                    std::thread::sleep(Duration::from_millis(20));
                }
            } else {
                let _s = ports.subscriber(&format!("{base}/idle"))?;
                ready("");
                while !control.closed() {
                    std::thread::sleep(Duration::from_millis(20));
                }
            }
            Ok(())
        }
        other => anyhow::bail!("unknown role {other:?}"),
    }
}

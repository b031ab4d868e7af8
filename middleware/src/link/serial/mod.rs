//! The serial link: the Serial Transport Protocol (003 ch. 5, DESIGN §5) over one port or a
//! `serialduo` pair, with one peer at the other end ([`PeerAddr::PointToPoint`]).
//!
//! Layers: [`crc`] and [`frame`] (DLE/ETX framing, CRC32, frame types), [`fragment`]
//! (fragmentation, batching, reassembly), [`stp`] (the pure engine: queues, priorities, ARQ,
//! pacing), [`port`] (tty/pty opening and reopening), [`sim`] (fault injection for tests). This
//! file is the async driver: one reader and one writer task per port set, restarted with
//! backoff when the port vanishes.

pub mod crc;
pub mod fragment;
pub mod frame;
pub mod port;
pub mod sim;
pub mod stp;

use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::auth::LinkSecurity;
use super::completion::acknowledge_all;
use super::{Link, LinkHandler, LinkSendError, LinkStats, Outgoing, PeerAddr, SafeCompletion};
use port::{BoxRead, BoxWrite, PortOpener};
use stp::{Stp, StpConfig, StpEvent, StpStats};

/// Why a serial link could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum SerialLinkOpenError {
    /// A port could not be opened.
    #[error("link {link}: cannot open {ports}: {source}")]
    Port {
        /// Link name.
        link: String,
        /// The port(s).
        ports: String,
        /// The OS error.
        source: io::Error,
    },
}

/// The serial link.
pub struct SerialLink {
    index: usize,
    name: String,
    describe: String,
    stp: Mutex<Stp<SafeCompletion>>,
    wake: Notify,
    handler: Arc<dyn LinkHandler>,
    reopens: AtomicU64,
    /// [`STREAM_LINE_TIME`] of line, in bytes.
    stream_window: u64,
}

/// Line time a lossless stream may have unacknowledged on a serial link: enough to keep the
/// line busy across a resend period, short enough that events do not queue for minutes.
const STREAM_LINE_TIME: Duration = Duration::from_secs(4);

use crate::sync::lock;

impl SerialLink {
    /// Opens the ports of `opener` and starts the link's tasks on `tasks`, stopping on `cancel`.
    /// If the ports vanish later they are reopened with backoff. With `security`, every frame
    /// is sealed with the domain key and only sealed frames are taken.
    ///
    /// # Errors
    /// [`SerialLinkOpenError`] when the ports cannot be opened now.
    #[allow(clippy::too_many_arguments)]
    pub fn open(
        index: usize,
        name: &str,
        opener: Arc<dyn PortOpener>,
        cfg: StpConfig,
        security: Option<&LinkSecurity>,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Result<Arc<Self>, SerialLinkOpenError> {
        let first = opener.open().map_err(|source| SerialLinkOpenError::Port {
            link: name.to_owned(),
            ports: opener.describe(),
            source,
        })?;
        let link = Arc::new(SerialLink {
            index,
            name: name.to_owned(),
            describe: opener.describe(),
            stp: Mutex::new(stp_for(cfg, name, security, &handler)),
            wake: Notify::new(),
            handler,
            reopens: AtomicU64::new(0),
            stream_window: cfg.line_bytes(STREAM_LINE_TIME),
        });
        let l = link.clone();
        let t = tasks.clone();
        crate::sync::spawn_tracked(tasks, async move {
            l.supervise(opener, Some(first), t, cancel).await
        });
        Ok(link)
    }

    /// A link over already-open streams (tests, in-memory pipes); it is not reopened.
    pub fn with_streams(
        index: usize,
        name: &str,
        streams: (BoxRead, BoxWrite),
        cfg: StpConfig,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Arc<Self> {
        Self::with_streams_secured(index, name, streams, cfg, None, handler, tasks, cancel)
    }

    /// [`SerialLink::with_streams`] sealing its frames with `security`.
    #[allow(clippy::too_many_arguments)]
    pub fn with_streams_secured(
        index: usize,
        name: &str,
        streams: (BoxRead, BoxWrite),
        cfg: StpConfig,
        security: Option<&LinkSecurity>,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Arc<Self> {
        let link = Arc::new(SerialLink {
            index,
            name: name.to_owned(),
            describe: "in-memory".to_owned(),
            stp: Mutex::new(stp_for(cfg, name, security, &handler)),
            wake: Notify::new(),
            handler,
            reopens: AtomicU64::new(0),
            stream_window: cfg.line_bytes(STREAM_LINE_TIME),
        });
        let l = link.clone();
        let t = tasks.clone();
        crate::sync::spawn_tracked(tasks, async move {
            let (r, w) = streams;
            l.run_ports(r, w, &t, &cancel).await;
            l.fail_all(LinkSendError::Shutdown);
        });
        link
    }

    /// Protocol counters and gauges.
    pub fn stp_stats(&self) -> StpStats {
        lock(&self.stp).stats()
    }

    /// How many times the ports were reopened.
    pub fn reopens(&self) -> u64 {
        self.reopens.load(Ordering::Relaxed)
    }

    async fn supervise(
        self: Arc<Self>,
        opener: Arc<dyn PortOpener>,
        mut first: Option<(BoxRead, BoxWrite)>,
        tasks: TaskTracker,
        cancel: CancellationToken,
    ) {
        let mut backoff = port::REOPEN_MIN;
        while !cancel.is_cancelled() {
            let ports = match first.take() {
                Some(p) => Ok(p),
                None => opener.open(),
            };
            match ports {
                Ok((r, w)) => {
                    backoff = port::REOPEN_MIN;
                    self.run_ports(r, w, &tasks, &cancel).await;
                    if cancel.is_cancelled() {
                        break;
                    }
                    tracing::warn!(link = %self.name, ports = %self.describe, "port lost; reopening");
                    self.reopens.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    tracing::debug!(link = %self.name, ports = %self.describe, error = %e, "reopen failed");
                    backoff = port::next_backoff(backoff);
                }
            }
            tokio::select! {
                _ = cancel.cancelled() => break,
                _ = tokio::time::sleep(backoff) => {}
            }
        }
        self.fail_all(LinkSendError::Shutdown);
    }

    /// Runs a reader and a writer until either fails or `cancel` fires.
    async fn run_ports(
        self: &Arc<Self>,
        r: BoxRead,
        w: BoxWrite,
        tasks: &TaskTracker,
        cancel: &CancellationToken,
    ) {
        let stop = cancel.child_token();
        let reader = {
            let l = self.clone();
            let stop = stop.clone();
            crate::sync::spawn_tracked(tasks, async move {
                l.read_loop(r, &stop).await;
                stop.cancel();
            })
        };
        let writer = {
            let l = self.clone();
            let stop = stop.clone();
            crate::sync::spawn_tracked(tasks, async move {
                l.write_loop(w, &stop).await;
                stop.cancel();
            })
        };
        let _ = reader.await;
        let _ = writer.await;
    }

    async fn read_loop(&self, mut r: BoxRead, stop: &CancellationToken) {
        let mut buf = vec![0u8; 4096];
        let mut events = Vec::new();
        loop {
            let n = tokio::select! {
                _ = stop.cancelled() => return,
                n = r.read(&mut buf) => n,
            };
            match n {
                Ok(0) => {
                    tracing::debug!(link = %self.name, "port closed");
                    return;
                }
                Ok(n) => {
                    lock(&self.stp).on_bytes(Instant::now(), &buf[..n], &mut events);
                    // Acknowledgements may be owed; received ACKs may open the window.
                    self.wake.notify_one();
                    self.handle(&mut events);
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == io::ErrorKind::TimedOut => {}
                Err(e) => {
                    tracing::warn!(link = %self.name, error = %e, "port read failed");
                    return;
                }
            }
        }
    }

    async fn write_loop(&self, mut w: BoxWrite, stop: &CancellationToken) {
        let mut frames: Vec<Vec<u8>> = Vec::new();
        loop {
            let next = {
                let mut stp = lock(&self.stp);
                let now = Instant::now();
                stp.expire(now);
                while let Some(f) = stp.poll_transmit(now) {
                    frames.push(f);
                }
                stp.poll_at(now)
            };
            for f in frames.drain(..) {
                let r = tokio::select! {
                    _ = stop.cancelled() => return,
                    r = w.write_all(&f) => r,
                };
                if let Err(e) = r {
                    tracing::warn!(link = %self.name, error = %e, "port write failed");
                    return;
                }
            }
            if let Err(e) = w.flush().await {
                tracing::warn!(link = %self.name, error = %e, "port flush failed");
                return;
            }
            let sleep = next.unwrap_or_else(|| Instant::now() + Duration::from_secs(3600));
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = self.wake.notified() => {}
                _ = tokio::time::sleep_until(sleep.into()) => {}
            }
        }
    }

    fn handle(&self, events: &mut Vec<StpEvent<SafeCompletion>>) {
        let peer = PeerAddr::PointToPoint;
        for e in events.drain(..) {
            match e {
                StpEvent::Message(m) => self.handler.on_message(self.index, peer, &m),
                StpEvent::Acked(done) => acknowledge_all(done),
                StpEvent::Failed(done, err) => {
                    for d in done {
                        let _ = d.send(Err(err.clone()));
                    }
                }
                StpEvent::PeerReset => {
                    tracing::warn!(link = %self.name, "the peer started a new session: what was in flight to it is lost");
                    self.handler.on_peer_reset(self.index, peer)
                }
            }
        }
    }

    fn fail_all(&self, err: LinkSendError) {
        tracing::debug!(link = %self.name, error = %err, "peer forgotten: new sessions");
        let mut events = lock(&self.stp).reset_peer(fresh_session(), err);
        self.handle(&mut events);
    }
}

fn fresh_session() -> u16 {
    rand::random::<u16>().max(1)
}

/// The link's protocol machine, ageing its reliable messages through `handler`
/// ([`LinkHandler::age_safe`]) as they leave the queue.
fn stp_for(
    cfg: StpConfig,
    name: &str,
    security: Option<&LinkSecurity>,
    handler: &Arc<dyn LinkHandler>,
) -> Stp<SafeCompletion> {
    let mut stp = Stp::new(cfg, fresh_session()).named(name).secured(security);
    let h = handler.clone();
    stp.set_ager(Arc::new(move |msg, waited| h.age_safe(msg, waited)));
    stp
}

impl Link for SerialLink {
    fn name(&self) -> &str {
        &self.name
    }

    fn local_addr(&self) -> String {
        self.describe.clone()
    }

    fn send(&self, to: PeerAddr, out: Outgoing) {
        if to != PeerAddr::PointToPoint {
            return out.refuse(to);
        }
        match out {
            Outgoing::Fast { coalesce, msg } => {
                lock(&self.stp).push_fast(Instant::now(), coalesce, msg);
            }
            Outgoing::Safe { msg, done } => {
                let refused = lock(&self.stp).push_safe(Instant::now(), Vec::from(msg), done);
                if let Some((d, e)) = refused {
                    let _ = d.send(Err(e));
                }
            }
        }
        self.wake.notify_one();
    }

    fn announce(&self, msg: &[u8]) {
        lock(&self.stp).push_announce(msg.to_vec());
        self.wake.notify_one();
    }

    fn close_peer(&self, _to: PeerAddr) {
        self.fail_all(LinkSendError::PeerClosed(self.describe.clone()));
        self.wake.notify_one();
    }

    fn stream_window_bytes(&self) -> Option<u64> {
        Some(self.stream_window)
    }

    fn stats(&self) -> LinkStats {
        lock(&self.stp).stats().link
    }
}

#[cfg(test)]
mod tests {
    use super::sim::{faulty_pipe, Faults};
    use super::*;
    use std::sync::Mutex as StdMutex;
    use tokio::sync::oneshot;

    #[derive(Default)]
    struct Collect {
        got: StdMutex<Vec<Vec<u8>>>,
        changed: Notify,
        resets: AtomicU64,
    }

    impl LinkHandler for Collect {
        fn on_message(&self, _link: usize, _from: PeerAddr, msg: &[u8]) {
            self.got.lock().unwrap().push(msg.to_vec());
            self.changed.notify_one();
        }
        fn on_announce(&self, _link: usize, _from: PeerAddr, _msg: &[u8]) {}
        fn on_peer_reset(&self, _link: usize, _from: PeerAddr) {
            self.resets.fetch_add(1, Ordering::Relaxed);
        }
    }

    type Pair = (
        Arc<SerialLink>,
        Arc<SerialLink>,
        Arc<Collect>,
        Arc<Collect>,
        (sim::OutageSwitch, sim::OutageSwitch),
    );

    fn pair(
        faults: Faults,
        cfg: StpConfig,
        tasks: &TaskTracker,
        cancel: &CancellationToken,
    ) -> Pair {
        let (wa, rb, sa) = faulty_pipe(1, faults);
        let (wb, ra, sb) = faulty_pipe(2, faults);
        let ha = Arc::new(Collect::default());
        let hb = Arc::new(Collect::default());
        let a = SerialLink::with_streams(
            0,
            "a",
            (Box::new(ra), Box::new(wa)),
            cfg,
            ha.clone(),
            tasks,
            cancel.clone(),
        );
        let b = SerialLink::with_streams(
            0,
            "b",
            (Box::new(rb), Box::new(wb)),
            cfg,
            hb.clone(),
            tasks,
            cancel.clone(),
        );
        (a, b, ha, hb, (sa, sb))
    }

    async fn wait_for(h: &Collect, n: usize, timeout: Duration) -> bool {
        tokio::time::timeout(timeout, async {
            loop {
                let notified = h.changed.notified();
                if h.got.lock().unwrap().len() >= n {
                    return;
                }
                notified.await;
            }
        })
        .await
        .is_ok()
    }

    /// Safe messages over a pipe losing and corrupting 1 % of bytes arrive exactly once, in
    /// order, and every completion resolves Ok.
    #[tokio::test]
    async fn safe_messages_cross_a_lossy_pipe_exactly_once_in_order() {
        let tasks = TaskTracker::new();
        let cancel = CancellationToken::new();
        let cfg = StpConfig::new(1_000_000, Duration::from_millis(200), 64, 20);
        let faults = Faults {
            loss: 0.005,
            corrupt: 0.005,
        };
        let (a, _b, _ha, hb, _) = pair(faults, cfg, &tasks, &cancel);
        let mut dones = Vec::new();
        let sent: Vec<Vec<u8>> = (0..300u32)
            .map(|i| {
                let len = (i as usize * 37) % 400;
                let mut m = i.to_le_bytes().to_vec();
                m.resize(4 + len, i as u8);
                m
            })
            .collect();
        for m in &sent {
            let (tx, rx) = oneshot::channel();
            a.send(
                PeerAddr::PointToPoint,
                Outgoing::Safe {
                    msg: m.clone().into(),
                    done: Some(tx.into()),
                },
            );
            dones.push(rx);
        }
        assert!(wait_for(&hb, sent.len(), Duration::from_secs(30)).await);
        for d in dones {
            let r = tokio::time::timeout(Duration::from_secs(10), d).await;
            assert_eq!(r.unwrap().unwrap(), Ok(()));
        }
        assert_eq!(*hb.got.lock().unwrap(), sent);
        let s = a.stp_stats();
        assert!(s.link.retransmitted > 0, "{s:?}");
        cancel.cancel();
        tasks.close();
        tasks.wait().await;
    }

    #[tokio::test]
    async fn fast_messages_and_announces_cross_and_outage_recovers() {
        let tasks = TaskTracker::new();
        let cancel = CancellationToken::new();
        let cfg = StpConfig::new(2_000_000, Duration::from_millis(100), 300, 20);
        let (a, _b, _ha, hb, (sa, _)) = pair(Faults::default(), cfg, &tasks, &cancel);
        a.announce(b"hello");
        a.send(
            PeerAddr::PointToPoint,
            Outgoing::Fast {
                coalesce: Some(1),
                msg: vec![7; 1000],
            },
        );
        assert!(wait_for(&hb, 2, Duration::from_secs(5)).await);
        sa.set(true);
        let (tx, rx) = oneshot::channel();
        a.send(
            PeerAddr::PointToPoint,
            Outgoing::Safe {
                msg: b"after".to_vec().into(),
                done: Some(tx.into()),
            },
        );
        tokio::time::sleep(Duration::from_millis(300)).await;
        sa.set(false);
        let r = tokio::time::timeout(Duration::from_secs(5), rx).await;
        assert_eq!(r.unwrap().unwrap(), Ok(()));
        let got = hb.got.lock().unwrap().clone();
        assert_eq!(got[0], b"hello");
        assert_eq!(got[1], vec![7; 1000]);
        assert_eq!(got[2], b"after");
        a.close_peer(PeerAddr::PointToPoint);
        cancel.cancel();
        tasks.close();
        tasks.wait().await;
    }

    #[tokio::test]
    async fn shutdown_fails_pending_safe_messages() {
        let tasks = TaskTracker::new();
        let cancel = CancellationToken::new();
        let cfg = StpConfig::new(57_600, Duration::from_millis(100), 300, 20);
        let (a, _b, _ha, _hb, (sa, _)) = pair(Faults::default(), cfg, &tasks, &cancel);
        sa.set(true);
        let (tx, rx) = oneshot::channel();
        a.send(
            PeerAddr::PointToPoint,
            Outgoing::Safe {
                msg: b"never".to_vec().into(),
                done: Some(tx.into()),
            },
        );
        cancel.cancel();
        let r = tokio::time::timeout(Duration::from_secs(5), rx).await;
        assert!(r.unwrap().unwrap().is_err());
        tasks.close();
        tasks.wait().await;
    }
}

//! The control thread of a shared-memory link: creates and owns the iceoryx2 node and does
//! what may wait on the file system (creating the inbox, opening peers' inboxes, listing the
//! host's nodes, removing dead ones' resources), never on a tokio worker.
//!
//! One thread does all of it, from the link's creation on: iceoryx2's setup runs deep on the
//! stack and allocates much that it frees again, and a second thread doing part of it (a tokio
//! blocking thread creating the inbox) kept a second deep stack and a second malloc arena
//! resident for the process's life.

use std::collections::HashSet;
use std::sync::atomic::Ordering;
use std::sync::{mpsc, Arc};
use std::time::Instant;

use tokio::sync::oneshot;

use super::inbox::{self, Inbox, Node, OpenError};
use super::{ShmLink, ShmLinkOpenError, ShmLinkOptions};
use crate::link::{LinkSendError, PeerAddr};
use crate::sync::lock;

/// Requests to the control thread.
pub(super) enum Ctl {
    /// Open the inbox of this peer.
    Open(u64),
    /// Open the bulk inbox of this peer.
    OpenBulk(u64),
    /// The link shuts down.
    Stop,
}

/// The control thread's state.
struct Control {
    link: Arc<ShmLink>,
    node: Node,
    ctl: mpsc::Receiver<Ctl>,
    next_scan: Instant,
    /// Peers we were told about once that no inbox has room for them (this one's or theirs:
    /// `maxPeers` is taken); forgotten when they connect or die.
    no_room: HashSet<u64>,
}

/// A started control thread, as the opening link sees it.
pub(super) struct Started {
    /// The inbox the thread created, or why it could not.
    pub(super) inbox: oneshot::Receiver<Result<Inbox, ShmLinkOpenError>>,
    /// Gives the thread the link to serve; dropped unsent, it ends the thread.
    pub(super) serve: mpsc::Sender<Arc<ShmLink>>,
    /// Sent once the first scan connected to the same-host nodes already there.
    pub(super) scanned: oneshot::Receiver<()>,
    /// Closed when the thread ends.
    pub(super) ended: oneshot::Receiver<()>,
}

/// Starts the control thread of link `id`: it creates the inbox, waits for the link, scans
/// once, then serves `ctl` until the link stops.
pub(super) fn start(
    options: &ShmLinkOptions,
    id: u64,
    ctl: mpsc::Receiver<Ctl>,
) -> std::io::Result<Started> {
    let (inbox_tx, inbox) = oneshot::channel();
    let (serve, serve_rx) = mpsc::channel::<Arc<ShmLink>>();
    let (scanned_tx, scanned) = oneshot::channel();
    let (ended_tx, ended) = oneshot::channel::<()>();
    let opts = options.clone();
    std::thread::Builder::new()
        .name(format!("marea-shm-ctl-{}", options.name))
        .spawn(move || {
            let _ended = ended_tx;
            let node = match Inbox::create(&opts, id) {
                Ok((node, made)) => {
                    if inbox_tx.send(Ok(made)).is_err() {
                        return;
                    }
                    node
                }
                Err(e) => {
                    let _ = inbox_tx.send(Err(e));
                    return;
                }
            };
            let Ok(link) = serve_rx.recv() else {
                return;
            };
            let mut control = Control {
                link,
                node,
                ctl,
                next_scan: Instant::now(),
                no_room: HashSet::new(),
            };
            control.scan();
            let _ = scanned_tx.send(());
            control.run();
        })?;
    Ok(Started {
        inbox,
        serve,
        scanned,
        ended,
    })
}

impl Control {
    /// Serves requests and rescans until the link stops.
    fn run(mut self) {
        loop {
            let timeout = self.next_scan.saturating_duration_since(Instant::now());
            match self.ctl.recv_timeout(timeout) {
                Ok(Ctl::Open(id)) => self.connect(id),
                Ok(Ctl::OpenBulk(id)) => self.open_bulk(id),
                Ok(Ctl::Stop) | Err(mpsc::RecvTimeoutError::Disconnected) => break,
                Err(mpsc::RecvTimeoutError::Timeout) => {}
            }
            if self.link.stop.load(Ordering::SeqCst) {
                break;
            }
            if Instant::now() >= self.next_scan {
                self.scan();
            }
        }
    }

    /// Opens the bulk inbox of peer `id` (asked for by its first large message) and writes
    /// what waited for it; if it cannot be opened, large messages go fragmented into the safe
    /// inbox.
    fn open_bulk(&mut self, id: u64) {
        let Some(p) = self.link.peer(id, false) else {
            return;
        };
        let opened = inbox::open_bulk(&self.node, &self.link.options.service, id);
        let mut st = lock(&p);
        let ok = match opened {
            Ok(b) => {
                st.bulk = Some(b);
                true
            }
            Err(e) => {
                tracing::warn!(link = %self.link.options.name, peer = format_args!("{id:016x}"), error = %e, "cannot open the peer's bulk inbox; large messages go fragmented");
                false
            }
        };
        self.link
            .with_tx(&mut st, |tx, w, c| tx.bulk_opened(ok, w, c));
    }

    /// Opens peer `id`'s inbox if it is not open yet, and writes what waited for it.
    fn connect(&mut self, id: u64) {
        let Some(p) = self.link.peer(id, true) else {
            if id != self.link.id && self.no_room.insert(id) {
                tracing::warn!(link = %self.link.options.name, peer = format_args!("{id:016x}"), max_peers = self.link.options.max_peers, "this link has maxPeers same-host peers already; this one cannot reach it over shared memory (raise maxPeers in <shm>)");
            }
            return;
        };
        if lock(&p).conn.is_some() {
            return;
        }
        // Opening may wait (iceoryx2 retries a service still being created, e.g. by a peer
        // starting up): not under the peer's lock, which every send to it takes. A publisher
        // blocked 3 s in `set` while a restarted subscriber's inbox was being opened.
        let opened = inbox::open_conn(&self.node, &self.link.options.service, id);
        let mut st = lock(&p);
        if st.conn.is_some() {
            return;
        }
        match opened {
            Ok(c) => {
                st.conn = Some(c);
                self.link.with_tx(&mut st, |tx, w, c| tx.opened(w, c));
                self.no_room.remove(&id);
            }
            Err(e @ OpenError::Full(_)) => {
                if self.no_room.insert(id) {
                    tracing::warn!(link = %self.link.options.name, peer = format_args!("{id:016x}"), error = %e, "cannot reach a same-host peer over shared memory");
                }
            }
            Err(e) => {
                tracing::debug!(link = %self.link.options.name, peer = format_args!("{id:016x}"), error = %e, "peer inbox not open yet");
            }
        }
    }

    /// Lists the host's iceoryx2 nodes: connects to the inboxes of the same `service` and
    /// removes what dead ones left behind.
    fn scan(&mut self) {
        let listing = inbox::list_nodes(&self.node, &self.link.options.service);
        if let Some(e) = listing.error {
            tracing::warn!(link = %self.link.options.name, error = %e, "listing shared-memory nodes failed");
        }
        for (id, dead) in listing.dead {
            self.no_room.remove(&id);
            match dead.remove_stale() {
                Ok(()) => {
                    tracing::info!(link = %self.link.options.name, peer = format_args!("{id:016x}"), "removed resources of a dead shared-memory node")
                }
                Err(e) => {
                    tracing::debug!(link = %self.link.options.name, error = %e, "dead node cleanup failed")
                }
            }
            let p = lock(&self.link.peers).remove(&id);
            if let Some(p) = p {
                lock(&p)
                    .tx
                    .fail_all(&LinkSendError::PeerClosed(PeerAddr::Shm(id).to_string()));
            }
        }
        for id in listing.alive {
            if id != self.link.id {
                self.connect(id);
            }
        }
        self.next_scan = Instant::now() + self.link.options.scan;
    }
}

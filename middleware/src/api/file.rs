//! File transfer: chunked, windowed, hash-verified, atomically renamed, resumable after either
//! side restarts, with observable progress.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio::sync::{oneshot, watch};
use tokio_util::sync::{CancellationToken, DropGuard};

use super::errors::{FileSendError, RecvError};
use super::service::Declared;
use crate::codec::encode_message;
use crate::link::{LinkSendError, Outgoing, DEFAULT_FILE_CHUNK};
use crate::node::files::{hash_file, Control, FileSinkStats, ReceivedFile, SinkMailbox, SinkState};
use crate::node::{LocalOffer, NodeInner};
use crate::protocol::{FileVerdict, ItemKind, Message, NodeId};

/// Most bytes in flight of one transfer, whatever its window in chunks: with the large chunks of
/// shared memory, 128 chunks would be 32 MiB read ahead of the receiver.
const MAX_WINDOW_BYTES: usize = 16 << 20;

/// A sink accepting files; dropping it withdraws the sink.
pub struct FileSink {
    offer: Arc<LocalOffer>,
    mailbox: Arc<SinkMailbox>,
    state: Arc<SinkState>,
    _declared: Declared,
    /// Stops the periodic removal of stale partial files with the sink.
    _sweeping: DropGuard,
}

impl FileSink {
    pub(crate) fn new(
        offer: Arc<LocalOffer>,
        mailbox: Arc<SinkMailbox>,
        declared: Declared,
        state: Arc<SinkState>,
        sweeping: CancellationToken,
    ) -> Self {
        FileSink {
            offer,
            mailbox,
            state,
            _declared: declared,
            _sweeping: sweeping.drop_guard(),
        }
    }

    /// Full name senders use.
    pub fn name(&self) -> &str {
        &self.offer.name
    }

    /// The directory files are stored in.
    pub fn dir(&self) -> &Path {
        &self.state.dir
    }

    /// What the sink stored and refused since it opened.
    pub fn stats(&self) -> FileSinkStats {
        self.state.stats()
    }

    /// Removes the stale partial files now (it also happens periodically); returns how many.
    pub fn remove_stale_parts(&self) -> usize {
        self.state.remove_stale_parts()
    }

    /// The next file stored (hash verified, renamed into place).
    ///
    /// # Errors
    /// [`RecvError::Closed`] at shutdown.
    pub async fn recv(&self) -> Result<ReceivedFile, RecvError> {
        self.mailbox.pop().await.ok_or(RecvError::Closed)
    }

    /// Like [`FileSink::recv`] with a time limit.
    ///
    /// # Errors
    /// [`RecvError::Closed`] or [`RecvError::Timeout`].
    pub async fn recv_timeout(&self, timeout: Duration) -> Result<ReceivedFile, RecvError> {
        match tokio::time::timeout(timeout, self.recv()).await {
            Ok(r) => r,
            Err(_) => Err(RecvError::Timeout(timeout)),
        }
    }
}

/// Tuning of one transfer.
#[derive(Debug, Clone, Copy)]
pub struct SendFileOptions {
    /// How long to keep looking for the sink and retrying after the receiver disappears.
    pub retry_for: Duration,
    /// Chunks in flight (at most 16 MiB).
    pub window: usize,
}

impl Default for SendFileOptions {
    fn default() -> Self {
        SendFileOptions {
            retry_for: Duration::from_secs(60),
            window: 128,
        }
    }
}

/// Progress of a transfer.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FileProgress {
    /// File size.
    pub total: u64,
    /// Bytes the receiver acknowledged.
    pub acknowledged: u64,
    /// Content bytes sent, over all attempts.
    pub sent: u64,
    /// Where the current attempt started (bytes the receiver already had).
    pub resumed_from: u64,
    /// Attempts so far.
    pub attempts: u32,
}

/// Outcome of a completed transfer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileReport {
    /// File size.
    pub size: u64,
    /// Content bytes sent, over all attempts (less than `size` when resumed).
    pub sent: u64,
    /// Where the last attempt started.
    pub resumed_from: u64,
    /// Attempts made.
    pub attempts: u32,
    /// The receiving node.
    pub receiver: String,
    /// Time taken.
    pub elapsed: Duration,
}

/// A transfer running in the background.
pub struct FileTransfer {
    progress: watch::Receiver<FileProgress>,
    result: oneshot::Receiver<Result<FileReport, FileSendError>>,
}

impl FileTransfer {
    pub(crate) fn start(
        node: Arc<NodeInner>,
        path: PathBuf,
        to: String,
        options: SendFileOptions,
    ) -> Self {
        let (ptx, prx) = watch::channel(FileProgress::default());
        let (rtx, rrx) = oneshot::channel();
        let tasks = node.tasks.clone();
        tasks.spawn(async move {
            let r = Sender {
                node,
                path,
                to,
                options,
                progress: ptx,
            }
            .run()
            .await;
            let _ = rtx.send(r);
        });
        FileTransfer {
            progress: prx,
            result: rrx,
        }
    }

    /// The latest progress.
    pub fn progress(&self) -> FileProgress {
        *self.progress.borrow()
    }

    /// A receiver that changes whenever progress does.
    pub fn watch_progress(&self) -> watch::Receiver<FileProgress> {
        self.progress.clone()
    }

    /// Waits for the outcome.
    ///
    /// # Errors
    /// [`FileSendError`] naming what failed.
    pub async fn wait(self) -> Result<FileReport, FileSendError> {
        self.result.await.unwrap_or(Err(FileSendError::Closed))
    }
}

/// The error a sender reports for a receiver's verdict other than `Stored`.
fn refusal(node: &str, verdict: FileVerdict) -> FileSendError {
    let node = node.to_owned();
    match verdict {
        FileVerdict::TooLarge { size, max } => FileSendError::TooLarge { node, size, max },
        FileVerdict::QuotaExceeded { needed, quota } => FileSendError::QuotaExceeded {
            node,
            needed,
            quota,
        },
        FileVerdict::Busy { max } => FileSendError::Busy { node, max },
        FileVerdict::Failed(reason) => FileSendError::Rejected { node, reason },
        FileVerdict::Stored => FileSendError::Rejected {
            node,
            reason: "stored (unexpected here)".into(),
        },
    }
}

struct Sender {
    node: Arc<NodeInner>,
    path: PathBuf,
    to: String,
    options: SendFileOptions,
    progress: watch::Sender<FileProgress>,
}

enum Attempt {
    Done(Result<FileReport, FileSendError>),
    Retry(String),
}

impl Sender {
    fn io(&self, source: std::io::Error) -> FileSendError {
        FileSendError::Io {
            path: self.path.display().to_string(),
            source,
        }
    }

    /// The peer to send to, the receiving node's name, the sink's id there, and whether the
    /// receiver is that peer itself (not a node behind a gateway).
    fn find_sink(&self) -> Option<(NodeId, String, u32, bool)> {
        self.node.peers.iter().find_map(|p| {
            p.offers
                .iter()
                .find(|(id, o)| {
                    o.kind == ItemKind::File && *o.name == *self.to && !p.shadowed.contains(id)
                })
                // Through a gateway, the receiver is the node behind it.
                .map(|(id, o)| {
                    let name = o.origin_name.as_ref().unwrap_or(&p.name);
                    (p.id, name.to_string(), *id, o.origin.is_none())
                })
        })
    }

    async fn run(self) -> Result<FileReport, FileSendError> {
        let started = Instant::now();
        let give_up = tokio::time::Instant::now() + self.options.retry_for;
        let size = tokio::fs::metadata(&self.path)
            .await
            .map_err(|e| self.io(e))?
            .len();
        let hash = hash_file(self.path.clone()).await.map_err(|e| self.io(e))?;
        let name = self
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "file".into());
        let transfer = {
            let mut h = blake3::Hasher::new();
            h.update(&hash);
            h.update(name.as_bytes());
            let d = h.finalize();
            let mut b = [0u8; 8];
            b.copy_from_slice(&d.as_bytes()[..8]);
            u64::from_le_bytes(b)
        };
        self.progress.send_modify(|p| p.total = size);
        let mut changed = self.node.changed.subscribe();
        let mut last = String::new();
        loop {
            let Some((peer, peer_name, sink, direct)) = self.find_sink() else {
                let wait = tokio::select! {
                    _ = self.node.cancel.cancelled() => return Err(FileSendError::Closed),
                    r = tokio::time::timeout_at(give_up, changed.changed()) => r,
                };
                if wait.is_err() {
                    let attempts = self.progress.borrow().attempts;
                    return Err(if attempts == 0 {
                        FileSendError::NoSink {
                            to: self.to.clone(),
                            waited: self.options.retry_for,
                        }
                    } else {
                        FileSendError::GaveUp {
                            to: self.to.clone(),
                            last,
                        }
                    });
                }
                continue;
            };
            self.progress.send_modify(|p| p.attempts += 1);
            let attempt = self
                .attempt(
                    (peer, &peer_name, sink, direct),
                    transfer,
                    &name,
                    size,
                    hash,
                    started,
                )
                .await;
            self.node.transfers.unregister_sender(transfer);
            match attempt {
                Attempt::Done(r) => return r,
                Attempt::Retry(why) => {
                    tracing::info!(to = %self.to, receiver = %peer_name, reason = %why, "file transfer interrupted; will resume");
                    last = why;
                    if tokio::time::Instant::now() >= give_up {
                        return Err(FileSendError::GaveUp {
                            to: self.to.clone(),
                            last,
                        });
                    }
                    // Let the peer table settle (the receiver is dropped, then reappears).
                    let _ =
                        tokio::time::timeout(Duration::from_millis(200), changed.changed()).await;
                }
            }
        }
    }

    async fn attempt(
        &self,
        (peer, peer_name, sink, direct): (NodeId, &str, u32, bool),
        transfer: u64,
        name: &str,
        size: u64,
        hash: [u8; 32],
        started: Instant,
    ) -> Attempt {
        let mut ctl = self.node.transfers.register_sender(transfer, peer);
        let Some((link, addr)) = self.node.peers.get(&peer).map(|p| (p.link, p.addr)) else {
            return Attempt::Retry("receiver vanished".into());
        };
        self.node.send_safe(
            link,
            addr,
            &Message::FileOffer {
                transfer,
                sink,
                name: name.to_owned(),
                size,
                hash,
            },
        );
        let report = |sent: u64, resumed_from: u64, attempts: u32| FileReport {
            size,
            sent,
            resumed_from,
            attempts,
            receiver: peer_name.to_owned(),
            elapsed: started.elapsed(),
        };
        let offset = match tokio::time::timeout(Duration::from_secs(10), ctl.recv()).await {
            Ok(Some(Control::Accept(o))) if o <= size => o,
            Ok(Some(Control::Accept(o))) => {
                return Attempt::Done(Err(FileSendError::Rejected {
                    node: peer_name.to_owned(),
                    reason: format!("receiver claims {o} bytes of a {size}-byte file"),
                }))
            }
            Ok(Some(Control::Done(FileVerdict::Stored))) => {
                let p = *self.progress.borrow();
                return Attempt::Done(Ok(report(p.sent, size, p.attempts)));
            }
            Ok(Some(Control::Done(verdict))) => {
                return Attempt::Done(Err(refusal(peer_name, verdict)))
            }
            Ok(Some(Control::PeerLost(why))) => return Attempt::Retry(why),
            Ok(None) => return Attempt::Done(Err(FileSendError::Closed)),
            Err(_) => {
                return Attempt::Retry(format!("node '{peer_name}' did not answer the offer"))
            }
        };
        self.progress.send_modify(|p| {
            p.resumed_from = offset;
            p.acknowledged = offset;
        });
        let mut file = match tokio::fs::File::open(&self.path).await {
            Ok(f) => f,
            Err(e) => return Attempt::Done(Err(self.io(e))),
        };
        if let Err(e) = file.seek(std::io::SeekFrom::Start(offset)).await {
            return Attempt::Done(Err(self.io(e)));
        }
        // Chunks as large as the link to the receiver carries best. Through a gateway the chunks
        // are relayed as they are onto links we cannot see (a radio), so they keep the size
        // every link carries.
        let chunk = match self.node.links().get(link) {
            Some(l) if direct => l.file_chunk().max(1),
            _ => DEFAULT_FILE_CHUNK,
        };
        // The window moves on the receiver's own progress acknowledgements (end to end, also
        // through gateways); the first hop's acknowledgements only reveal a broken link early.
        let window_bytes =
            (self.options.window.max(1) * chunk).min(MAX_WINDOW_BYTES.max(chunk)) as u64;
        // How long without progress before the attempt is abandoned (and resumed): generous
        // enough for the receiver to hash a large file once everything arrived.
        let stall = Duration::from_secs(30) + Duration::from_millis(size / 50_000);
        let mut deadline = tokio::time::Instant::now() + stall;
        let mut acked = offset;
        let mut pos = offset;
        let mut inflight: VecDeque<oneshot::Receiver<Result<(), LinkSendError>>> = VecDeque::new();
        enum Heard {
            Cancelled,
            Link(Result<Result<(), LinkSendError>, oneshot::error::RecvError>),
            Receiver(Option<Control>),
            Stalled,
        }
        loop {
            while pos < size && pos - acked < window_bytes {
                let want = chunk.min((size - pos) as usize);
                let mut data = vec![0u8; want];
                if let Err(e) = file.read_exact(&mut data).await {
                    return Attempt::Done(Err(self.io(e)));
                }
                let (tx, rx) = oneshot::channel();
                let msg = encode_message(&Message::FileChunk {
                    transfer,
                    offset: pos,
                    data,
                });
                self.node.send_to(
                    link,
                    addr,
                    Outgoing::Safe {
                        msg,
                        done: Some(tx),
                    },
                );
                pos += want as u64;
                inflight.push_back(rx);
                self.progress.send_modify(|p| p.sent += want as u64);
            }
            let heard = tokio::select! {
                _ = self.node.cancel.cancelled() => Heard::Cancelled,
                r = async {
                    match inflight.front_mut() {
                        Some(rx) => rx.await,
                        None => std::future::pending().await,
                    }
                } => Heard::Link(r),
                c = ctl.recv() => Heard::Receiver(c),
                _ = tokio::time::sleep_until(deadline) => Heard::Stalled,
            };
            match heard {
                Heard::Cancelled => return Attempt::Done(Err(FileSendError::Closed)),
                Heard::Link(r) => {
                    inflight.pop_front();
                    match r {
                        Ok(Ok(())) => {}
                        Ok(Err(e)) => return Attempt::Retry(format!("node '{peer_name}': {e}")),
                        Err(_) => {
                            return Attempt::Retry(format!("node '{peer_name}': link closed"))
                        }
                    }
                }
                Heard::Receiver(Some(Control::Accept(o))) => {
                    if o > acked && o <= size {
                        acked = o;
                        deadline = tokio::time::Instant::now() + stall;
                        self.progress.send_modify(|p| p.acknowledged = o);
                    }
                }
                Heard::Receiver(Some(Control::Done(FileVerdict::Stored))) => {
                    self.progress.send_modify(|p| p.acknowledged = size);
                    let p = *self.progress.borrow();
                    return Attempt::Done(Ok(report(p.sent, offset, p.attempts)));
                }
                Heard::Receiver(Some(Control::Done(verdict))) => {
                    return Attempt::Done(Err(refusal(peer_name, verdict)))
                }
                Heard::Receiver(Some(Control::PeerLost(why))) => return Attempt::Retry(why),
                Heard::Receiver(None) => return Attempt::Done(Err(FileSendError::Closed)),
                Heard::Stalled => {
                    return Attempt::Retry(format!(
                        "node '{peer_name}' acknowledged nothing for {stall:?}"
                    ))
                }
            }
        }
    }
}

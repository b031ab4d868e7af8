//! Sending a file: found by the sink's name, offered, read in chunks sent in a window that the
//! receiver's own acknowledgements move (end to end, also through gateways), resumed from what
//! the receiver has when it disappears and comes back, until `retry_for` runs out.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio::sync::{oneshot, watch};

use super::{hash_file, Control};
use crate::codec::encode_message;
use crate::link::{LinkSendError, Outgoing, DEFAULT_FILE_CHUNK};
use crate::node::NodeInner;
use crate::protocol::{FileOffer, FileVerdict, ItemKind, Message, NodeId};

/// Why a file could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum FileSendError {
    /// No node offers a sink of that name within the retry time.
    #[error("no file sink '{to}' found within {waited:?}")]
    NoSink {
        /// Sink name.
        to: String,
        /// How long we looked.
        waited: Duration,
    },
    /// The local file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The receiver refused or failed.
    #[error("node '{node}' refused the file: {reason}")]
    Rejected {
        /// Receiving node.
        node: String,
        /// Its reason.
        reason: String,
    },
    /// The receiver's access rules (`<access>` in its network.xml) do not let this node send
    /// to that sink.
    #[error("node '{node}' denied the file: {reason}")]
    Denied {
        /// Receiving node.
        node: String,
        /// Its reason (names the sink and the sender).
        reason: String,
    },
    /// The receiver kept disappearing until the retry time ran out.
    #[error("gave up sending to '{to}': {last}")]
    GaveUp {
        /// Sink name.
        to: String,
        /// The last failure.
        last: String,
    },
    /// The node shut down.
    #[error("node is shutting down")]
    Closed,
    /// The receiver refused the file as larger than its sink accepts (announced, or sent
    /// beyond the announcement).
    #[error("node '{node}' refused the file as too large: {size} bytes, at most {max}")]
    TooLarge {
        /// Receiving node.
        node: String,
        /// Bytes announced or reached.
        size: u64,
        /// The sink's limit.
        max: u64,
    },
    /// The receiver's sink has no room left under its quota.
    #[error("node '{node}' refused the file: the sink would hold {needed} bytes, quota {quota}")]
    QuotaExceeded {
        /// Receiving node.
        node: String,
        /// Bytes the sink would hold with this file.
        needed: u64,
        /// The sink's quota.
        quota: u64,
    },
    /// The receiver's sink already receives its maximum of files at once; try again later.
    #[error("node '{node}' is busy: its sink receives {max} files at once already")]
    Busy {
        /// Receiving node.
        node: String,
        /// Concurrent transfers the sink allows.
        max: u32,
    },
}

/// Most bytes in flight of one transfer, whatever its window in chunks: with the large chunks of
/// shared memory, 128 chunks would be 32 MiB read ahead of the receiver.
const MAX_WINDOW_BYTES: usize = 16 << 20;

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
        FileVerdict::Denied(reason) => FileSendError::Denied { node, reason },
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
        self.node.peers.by_id.iter().find_map(|p| {
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
        let Some((link, addr)) = self.node.peers.by_id.get(&peer).map(|p| (p.link, p.addr)) else {
            return Attempt::Retry("receiver vanished".into());
        };
        self.node.send_safe(
            link,
            addr,
            &Message::FileOffer(FileOffer {
                transfer,
                sink,
                name: name.to_owned(),
                size,
                hash,
                sender: None,
            }),
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
                        msg: msg.into(),
                        done: Some(tx.into()),
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

/// Starts sending the file at `path` to the sink named `to` in the background: its progress as
/// it changes, and its outcome.
pub(crate) fn start_sending(
    node: Arc<NodeInner>,
    path: PathBuf,
    to: String,
    options: SendFileOptions,
) -> (
    watch::Receiver<FileProgress>,
    oneshot::Receiver<Result<FileReport, FileSendError>>,
) {
    let (ptx, prx) = watch::channel(FileProgress::default());
    let (rtx, rrx) = oneshot::channel();
    let tasks = node.tasks.clone();
    crate::sync::spawn_tracked(&tasks, async move {
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
    (prx, rrx)
}

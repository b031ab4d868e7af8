//! File transfer, node side: routing control messages to sending tasks, and receiving files
//! into a sink's directory (temp file, hash check, atomic rename, resume from what is on disk).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use dashmap::DashMap;
use tokio::io::AsyncWriteExt;
use tokio::sync::{mpsc, Notify};

use super::{lock, NodeInner, OfferRole};
use crate::protocol::{FileVerdict, Message, NodeId};

/// Chunks between two progress acknowledgements of a receiver (`FileAccept` with the bytes
/// written so far). Well below the sender's default window, so it never stalls on them.
const PROGRESS_EVERY: u32 = 16;
/// Bytes after which a receiver acknowledges progress even before [`PROGRESS_EVERY`] chunks:
/// large chunks (shared memory) would otherwise move the sender's window in big steps.
const PROGRESS_BYTES: u64 = 1 << 20;

/// What a sending task hears from the receiver (or about it).
#[derive(Debug)]
pub(crate) enum Control {
    Accept(u64),
    Done(FileVerdict),
    PeerLost(String),
}

struct Incoming {
    node: NodeId,
    chunks: mpsc::UnboundedSender<(u64, Vec<u8>)>,
}

/// Transfers in progress on this node.
#[derive(Default)]
pub(crate) struct Transfers {
    senders: DashMap<u64, (NodeId, mpsc::UnboundedSender<Control>)>,
    incoming: DashMap<u64, Incoming>,
}

impl Transfers {
    pub fn register_sender(&self, transfer: u64, node: NodeId) -> mpsc::UnboundedReceiver<Control> {
        let (tx, rx) = mpsc::unbounded_channel();
        self.senders.insert(transfer, (node, tx));
        rx
    }

    pub fn unregister_sender(&self, transfer: u64) {
        self.senders.remove(&transfer);
    }

    pub fn to_sender(&self, transfer: u64, c: Control) {
        if let Some(s) = self.senders.get(&transfer) {
            let _ = s.1.send(c);
        }
    }

    pub fn peer_lost(&self, node: NodeId, name: &str, reason: &str) {
        for s in self.senders.iter().filter(|s| s.0 == node) {
            let _ =
                s.1.send(Control::PeerLost(format!("node '{name}' {reason}")));
        }
        self.incoming.retain(|_, i| i.node != node);
    }
}

/// A file that arrived in a sink.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReceivedFile {
    /// Where it was stored.
    pub path: PathBuf,
    /// Its name as sent.
    pub name: String,
    /// Size in bytes.
    pub size: u64,
    /// The sending node.
    pub from: String,
    /// Bytes that were already on disk from an interrupted attempt.
    pub resumed_from: u64,
}

/// Completed files waiting for the sink's owner.
#[derive(Default)]
pub(crate) struct SinkMailbox {
    queue: Mutex<(VecDeque<ReceivedFile>, bool)>,
    notify: Notify,
}

impl SinkMailbox {
    pub fn push(&self, f: ReceivedFile) {
        lock(&self.queue).0.push_back(f);
        self.notify.notify_one();
    }

    pub fn close(&self) {
        lock(&self.queue).1 = true;
        self.notify.notify_one();
    }

    pub async fn pop(&self) -> Option<ReceivedFile> {
        loop {
            {
                let mut g = lock(&self.queue);
                if let Some(f) = g.0.pop_front() {
                    return Some(f);
                }
                if g.1 {
                    return None;
                }
            }
            self.notify.notified().await;
        }
    }
}

/// A plain file name: no directories, no parent references, not hidden.
fn safe_file_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 255
        && !name.starts_with('.')
        && !name.contains(['/', '\\', '\0'])
}

fn part_path(dir: &Path, name: &str, transfer: u64) -> PathBuf {
    dir.join(format!(".{name}.{transfer:016x}.part"))
}

/// blake3 of a file, off the async workers.
pub(crate) async fn hash_file(path: PathBuf) -> std::io::Result<[u8; 32]> {
    tokio::task::spawn_blocking(move || {
        let mut h = blake3::Hasher::new();
        let mut f = std::fs::File::open(&path)?;
        std::io::copy(&mut f, &mut h)?;
        Ok(*h.finalize().as_bytes())
    })
    .await
    .map_err(std::io::Error::other)?
}

impl NodeInner {
    fn reply_file(&self, node: NodeId, transfer: u64, verdict: FileVerdict) {
        self.send_safe_to_node(node, &Message::FileDone { transfer, verdict });
    }

    pub fn on_file_offer(
        self: &Arc<Self>,
        node: NodeId,
        transfer: u64,
        sink: u32,
        name: String,
        size: u64,
        hash: [u8; 32],
    ) {
        let sink_name = self.offers.get(&sink).map(|o| o.name.clone());
        if let Some(sink_name) = sink_name {
            if !self.permitted(node, crate::config::AccessKind::File, &sink_name) {
                let verdict = FileVerdict::Denied(format!(
                    "sending to '{sink_name}' is not allowed for this node by <access>"
                ));
                self.reply_file(node, transfer, verdict);
                return;
            }
        }
        let relay = self.offers.get(&sink).and_then(|o| match o.role {
            OfferRole::Relay { origin, remote_id } => Some((origin, remote_id)),
            _ => None,
        });
        if let Some((receiver, remote_sink)) = relay {
            let offer = Message::FileOffer {
                transfer,
                sink: remote_sink,
                name,
                size,
                hash,
            };
            self.relay_file_offer(node, receiver, transfer, &offer);
            return;
        }
        let Some((dir, mailbox)) = self.offers.get(&sink).and_then(|o| match &o.role {
            OfferRole::File { dir, mailbox } => Some((dir.clone(), mailbox.clone())),
            _ => None,
        }) else {
            self.reply_file(
                node,
                transfer,
                FileVerdict::Failed("no such file sink".into()),
            );
            return;
        };
        if !safe_file_name(&name) {
            self.reply_file(
                node,
                transfer,
                FileVerdict::Failed(format!(
                    "refused file name {name:?}: must be a plain file name"
                )),
            );
            return;
        }
        // A new offer for the same transfer (the sender restarted) replaces the old writer.
        self.transfers.incoming.remove(&transfer);
        let part = part_path(&dir, &name, transfer);
        let mut offset = std::fs::metadata(&part).map(|m| m.len()).unwrap_or(0);
        if offset > size {
            let _ = std::fs::remove_file(&part);
            offset = 0;
        }
        let (tx, mut rx) = mpsc::unbounded_channel::<(u64, Vec<u8>)>();
        self.transfers
            .incoming
            .insert(transfer, Incoming { node, chunks: tx });
        let from = self
            .peers
            .get(&node)
            .map(|p| p.name.to_string())
            .unwrap_or_default();
        let inner = self.clone();
        self.tasks.spawn(async move {
            let result: Result<ReceivedFile, String> = async {
                let file = tokio::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&part)
                    .await
                    .map_err(|e| format!("cannot open {}: {e}", part.display()))?;
                let mut w = tokio::io::BufWriter::with_capacity(1 << 18, file);
                let mut expected = offset;
                let mut acknowledged = offset;
                let mut unacknowledged = 0u32;
                while expected < size {
                    let next = tokio::select! {
                        _ = inner.cancel.cancelled() => None,
                        c = rx.recv() => c,
                    };
                    let Some((at, data)) = next else {
                        // Sender gone or node stopping: keep what we have for a resume.
                        let _ = w.flush().await;
                        return Err(String::new());
                    };
                    if at != expected || at + data.len() as u64 > size {
                        continue;
                    }
                    w.write_all(&data)
                        .await
                        .map_err(|e| format!("cannot write {}: {e}", part.display()))?;
                    expected += data.len() as u64;
                    // End-to-end progress: the sender's window moves on what we wrote, not on
                    // what the first hop (maybe a gateway) acknowledged.
                    unacknowledged += 1;
                    if unacknowledged >= PROGRESS_EVERY
                        || expected - acknowledged >= PROGRESS_BYTES
                        || expected == size
                    {
                        unacknowledged = 0;
                        acknowledged = expected;
                        inner.send_safe_to_node(
                            node,
                            &Message::FileAccept {
                                transfer,
                                offset: expected,
                            },
                        );
                    }
                }
                w.flush()
                    .await
                    .map_err(|e| format!("cannot write {}: {e}", part.display()))?;
                drop(w);
                let got = hash_file(part.clone())
                    .await
                    .map_err(|e| format!("cannot read back {}: {e}", part.display()))?;
                if got != hash {
                    let _ = tokio::fs::remove_file(&part).await;
                    return Err("content hash mismatch; partial file discarded".into());
                }
                let dest = dir.join(&name);
                tokio::fs::rename(&part, &dest)
                    .await
                    .map_err(|e| format!("cannot rename into {}: {e}", dest.display()))?;
                Ok(ReceivedFile {
                    path: dest,
                    name: name.clone(),
                    size,
                    from: from.clone(),
                    resumed_from: offset,
                })
            }
            .await;
            inner.transfers.incoming.remove(&transfer);
            match result {
                Ok(f) => {
                    tracing::info!(file = %f.path.display(), size, from = %f.from, "file received");
                    inner.reply_file(node, transfer, FileVerdict::Stored);
                    mailbox.push(f);
                }
                Err(reason) if reason.is_empty() => {}
                Err(reason) => {
                    tracing::warn!(%reason, "file transfer failed");
                    inner.reply_file(node, transfer, FileVerdict::Failed(reason));
                }
            }
        });
        self.send_safe_to_node(node, &Message::FileAccept { transfer, offset });
    }

    pub fn on_file_chunk(&self, node: NodeId, transfer: u64, offset: u64, data: Vec<u8>) {
        if let Some(i) = self.transfers.incoming.get(&transfer) {
            if i.node == node {
                let _ = i.chunks.send((offset, data));
            }
        }
    }

    pub fn on_file_cancel(&self, node: NodeId, transfer: u64) {
        self.transfers
            .incoming
            .remove_if(&transfer, |_, i| i.node == node);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_plain_file_names_are_accepted() {
        assert!(safe_file_name("plan.xml"));
        assert!(!safe_file_name("../etc/passwd"));
        assert!(!safe_file_name("a/b"));
        assert!(!safe_file_name(".hidden"));
        assert!(!safe_file_name(""));
    }
}

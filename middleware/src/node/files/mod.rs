//! File transfer: sending a file (`send`: offered, chunked in a window moved by the receiver's
//! acknowledgements, resumed after either side restarts) and receiving it into a sink's
//! directory (`receive`: temp file, hash check, atomic rename, resume from what is on disk);
//! here, what routes the receiver's answers to a sending task and the content hash both use.

mod receive;
mod send;

use std::os::unix::fs::OpenOptionsExt;
use std::path::PathBuf;
use std::sync::atomic::AtomicU64;

use dashmap::DashMap;
use tokio::sync::mpsc;

use crate::protocol::{FileVerdict, NodeId};

#[cfg(test)]
pub(crate) use receive::{part_path, PARTIAL_DIR};
pub use receive::{
    FileCheck, FileCheckFuture, FileSinkOptions, FileSinkStats, FileToCheck, ReceivedFile,
};
pub(crate) use receive::{SinkMailbox, SinkState};
pub(crate) use send::start_sending;
pub use send::{FileProgress, FileReport, FileSendError, SendFileOptions};

/// What a sending task hears from the receiver (or about it).
#[derive(Debug)]
pub(crate) enum Control {
    Accept(u64),
    Done(FileVerdict),
    PeerLost(String),
}

struct Incoming {
    node: NodeId,
    /// Tells this receiving task from one that replaced it (same transfer offered again).
    generation: u64,
    chunks: mpsc::UnboundedSender<(u64, Vec<u8>)>,
}

/// Transfers in progress on this node.
#[derive(Default)]
pub(crate) struct Transfers {
    senders: DashMap<u64, (NodeId, mpsc::UnboundedSender<Control>)>,
    incoming: DashMap<u64, Incoming>,
    generations: AtomicU64,
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

/// blake3 of a file, off the async workers.
pub(crate) async fn hash_file(path: PathBuf) -> std::io::Result<[u8; 32]> {
    hash_with(path, false).await
}

async fn hash_with(path: PathBuf, no_follow: bool) -> std::io::Result<[u8; 32]> {
    tokio::task::spawn_blocking(move || {
        let mut h = blake3::Hasher::new();
        let mut o = std::fs::OpenOptions::new();
        o.read(true);
        if no_follow {
            o.custom_flags(libc::O_NOFOLLOW);
        }
        let mut f = o.open(&path)?;
        std::io::copy(&mut f, &mut h)?;
        Ok(*h.finalize().as_bytes())
    })
    .await
    .map_err(std::io::Error::other)?
}

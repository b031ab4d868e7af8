//! File transfer handles: a sink receiving files, and a transfer running in the background with
//! observable progress (the mechanics are in `node::files`).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{oneshot, watch};
use tokio_util::sync::{CancellationToken, DropGuard};

use super::errors::RecvError;
use super::service::Declared;
use crate::node::files::{
    start_sending, FileProgress, FileReport, FileSendError, FileSinkStats, ReceivedFile,
    SendFileOptions, SinkMailbox, SinkState,
};
use crate::node::{LocalOffer, NodeInner};

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
        let (prx, rrx) = start_sending(node, path, to, options);
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

#[cfg(test)]
mod tests {
    //! Sinks' caps and safety between real nodes over UDP loopback.

    use std::net::{Ipv4Addr, SocketAddrV4};
    use std::os::unix::fs::PermissionsExt;

    use super::*;
    use crate::api::Node;
    use crate::config::NetworkConfig;
    use crate::config::{EthernetConfig, LinkConfig};
    use crate::node::files::{part_path, Control, FileSinkOptions, PARTIAL_DIR};
    use crate::protocol::{FileOffer, FileVerdict, ItemKind, Message, NodeId};

    const T: Duration = Duration::from_secs(20);

    /// Two nodes of a domain of their own: `rx` (namespace `rx`) and `tx`.
    async fn pair(test: &str, k: u16) -> (Node, Node) {
        let pid = std::process::id();
        let port = 41_000 + ((pid as u16 % 2_000) * 8 + k) % 20_000;
        let cfg = |node: &str, ns: Option<&str>| {
            let mut c = NetworkConfig::ethernet_loopback(node);
            c.domain = format!("files-{test}-{pid}");
            c.namespace = ns.map(Into::into);
            c.links = vec![LinkConfig::Ethernet(EthernetConfig {
                interface: Ipv4Addr::LOCALHOST,
                bind: "127.0.0.1:0".parse().unwrap(),
                multicast: SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 6), port),
                heartbeat: Duration::from_millis(200),
                lease: Duration::from_secs(30),
                ..EthernetConfig::default()
            })];
            c
        };
        let rx = Node::open(&cfg("rx", Some("rx"))).await.unwrap();
        let tx = Node::open(&cfg("tx", None)).await.unwrap();
        (rx, tx)
    }

    fn opts(dir: &Path) -> FileSinkOptions {
        FileSinkOptions {
            dir: Some(dir.to_owned()),
            ..FileSinkOptions::default()
        }
    }

    fn content(n: usize) -> Vec<u8> {
        (0..n as u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8)
            .collect()
    }

    /// The transfer id a sender uses for a file (as `Sender::run` computes it).
    fn transfer_of(data: &[u8], name: &str) -> u64 {
        let hash = blake3::hash(data);
        let mut h = blake3::Hasher::new();
        h.update(hash.as_bytes());
        h.update(name.as_bytes());
        u64::from_le_bytes(h.finalize().as_bytes()[..8].try_into().unwrap())
    }

    /// What the raw tests need to speak the file protocol by hand from `tx`: the receiver's
    /// node id and the sink's id as `tx` knows them.
    async fn sink_seen_from(tx: &Node, sink: &str) -> (NodeId, u32) {
        let found = || {
            tx.inner.peers.by_id.iter().find_map(|p| {
                p.offers
                    .iter()
                    .find(|(_, o)| o.kind == ItemKind::File && *o.name == *sink)
                    .map(|(id, _)| (p.id, *id))
            })
        };
        assert!(
            tx.wait_until(T, |_| found().is_some()).await,
            "sink {sink} never seen"
        );
        found().unwrap()
    }

    async fn next_control(ctl: &mut tokio::sync::mpsc::UnboundedReceiver<Control>) -> Control {
        tokio::time::timeout(T, ctl.recv())
            .await
            .expect("no answer from the receiver")
            .expect("control channel closed")
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_link_planted_at_the_part_path_is_not_followed() {
        let (rx, tx) = pair("symlink", 0).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink("plans", &dir)
            .unwrap();
        let data = content(300_000);
        let src = t.path().join("plan.xml");
        std::fs::write(&src, &data).unwrap();
        // Someone plants a link where the partial file of this transfer will be, pointing at a
        // file of theirs choosing (shorter than the file: a follower would "resume" into it).
        let target = t.path().join("victim");
        std::fs::write(&target, b"secret").unwrap();
        let part = part_path(
            &dir.join(PARTIAL_DIR),
            "plan.xml",
            transfer_of(&data, "plan.xml"),
        );
        std::os::unix::fs::symlink(&target, &part).unwrap();

        let report = tx
            .service("fpmo")
            .unwrap()
            .send_file(&src, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await
            .unwrap();
        assert_eq!(report.resumed_from, 0, "resumed from the link's target");
        let got = sink.recv_timeout(T).await.unwrap();
        assert_eq!(std::fs::read(&got.path).unwrap(), data);
        assert_eq!(std::fs::read(&target).unwrap(), b"secret", "link followed");
        assert!(
            std::fs::symlink_metadata(&part).is_err(),
            "partial file left"
        );
        rx.shutdown().await;
        tx.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_announced_size_over_the_cap_is_refused_as_too_large() {
        let (rx, tx) = pair("too_large", 1).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink_with(
                "plans",
                FileSinkOptions {
                    max_file_size: 1_000,
                    ..opts(&dir)
                },
            )
            .unwrap();
        let src = t.path().join("big.xml");
        std::fs::write(&src, content(5_000)).unwrap();
        let r = tx
            .service("fpmo")
            .unwrap()
            .send_file(&src, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await;
        match r {
            Err(FileSendError::TooLarge { node, size, max }) => {
                assert_eq!((node.as_str(), size, max), ("rx", 5_000, 1_000))
            }
            other => panic!("expected TooLarge, got {other:?}"),
        }
        assert_eq!(sink.stats().too_large, 1);
        // Counted in the sender's link health too.
        assert_eq!(rx.refusals().rejected, 1);
        assert!(!dir.join("big.xml").exists());
        rx.shutdown().await;
        tx.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_sender_going_past_its_announced_size_is_cut_off() {
        let (rx, tx) = pair("lying", 2).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink("plans", &dir)
            .unwrap();
        let (peer, sink_id) = sink_seen_from(&tx, "rx/fpma/plans").await;
        let transfer = 0x1234_5678;
        let mut ctl = tx.inner.transfers.register_sender(transfer, peer);
        let offer = Message::FileOffer(FileOffer {
            transfer,
            sink: sink_id,
            name: "liar.bin".into(),
            size: 100,
            hash: [0; 32],
            sender: None,
        });
        assert!(tx.inner.send_safe_to_node(peer, &offer));
        assert!(matches!(next_control(&mut ctl).await, Control::Accept(0)));
        for (offset, len) in [(0u64, 60usize), (60, 80)] {
            let chunk = Message::FileChunk {
                transfer,
                offset,
                data: vec![7; len],
            };
            tx.inner.send_safe_to_node(peer, &chunk);
        }
        loop {
            match next_control(&mut ctl).await {
                Control::Accept(_) => continue,
                Control::Done(v) => {
                    assert_eq!(
                        v,
                        FileVerdict::TooLarge {
                            size: 140,
                            max: 100
                        }
                    );
                    break;
                }
                other => panic!("unexpected {other:?}"),
            }
        }
        assert_eq!(sink.stats().too_large, 1);
        assert_eq!(rx.refusals().rejected, 1);
        let part = part_path(&dir.join(PARTIAL_DIR), "liar.bin", transfer);
        assert!(
            std::fs::symlink_metadata(&part).is_err(),
            "cut-off part kept"
        );
        assert!(!dir.join("liar.bin").exists());
        rx.shutdown().await;
        tx.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_quota_counts_stored_files_and_refuses_past_it() {
        let (rx, tx) = pair("quota", 3).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("old.xml"), content(6_000)).unwrap();
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink_with(
                "plans",
                FileSinkOptions {
                    quota_bytes: 10_000,
                    ..opts(&dir)
                },
            )
            .unwrap();
        let fpmo = tx.service("fpmo").unwrap();
        let big = t.path().join("big.xml");
        std::fs::write(&big, content(5_000)).unwrap();
        let r = fpmo
            .send_file(&big, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await;
        match r {
            Err(FileSendError::QuotaExceeded { needed, quota, .. }) => {
                assert_eq!((needed, quota), (11_000, 10_000))
            }
            other => panic!("expected QuotaExceeded, got {other:?}"),
        }
        assert_eq!(sink.stats().quota_exceeded, 1);
        assert!(!dir.join("big.xml").exists());
        // What fits is stored; and a file replacing one of the same name counts only once.
        let small = t.path().join("small.xml");
        std::fs::write(&small, content(3_000)).unwrap();
        fpmo.send_file(&small, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await
            .unwrap();
        let again = t.path().join("again").join("old.xml");
        std::fs::create_dir_all(again.parent().unwrap()).unwrap();
        std::fs::write(&again, content(1_000)).unwrap();
        fpmo.send_file(&again, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await
            .unwrap();
        assert_eq!(sink.stats().stored, 2);
        assert_eq!(std::fs::metadata(dir.join("old.xml")).unwrap().len(), 1_000);
        rx.shutdown().await;
        tx.shutdown().await;
    }

    /// A sink's check decides after the file arrived whole: a refusal reaches the sender with
    /// its reason and nothing is stored; a file it takes is stored and delivered.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_sinks_check_refuses_with_its_reason_and_stores_what_it_takes() {
        let (rx, tx) = pair("check", 6).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let check = crate::FileCheck::new(|f: crate::FileToCheck| async move {
            let text = tokio::fs::read_to_string(&f.path)
                .await
                .map_err(|e| e.to_string())?;
            if text.contains("NOPE") {
                Err(format!("{} from {}: unknown fix `NOPE`", f.name, f.from))
            } else {
                Ok(())
            }
        });
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink_with(
                "plans",
                FileSinkOptions {
                    check: Some(check),
                    ..opts(&dir)
                },
            )
            .unwrap();
        let sender = tx.service("fpmo").unwrap();
        let bad = t.path().join("bad.xml");
        std::fs::write(&bad, "<flightPlan><leg fix=\"NOPE\"/></flightPlan>").unwrap();
        let r = sender
            .send_file(&bad, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await;
        match r {
            Err(FileSendError::Rejected { node, reason }) => {
                assert_eq!(node, "rx");
                assert_eq!(reason, "bad.xml from tx: unknown fix `NOPE`");
            }
            other => panic!("expected Rejected, got {other:?}"),
        }
        assert!(!dir.join("bad.xml").exists(), "a refused file was stored");
        assert_eq!(sink.stats().stored, 0);

        let good = t.path().join("good.xml");
        std::fs::write(&good, "<flightPlan/>").unwrap();
        let report = sender
            .send_file(&good, "rx/fpma/plans", SendFileOptions::default())
            .wait()
            .await
            .expect("the good file is taken");
        assert_eq!(report.receiver, "rx");
        let got = sink.recv_timeout(T).await.expect("delivered");
        assert_eq!(got.name, "good.xml");
        assert_eq!(std::fs::read_to_string(&got.path).unwrap(), "<flightPlan/>");
        rx.shutdown().await;
        tx.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_sink_receiving_its_maximum_refuses_one_more_as_busy() {
        let (rx, tx) = pair("busy", 4).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let sink = rx
            .service("fpma")
            .unwrap()
            .file_sink_with(
                "plans",
                FileSinkOptions {
                    max_concurrent: 1,
                    ..opts(&dir)
                },
            )
            .unwrap();
        let (peer, sink_id) = sink_seen_from(&tx, "rx/fpma/plans").await;
        let offer = |transfer: u64, name: &str| {
            Message::FileOffer(FileOffer {
                transfer,
                sink: sink_id,
                name: name.into(),
                size: 1_000,
                hash: [0; 32],
                sender: None,
            })
        };
        let mut first = tx.inner.transfers.register_sender(1, peer);
        tx.inner.send_safe_to_node(peer, &offer(1, "a.bin"));
        assert!(matches!(next_control(&mut first).await, Control::Accept(0)));
        let mut second = tx.inner.transfers.register_sender(2, peer);
        tx.inner.send_safe_to_node(peer, &offer(2, "b.bin"));
        assert_eq!(
            match next_control(&mut second).await {
                Control::Done(v) => v,
                other => panic!("unexpected {other:?}"),
            },
            FileVerdict::Busy { max: 1 }
        );
        assert_eq!(sink.stats().busy, 1);
        // The first one offered again (its sender restarted) is not "one more".
        tx.inner.send_safe_to_node(peer, &offer(1, "a.bin"));
        assert!(matches!(next_control(&mut first).await, Control::Accept(0)));
        // Once it ends (cancelled), the sink takes another.
        tx.inner
            .send_safe_to_node(peer, &Message::FileCancel { transfer: 1 });
        let mut third = tx.inner.transfers.register_sender(3, peer);
        let accepted = tokio::time::timeout(T, async {
            loop {
                tx.inner.send_safe_to_node(peer, &offer(3, "c.bin"));
                match next_control(&mut third).await {
                    Control::Accept(_) => break,
                    // The cancel may not have landed yet.
                    Control::Done(FileVerdict::Busy { .. }) => {
                        tokio::time::sleep(Duration::from_millis(50)).await
                    }
                    other => panic!("unexpected {other:?}"),
                }
            }
        })
        .await;
        assert!(
            accepted.is_ok(),
            "sink stayed busy after the transfer ended"
        );
        rx.shutdown().await;
        tx.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn stale_parts_are_removed_at_open_and_periodically() {
        let (rx, tx) = pair("stale", 5).await;
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("inbox");
        let partial = dir.join(PARTIAL_DIR);
        std::fs::create_dir_all(&partial).unwrap();
        std::fs::set_permissions(&partial, std::fs::Permissions::from_mode(0o700)).unwrap();
        let old = partial.join(".old.xml.0000000000000001.part");
        let fresh = partial.join(".fresh.xml.0000000000000002.part");
        std::fs::write(&old, b"old").unwrap();
        std::fs::write(&fresh, b"fresh").unwrap();
        std::fs::File::options()
            .write(true)
            .open(&old)
            .unwrap()
            .set_modified(std::time::SystemTime::now() - Duration::from_secs(7_200))
            .unwrap();
        // A partial file an earlier version left beside the stored files.
        let legacy = dir.join(".plan.xml.0000000000000003.part");
        std::fs::write(&legacy, b"legacy").unwrap();
        std::fs::File::options()
            .write(true)
            .open(&legacy)
            .unwrap()
            .set_modified(std::time::SystemTime::now() - Duration::from_secs(7_200))
            .unwrap();
        let svc = rx.service("fpma").unwrap();
        let sink = svc
            .file_sink_with(
                "plans",
                FileSinkOptions {
                    stale_part_age: Duration::from_secs(3_600),
                    ..opts(&dir)
                },
            )
            .unwrap();
        assert!(!old.exists(), "stale part kept at open");
        assert!(
            !legacy.exists(),
            "stale part of an earlier version kept at open"
        );
        assert!(fresh.exists(), "a part within the age was removed");
        assert_eq!(sink.stats().stale_parts_removed, 2);
        drop(sink);
        // A short age: the periodic sweep removes a part once it gets that old.
        let sink = svc
            .file_sink_with(
                "plans2",
                FileSinkOptions {
                    stale_part_age: Duration::from_millis(300),
                    ..opts(&dir)
                },
            )
            .unwrap();
        let gone = tokio::time::timeout(T, async {
            while fresh.exists() {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
        .await;
        assert!(gone.is_ok(), "stale part never swept");
        assert!(sink.stats().stale_parts_removed >= 1);
        rx.shutdown().await;
        tx.shutdown().await;
    }
}

//! Moving a peer to a better path without reordering its safe messages.
//!
//! A peer first heard over UDP may later be heard over shared memory too, and is then reached
//! over shared memory only (see `discovery::path_rank`). Each link keeps its own safe stream in
//! order, but two links are two streams: an event still in flight on the old path would arrive
//! after the events sent next on the new one. So a switch drains the old path first: from the
//! moment it starts, safe messages for the old path are held, in order; a marker goes out on the
//! old path, and once the peer acknowledged it (everything sent before it arrived) or its lease
//! ran out, the switch is made, the peer's Hello opens the new path and the held messages follow
//! on it. Messages that still name the old path afterwards (a route copied just before the
//! switch) are redirected to the new one.
//!
//! Fast messages are best effort, without an order between them to keep: they are never held
//! (and go where their route says; routes are recomputed when the switch is made).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

use super::NodeInner;
use crate::codec::encode_message;
use crate::link::{Link, LinkLoan, Outgoing, PeerAddr, SafeCompletion};
use crate::protocol::NodeId;
use crate::sync::lock;

/// A path: a link and the peer's address on it.
pub(crate) type Path = (usize, PeerAddr);

/// A path being left, or left.
struct Switch {
    node: NodeId,
    to: Path,
    /// Safe messages for the old path while it drains; `None` once the switch is made.
    held: Mutex<Option<Vec<Outgoing>>>,
}

/// The switches of one node, keyed by the path left.
#[derive(Default)]
pub(crate) struct PathSwitches {
    /// Read for every safe send (held across the link's `send`), written to start or make a
    /// switch: a safe message is then either sent before the marker or held. A switch made
    /// stays (redirecting) until its peer is forgotten.
    map: RwLock<HashMap<Path, Switch>>,
}

impl PathSwitches {
    /// Sends `out` to `path` on `links`, holding or redirecting it while that path is left.
    pub(crate) fn send(&self, links: &[Arc<dyn Link>], path: Path, out: Outgoing) {
        if matches!(out, Outgoing::Fast { .. }) {
            return send_on(links, path, out);
        }
        let map = self.map.read().unwrap_or_else(|e| e.into_inner());
        // No switch at all (nearly always): no hashing of the path per message.
        if map.is_empty() {
            return send_on(links, path, out);
        }
        let Some(s) = map.get(&path) else {
            return send_on(links, path, out);
        };
        if let Some(held) = lock(&s.held).as_mut() {
            held.push(out);
            return;
        }
        send_on(links, s.to, out);
    }

    /// Sends the message written in `buf`, lent by the link of `path`, on that path unless it
    /// is being left (then `buf` and `done` come back: the message must go as a copy).
    pub(crate) fn send_loan(
        &self,
        links: &[Arc<dyn Link>],
        path: Path,
        buf: Box<dyn LinkLoan>,
        done: Option<SafeCompletion>,
    ) -> Result<(), (Box<dyn LinkLoan>, Option<SafeCompletion>)> {
        let map = self.map.read().unwrap_or_else(|e| e.into_inner());
        match links.get(path.0) {
            Some(l) if !map.contains_key(&path) => {
                l.send_loan(path.1, buf, done);
                Ok(())
            }
            _ => Err((buf, done)),
        }
    }

    /// Sends the safe messages `outs` to `path` one after the other, with no other safe message
    /// between them: under the write lock, which every safe send holds for reading. An
    /// introduction (our Hello, then our declarations) goes out this way, so a message another
    /// task sends the peer meanwhile (a late joiner's value answering the peer's own
    /// declarations, which can arrive as soon as our Hello did) cannot overtake the
    /// declarations that give its ids a meaning.
    pub(crate) fn send_in_sequence(
        &self,
        links: &[Arc<dyn Link>],
        path: Path,
        outs: Vec<Outgoing>,
    ) {
        let map = self.map.write().unwrap_or_else(|e| e.into_inner());
        let to = match map.get(&path) {
            None => path,
            Some(s) => {
                if let Some(held) = lock(&s.held).as_mut() {
                    held.extend(outs);
                    return;
                }
                s.to
            }
        };
        for out in outs {
            send_on(links, to, out);
        }
    }

    /// Starts leaving `from` for `to` (both reaching `node`). Returns `false` when `from` is
    /// being left already.
    fn start(&self, node: NodeId, from: Path, to: Path) -> bool {
        let mut map = self.map.write().unwrap_or_else(|e| e.into_inner());
        if map.contains_key(&from) {
            return false;
        }
        map.insert(
            from,
            Switch {
                node,
                to,
                held: Mutex::new(Some(Vec::new())),
            },
        );
        true
    }

    /// Makes the switch away from `from`. Under the write lock, so no safe message can pass:
    /// `make` moves the peer it names to the new path and returns the message that introduces
    /// us there (or `None`: the peer is gone, and what was held is refused); that message, then
    /// the held ones, go out on the new path. Returns the new path when the switch was made.
    pub(crate) fn finish(
        &self,
        links: &[Arc<dyn Link>],
        from: Path,
        make: impl FnOnce(NodeId, Path) -> Option<Outgoing>,
    ) -> Option<Path> {
        let mut map = self.map.write().unwrap_or_else(|e| e.into_inner());
        let s = map.get(&from)?;
        let (node, to) = (s.node, s.to);
        let held = lock(&s.held).take().unwrap_or_default();
        let Some(introduction) = make(node, to) else {
            map.remove(&from);
            for out in held {
                out.refuse(from.1);
            }
            return None;
        };
        send_on(links, to, introduction);
        for out in held {
            send_on(links, to, out);
        }
        Some(to)
    }

    /// Forgets the switches of `node` (it is gone); what they held is refused.
    pub(crate) fn forget(&self, node: NodeId) {
        let mut map = self.map.write().unwrap_or_else(|e| e.into_inner());
        let gone: Vec<Path> = map
            .iter()
            .filter(|(_, s)| s.node == node)
            .map(|(p, _)| *p)
            .collect();
        for path in gone {
            if let Some(s) = map.remove(&path) {
                for out in lock(&s.held).take().unwrap_or_default() {
                    out.refuse(path.1);
                }
            }
        }
    }
}

fn send_on(links: &[Arc<dyn Link>], (link, addr): Path, out: Outgoing) {
    if let Some(l) = links.get(link) {
        l.send(addr, out);
    }
}

impl NodeInner {
    /// Moves `node` from the path `from` to the better path `to`, keeping its safe messages in
    /// order (see the module doc).
    pub(crate) fn switch_path(
        self: &Arc<Self>,
        node: NodeId,
        from: Path,
        to: Path,
        lease: Duration,
    ) {
        if !self.path_switches.start(node, from, to) {
            return;
        }
        let (marker, acknowledged) = tokio::sync::oneshot::channel();
        send_on(
            self.links(),
            from,
            Outgoing::Safe {
                msg: encode_message(&self.heartbeat()).into(),
                done: Some(marker.into()),
            },
        );
        let me = self.clone();
        crate::sync::spawn_tracked(&self.tasks, async move {
            tokio::select! {
                _ = me.cancel.cancelled() => return,
                // Acknowledged, failed (the path is gone) or never answered within the lease:
                // in every case nothing more is to be waited for on the old path.
                _ = tokio::time::timeout(lease, acknowledged) => {}
            }
            me.finish_switch(from);
        });
    }

    /// Makes the switch started by [`NodeInner::switch_path`]: the peer is reached over the new
    /// path from now on, introduced there by our Hello, followed by what was held.
    fn finish_switch(&self, from: Path) {
        let made = self.path_switches.finish(self.links(), from, |node, to| {
            let mut p = self.peers.by_id.get_mut(&node)?;
            tracing::info!(peer = %p.name, was = %from.1, now = %to.1, "peer reached over a better link");
            p.link = to.0;
            p.addr = to.1;
            Some(Outgoing::Safe {
                msg: encode_message(&self.hello(to.0)).into(),
                done: None,
            })
        });
        if made.is_some() {
            self.recompute_routes();
            self.recompute_forwarding();
            self.bump();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::{LinkSendError, LinkStats};

    /// A link that records what it is asked to send.
    #[derive(Default)]
    struct Recorder(Mutex<Vec<(PeerAddr, Vec<u8>)>>);

    impl Link for Recorder {
        fn name(&self) -> &str {
            "recorder"
        }
        fn local_addr(&self) -> String {
            String::new()
        }
        fn send(&self, to: PeerAddr, out: Outgoing) {
            let msg = match out {
                Outgoing::Fast { msg, .. } => msg,
                Outgoing::Safe { msg, .. } => msg.to_vec(),
            };
            lock(&self.0).push((to, msg));
        }
        fn announce(&self, _: &[u8]) {}
        fn close_peer(&self, _: PeerAddr) {}
        fn stats(&self) -> LinkStats {
            LinkStats::default()
        }
    }

    fn safe(b: u8) -> Outgoing {
        Outgoing::Safe {
            msg: vec![b].into(),
            done: None,
        }
    }

    #[test]
    fn safe_messages_for_a_path_being_left_are_held_in_order_and_fast_ones_are_not() {
        let rec = Arc::new(Recorder::default());
        let links: Vec<Arc<dyn Link>> = vec![rec.clone()];
        let old: Path = (0, PeerAddr::Udp("127.0.0.1:1".parse().unwrap()));
        let new: Path = (0, PeerAddr::Shm(7));
        let s = PathSwitches::default();
        s.send(&links, old, safe(1));
        assert!(s.start(9, old, new));
        assert!(!s.start(9, old, new), "one switch per path");
        s.send(&links, old, safe(2));
        s.send(&links, old, safe(3));
        s.send(
            &links,
            old,
            Outgoing::Fast {
                coalesce: None,
                msg: vec![4],
            },
        );
        assert_eq!(
            *lock(&rec.0),
            [(old.1, vec![1]), (old.1, vec![4])],
            "safe messages after the start wait; fast ones go"
        );
        // Made: our introduction, then what was held, in order, on the new path.
        assert_eq!(s.finish(&links, old, |_, _| Some(safe(0))), Some(new));
        assert_eq!(
            lock(&rec.0)[2..],
            [(new.1, vec![0]), (new.1, vec![2]), (new.1, vec![3])]
        );
        // Whatever still names the old path goes to the new one.
        s.send(&links, old, safe(5));
        assert_eq!(lock(&rec.0).last(), Some(&(new.1, vec![5])));
    }

    #[test]
    fn a_switch_whose_peer_is_gone_refuses_what_it_held() {
        let links: Vec<Arc<dyn Link>> = vec![Arc::new(Recorder::default())];
        let old: Path = (0, PeerAddr::Udp("127.0.0.1:1".parse().unwrap()));
        let s = PathSwitches::default();
        assert!(s.start(9, old, (0, PeerAddr::Shm(7))));
        let (tx, mut rx) = tokio::sync::oneshot::channel();
        s.send(
            &links,
            old,
            Outgoing::Safe {
                msg: vec![1u8].into(),
                done: Some(tx.into()),
            },
        );
        assert_eq!(s.finish(&links, old, |_, _| None), None);
        assert!(matches!(
            rx.try_recv(),
            Ok(Err(LinkSendError::PeerClosed(_)))
        ));
    }

    #[test]
    fn forgetting_a_peer_refuses_what_its_switch_held() {
        let rec = Arc::new(Recorder::default());
        let links: Vec<Arc<dyn Link>> = vec![rec.clone()];
        let old: Path = (0, PeerAddr::Udp("127.0.0.1:1".parse().unwrap()));
        let s = PathSwitches::default();
        assert!(s.start(9, old, (0, PeerAddr::Shm(7))));
        let (tx, mut rx) = tokio::sync::oneshot::channel();
        s.send(
            &links,
            old,
            Outgoing::Safe {
                msg: vec![1u8].into(),
                done: Some(tx.into()),
            },
        );
        s.forget(9);
        assert!(matches!(
            rx.try_recv(),
            Ok(Err(LinkSendError::PeerClosed(_)))
        ));
        assert_eq!(
            s.finish(&links, old, |_, _| Some(safe(0))),
            None,
            "nothing left to make"
        );
        s.send(&links, old, safe(2));
        assert_eq!(
            *lock(&rec.0),
            [(old.1, vec![2])],
            "the old path is used again"
        );
    }

    /// A link that records what it sends and stops inside the send of message 1 until released.
    struct Gate {
        sent: Mutex<Vec<u8>>,
        entered: Mutex<std::sync::mpsc::Sender<()>>,
        release: Mutex<std::sync::mpsc::Receiver<()>>,
    }

    impl Link for Gate {
        fn name(&self) -> &str {
            "gate"
        }
        fn local_addr(&self) -> String {
            String::new()
        }
        fn send(&self, _: PeerAddr, out: Outgoing) {
            let msg = match out {
                Outgoing::Fast { msg, .. } => msg,
                Outgoing::Safe { msg, .. } => msg.to_vec(),
            };
            if msg == [1] {
                let _ = lock(&self.entered).send(());
                let _ = lock(&self.release).recv();
            }
            lock(&self.sent).extend(msg);
        }
        fn announce(&self, _: &[u8]) {}
        fn close_peer(&self, _: PeerAddr) {}
        fn stats(&self) -> LinkStats {
            LinkStats::default()
        }
    }

    #[test]
    fn a_safe_message_sent_during_a_sequence_waits_for_the_whole_sequence() {
        let (entered_tx, entered) = std::sync::mpsc::channel();
        let (release, release_rx) = std::sync::mpsc::channel();
        let gate = Arc::new(Gate {
            sent: Mutex::default(),
            entered: Mutex::new(entered_tx),
            release: Mutex::new(release_rx),
        });
        let links: Arc<Vec<Arc<dyn Link>>> = Arc::new(vec![gate.clone()]);
        let path: Path = (0, PeerAddr::Shm(7));
        let s = Arc::new(PathSwitches::default());
        let introduce = {
            let (s, links) = (s.clone(), links.clone());
            std::thread::spawn(move || s.send_in_sequence(&links, path, vec![safe(1), safe(2)]))
        };
        entered.recv().unwrap();
        // Another task sends while the sequence is half out: it must not get in between.
        let (done_tx, done) = std::sync::mpsc::channel();
        let other = {
            let (s, links) = (s.clone(), links.clone());
            std::thread::spawn(move || {
                s.send(&links, path, safe(9));
                let _ = done_tx.send(());
            })
        };
        assert!(
            done.recv_timeout(Duration::from_millis(200)).is_err(),
            "a safe message went out in the middle of a sequence"
        );
        release.send(()).unwrap();
        introduce.join().unwrap();
        other.join().unwrap();
        assert_eq!(*lock(&gate.sent), [1, 2, 9]);
    }
}

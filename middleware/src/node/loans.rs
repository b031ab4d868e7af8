//! Messages written in place: a publisher of a large value asks for a buffer before it has the
//! value, and the link towards its subscriber may lend one (a sample of the subscriber's
//! shared-memory inbox), so the value is written once, where the subscriber reads it.

use std::sync::atomic::Ordering;

use super::path_switch::Path;
use super::routes::RemoteSubscriber;
use super::NodeInner;
use crate::link::{HeapLoan, LinkLoan, SafeCompletion};

/// A buffer for one safe message: lent by the link of `path`, or on the heap.
pub(crate) struct MessageLoan {
    pub buf: Box<dyn LinkLoan>,
    /// The path whose link lent `buf`; `None` for a heap buffer.
    pub path: Option<Path>,
}

impl MessageLoan {
    /// The path to send the message in place on: the one whose link lent the buffer, if it is
    /// still the only live one of `routes` (the subscribers may have changed since the loan).
    pub fn path_among(&self, routes: &[RemoteSubscriber]) -> Option<Path> {
        self.path.filter(|p| match routes {
            [r] => (r.link, r.addr) == *p && r.alive.load(Ordering::Acquire),
            _ => false,
        })
    }

    /// Whether the buffer is a link's (shared memory), not the heap.
    pub fn is_lent(&self) -> bool {
        self.path.is_some()
    }

    /// The message, copied out of a lent buffer (which goes back to its link).
    pub fn into_vec(self) -> Vec<u8> {
        let mut buf = self.buf;
        if self.path.is_none() {
            if let Ok(heap) = buf.into_any().downcast::<HeapLoan>() {
                return heap.into_vec();
            }
            // A heap loan is always a `HeapLoan` (see `NodeInner::loan`).
            unreachable!("a heap buffer is a HeapLoan");
        }
        buf.init().to_vec()
    }
}

impl NodeInner {
    /// A buffer for a message of `len` bytes to `routes`: the first live route's link that
    /// lends one when it is the only route (a copy to several would cost what the loan
    /// saves), else the heap.
    pub fn loan(&self, routes: &[RemoteSubscriber], len: usize) -> MessageLoan {
        if let [r] = routes {
            if r.alive.load(Ordering::Acquire) {
                if let Some(buf) = self.links().get(r.link).and_then(|l| l.loan(r.addr, len)) {
                    return MessageLoan {
                        buf,
                        path: Some((r.link, r.addr)),
                    };
                }
            }
        }
        MessageLoan {
            buf: Box::new(HeapLoan::new(len)),
            path: None,
        }
    }

    /// Sends the message written in `buf`, which the link of `path` lent, on that path,
    /// settling on `done`; or, when that path is being left, as a copy (held or redirected
    /// like any safe message, see [`super::path_switch`]).
    pub fn send_loan(&self, path: Path, buf: Box<dyn LinkLoan>, done: Option<SafeCompletion>) {
        if let Err((mut buf, done)) = self.path_switches.send_loan(self.links(), path, buf, done) {
            let msg = bytes::Bytes::copy_from_slice(buf.init());
            drop(buf);
            let (link, addr) = path;
            self.send_to(link, addr, crate::link::Outgoing::Safe { msg, done });
        }
    }
}

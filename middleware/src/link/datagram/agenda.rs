//! The transmit task's agenda: which sessions to visit and when (a retransmission timer, a
//! blocked socket's retry) and which a sender asked it to flush now. The task visits only
//! those: walking every session at each wake-up cost a node work in proportion to its peers
//! per datagram received, and a node of a 200-node LAN spent most of its time doing it.
//!
//! Pure: the caller passes `now`. A session's timer may be entered again before the old
//! entry falls due (its deadline moved earlier); the caller keeps, per session, the time it
//! last entered and skips an entry that is not that one (see `DatagramLink::transmit_loop`).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashSet};
use std::hash::Hash;
use std::time::Instant;

/// See the module docs.
pub(crate) struct Agenda<K> {
    timers: BinaryHeap<Reverse<(Instant, K)>>,
    flush: Vec<K>,
}

impl<K> Default for Agenda<K>
where
    K: Ord,
{
    fn default() -> Self {
        Agenda {
            timers: BinaryHeap::new(),
            flush: Vec::new(),
        }
    }
}

/// What fell due at one visit of the task.
pub(crate) struct Due<K> {
    /// Sessions to flush now, each once.
    pub flush: Vec<K>,
    /// Timers that fell due, as (when entered, session), soonest first.
    pub timers: Vec<(Instant, K)>,
}

impl<K: Copy + Ord + Hash> Agenda<K> {
    /// Visit `key` at `when`. Returns whether it is now the soonest timer (the task, asleep
    /// until a later one, must be woken).
    pub(crate) fn at(&mut self, when: Instant, key: K) -> bool {
        let soonest = self.next_timer().is_none_or(|t| when < t);
        self.timers.push(Reverse((when, key)));
        soonest
    }

    /// Visit `key` at once. Returns whether the task must be woken for it (it was not asked
    /// already).
    pub(crate) fn flush(&mut self, key: K) -> bool {
        let first = self.flush.is_empty();
        self.flush.push(key);
        first
    }

    /// The soonest timer.
    pub(crate) fn next_timer(&self) -> Option<Instant> {
        self.timers.peek().map(|Reverse((t, _))| *t)
    }

    /// Takes what is due at `now`: every flush asked for and every timer at or before `now`.
    pub(crate) fn take_due(&mut self, now: Instant) -> Due<K> {
        let mut seen = HashSet::new();
        let flush = std::mem::take(&mut self.flush)
            .into_iter()
            .filter(|k| seen.insert(*k))
            .collect();
        let mut timers = Vec::new();
        while let Some(Reverse((t, k))) = self.timers.peek().copied() {
            if t > now {
                break;
            }
            self.timers.pop();
            timers.push((t, k));
        }
        Due { flush, timers }
    }

    /// Timers entered and not yet due (for tests and gauges).
    #[cfg(test)]
    fn len(&self) -> usize {
        self.timers.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn timers_fall_due_in_order_and_only_when_reached() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let mut a = Agenda::default();
        assert!(a.at(ms(30), 3u32), "the first timer is the soonest");
        assert!(a.at(ms(10), 1), "an earlier one is the soonest");
        assert!(!a.at(ms(20), 2), "a later one is not");
        assert_eq!(a.next_timer(), Some(ms(10)));
        let due = a.take_due(ms(5));
        assert!(due.timers.is_empty() && due.flush.is_empty());
        let due = a.take_due(ms(20));
        assert_eq!(due.timers, vec![(ms(10), 1), (ms(20), 2)]);
        assert_eq!(a.next_timer(), Some(ms(30)));
        assert_eq!(a.len(), 1);
    }

    #[test]
    fn flushes_are_taken_at_once_and_each_session_once() {
        let t0 = Instant::now();
        let mut a = Agenda::default();
        assert!(a.flush(7u32), "the first flush wakes the task");
        assert!(!a.flush(8), "it is awake already for the next");
        assert!(!a.flush(7));
        a.at(t0 + Duration::from_secs(1), 9);
        let due = a.take_due(t0);
        assert_eq!(due.flush, vec![7, 8]);
        assert!(due.timers.is_empty(), "a timer waits for its time");
        assert!(a.flush(7), "asked again after the task took them");
    }

    #[test]
    fn a_session_entered_twice_falls_due_twice() {
        // The caller tells the entries apart (see the module docs); the agenda keeps both.
        let t0 = Instant::now();
        let mut a = Agenda::default();
        a.at(t0 + Duration::from_millis(50), 1u32);
        a.at(t0 + Duration::from_millis(10), 1);
        let due = a.take_due(t0 + Duration::from_millis(60));
        assert_eq!(due.timers.len(), 2);
        assert_eq!(due.timers[0].0, t0 + Duration::from_millis(10));
    }
}

//! A bounded FIFO queue in which an entry with a key replaces the unsent entry with the same
//! key in place (newest value wins, position kept), in constant time: the fast queues of the
//! UDP, serial and shared-memory links and the mailboxes of variable subscriptions.

use std::collections::VecDeque;
use std::hash::Hash;

use rustc_hash::FxHashMap;

/// FIFO with per-key replacement and a bound.
///
/// At the bound, queuing a new entry (one that replaces nothing) drops the oldest entry, keyed
/// or not: best-effort traffic keeps the newest values. The dropped value is returned
/// ([`Pushed::DroppedOldest`]) so the owner can count it, and [`CoalescingQueue::dropped`]
/// counts every such drop.
#[derive(Debug)]
pub struct CoalescingQueue<K, V> {
    queue: VecDeque<(Option<K>, V)>,
    /// Absolute position (`popped` + offset) of the queued entry of each key.
    /// (Fx hashing: keys are offer ids and item names this node declared or accepted, and the
    /// lookup is on every publish.)
    at: FxHashMap<K, u64>,
    popped: u64,
    capacity: usize,
    dropped: u64,
}

/// What [`CoalescingQueue::push`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Pushed<V> {
    /// Queued at the back; nothing left the queue.
    Queued,
    /// Replaced the queued value of the same key in place: the old value.
    Replaced(V),
    /// Queued at the back of a full queue, whose oldest entry was dropped: its value.
    DroppedOldest(V),
}

impl<K, V> Default for CoalescingQueue<K, V> {
    /// An unbounded queue (a subscription's mailbox is bounded by the items it matches).
    fn default() -> Self {
        Self::with_capacity_bound(usize::MAX)
    }
}

impl<K, V> CoalescingQueue<K, V> {
    fn with_capacity_bound(capacity: usize) -> Self {
        CoalescingQueue {
            queue: VecDeque::new(),
            at: FxHashMap::default(),
            popped: 0,
            capacity,
            dropped: 0,
        }
    }
}

impl<K: Eq + Hash + Clone, V> CoalescingQueue<K, V> {
    /// An empty queue holding at most `capacity` entries (at least one).
    pub fn new(capacity: usize) -> Self {
        Self::with_capacity_bound(capacity.max(1))
    }

    /// Queues `value`; with a key already queued, replaces that entry's value instead. At the
    /// bound, a new entry drops the oldest one.
    pub fn push(&mut self, key: Option<K>, value: V) -> Pushed<V> {
        if let Some(k) = &key {
            if let Some(slot) = self.get_mut(k) {
                return Pushed::Replaced(std::mem::replace(slot, value));
            }
        }
        let dropped = if self.queue.len() >= self.capacity {
            self.dropped += 1;
            self.pop_front().map(|(_, v)| v)
        } else {
            None
        };
        if let Some(k) = &key {
            self.at
                .insert(k.clone(), self.popped + self.queue.len() as u64);
        }
        self.queue.push_back((key, value));
        dropped.map_or(Pushed::Queued, Pushed::DroppedOldest)
    }

    /// The queued value of `key`, to change in place.
    pub fn get_mut(&mut self, key: &K) -> Option<&mut V> {
        let abs = *self.at.get(key)?;
        let slot = abs
            .checked_sub(self.popped)
            .and_then(|i| self.queue.get_mut(i as usize))?;
        (slot.0.as_ref() == Some(key)).then_some(&mut slot.1)
    }

    /// Takes the oldest entry.
    pub fn pop_front(&mut self) -> Option<(Option<K>, V)> {
        let (k, v) = self.queue.pop_front()?;
        if let Some(k) = &k {
            if self.at.get(k) == Some(&self.popped) {
                self.at.remove(k);
            }
        }
        self.popped += 1;
        Some((k, v))
    }

    /// The oldest value.
    pub fn front(&self) -> Option<&V> {
        self.queue.front().map(|(_, v)| v)
    }

    /// The values, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &V> {
        self.queue.iter().map(|(_, v)| v)
    }

    /// Entries queued.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Whether nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// Entries dropped at the bound so far.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Removes everything.
    pub fn clear(&mut self) {
        self.popped += self.queue.len() as u64;
        self.queue.clear();
        self.at.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn newest_value_replaces_in_place() {
        let mut q = CoalescingQueue::new(10);
        assert_eq!(q.push(Some(1), "a1"), Pushed::Queued);
        assert_eq!(q.push(None, "x"), Pushed::Queued);
        assert_eq!(q.push(Some(2), "b1"), Pushed::Queued);
        assert_eq!(q.push(Some(1), "a2"), Pushed::Replaced("a1"));
        assert_eq!(q.len(), 3);
        assert_eq!(q.pop_front(), Some((Some(1), "a2")));
        assert_eq!(
            q.push(Some(1), "a3"),
            Pushed::Queued,
            "popped key is queued anew"
        );
        assert_eq!(q.pop_front(), Some((None, "x")));
        assert_eq!(q.pop_front(), Some((Some(2), "b1")));
        assert_eq!(q.pop_front(), Some((Some(1), "a3")));
        assert_eq!(q.pop_front(), None);
    }

    #[test]
    fn at_the_bound_the_oldest_entry_is_dropped_and_counted() {
        let mut q = CoalescingQueue::new(2);
        assert_eq!(q.push(Some(1), "a1"), Pushed::Queued);
        assert_eq!(q.push(None, "x"), Pushed::Queued);
        // Replacing needs no room.
        assert_eq!(q.push(Some(1), "a2"), Pushed::Replaced("a1"));
        assert_eq!(q.dropped(), 0);
        assert_eq!(q.push(Some(2), "b1"), Pushed::DroppedOldest("a2"));
        assert_eq!(q.dropped(), 1);
        // The dropped key is gone: its next value is a new entry (and drops the next oldest).
        assert_eq!(q.push(Some(1), "a3"), Pushed::DroppedOldest("x"));
        assert_eq!(q.len(), 2);
        assert_eq!(q.front(), Some(&"b1"));
        if let Some(v) = q.get_mut(&1) {
            *v = "a4";
        }
        assert_eq!(q.iter().copied().collect::<Vec<_>>(), ["b1", "a4"]);
        assert_eq!(q.dropped(), 2);
    }

    proptest! {
        /// Same behaviour as the obvious bounded linear-scan model.
        #[test]
        fn matches_a_linear_model(ops in proptest::collection::vec((any::<bool>(), 0u8..6, any::<u16>()), 0..300), cap in 1usize..8) {
            let mut q = CoalescingQueue::new(cap);
            let mut model: VecDeque<(Option<u8>, u16)> = VecDeque::new();
            for (pop, k, v) in ops {
                if pop {
                    prop_assert_eq!(q.pop_front(), model.pop_front());
                } else {
                    let key = if k == 5 { None } else { Some(k) };
                    let slot = key.and_then(|key| model.iter_mut().find(|(c, _)| *c == Some(key)));
                    let pushed = if let Some(s) = slot {
                        Pushed::Replaced(std::mem::replace(&mut s.1, v))
                    } else {
                        let dropped = if model.len() >= cap { model.pop_front() } else { None };
                        model.push_back((key, v));
                        dropped.map_or(Pushed::Queued, |(_, d)| Pushed::DroppedOldest(d))
                    };
                    prop_assert_eq!(q.push(key, v), pushed);
                }
                prop_assert_eq!(q.len(), model.len());
            }
        }
    }
}

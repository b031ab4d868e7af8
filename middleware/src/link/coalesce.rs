//! A FIFO queue in which an entry with a key replaces the unsent entry with the same key in
//! place (newest value wins, position kept), in constant time: the send queues of variables and
//! the mailboxes of variable subscriptions.

use std::collections::VecDeque;
use std::hash::Hash;

use rustc_hash::FxHashMap;

/// FIFO with per-key replacement.
#[derive(Debug)]
pub struct CoalescingQueue<K, V> {
    queue: VecDeque<(Option<K>, V)>,
    /// Absolute position (`popped` + offset) of the queued entry of each key.
    /// (Fx hashing: keys are offer ids and item names this node declared or accepted, and the
    /// lookup is on every publish.)
    at: FxHashMap<K, u64>,
    popped: u64,
}

impl<K, V> Default for CoalescingQueue<K, V> {
    fn default() -> Self {
        CoalescingQueue {
            queue: VecDeque::new(),
            at: FxHashMap::default(),
            popped: 0,
        }
    }
}

impl<K: Eq + Hash + Clone, V> CoalescingQueue<K, V> {
    /// An empty queue.
    pub fn new() -> Self {
        Self::default()
    }

    /// Queues `value`; with a key already queued, replaces that entry instead and returns the
    /// value it replaced.
    pub fn push(&mut self, key: Option<K>, value: V) -> Option<V> {
        if let Some(k) = &key {
            if let Some(&abs) = self.at.get(k) {
                if let Some(slot) = abs
                    .checked_sub(self.popped)
                    .and_then(|i| self.queue.get_mut(i as usize))
                {
                    if slot.0.as_ref() == Some(k) {
                        return Some(std::mem::replace(&mut slot.1, value));
                    }
                }
            }
            self.at
                .insert(k.clone(), self.popped + self.queue.len() as u64);
        }
        self.queue.push_back((key, value));
        None
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

    /// Entries queued.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Whether nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
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
        let mut q = CoalescingQueue::new();
        assert_eq!(q.push(Some(1), "a1"), None);
        assert_eq!(q.push(None, "x"), None);
        assert_eq!(q.push(Some(2), "b1"), None);
        assert_eq!(q.push(Some(1), "a2"), Some("a1"));
        assert_eq!(q.len(), 3);
        assert_eq!(q.pop_front(), Some((Some(1), "a2")));
        assert_eq!(q.push(Some(1), "a3"), None, "popped key is queued anew");
        assert_eq!(q.pop_front(), Some((None, "x")));
        assert_eq!(q.pop_front(), Some((Some(2), "b1")));
        assert_eq!(q.pop_front(), Some((Some(1), "a3")));
        assert_eq!(q.pop_front(), None);
    }

    proptest! {
        /// Same behaviour as the obvious linear-scan model.
        #[test]
        fn matches_a_linear_model(ops in proptest::collection::vec((any::<bool>(), 0u8..6, any::<u16>()), 0..300)) {
            let mut q = CoalescingQueue::new();
            let mut model: VecDeque<(Option<u8>, u16)> = VecDeque::new();
            for (pop, k, v) in ops {
                if pop {
                    prop_assert_eq!(q.pop_front(), model.pop_front());
                } else {
                    let key = if k == 5 { None } else { Some(k) };
                    let slot = key.and_then(|key| model.iter_mut().find(|(c, _)| *c == Some(key)));
                    let replaced = if let Some(s) = slot { Some(std::mem::replace(&mut s.1, v)) } else { model.push_back((key, v)); None };
                    prop_assert_eq!(q.push(key, v), replaced);
                }
                prop_assert_eq!(q.len(), model.len());
            }
        }
    }
}

//! A FIFO queue in which an entry with a key replaces the unsent entry with the same key in
//! place (newest value wins, position kept), in constant time: the send queues of variables and
//! the mailboxes of variable subscriptions.

use std::collections::{HashMap, VecDeque};
use std::hash::Hash;

/// FIFO with per-key replacement.
#[derive(Debug)]
pub struct CoalescingQueue<K, V> {
    queue: VecDeque<(Option<K>, V)>,
    /// Absolute position (`popped` + offset) of the queued entry of each key.
    at: HashMap<K, u64>,
    popped: u64,
}

impl<K, V> Default for CoalescingQueue<K, V> {
    fn default() -> Self {
        CoalescingQueue {
            queue: VecDeque::new(),
            at: HashMap::new(),
            popped: 0,
        }
    }
}

impl<K: Eq + Hash + Clone, V> CoalescingQueue<K, V> {
    /// An empty queue.
    pub fn new() -> Self {
        Self::default()
    }

    /// Queues `value`; with a key already queued, replaces that entry instead and returns `true`.
    pub fn push(&mut self, key: Option<K>, value: V) -> bool {
        if let Some(k) = &key {
            if let Some(&abs) = self.at.get(k) {
                if let Some(slot) = abs
                    .checked_sub(self.popped)
                    .and_then(|i| self.queue.get_mut(i as usize))
                {
                    if slot.0.as_ref() == Some(k) {
                        slot.1 = value;
                        return true;
                    }
                }
            }
            self.at
                .insert(k.clone(), self.popped + self.queue.len() as u64);
        }
        self.queue.push_back((key, value));
        false
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
        assert!(!q.push(Some(1), "a1"));
        assert!(!q.push(None, "x"));
        assert!(!q.push(Some(2), "b1"));
        assert!(q.push(Some(1), "a2"));
        assert_eq!(q.len(), 3);
        assert_eq!(q.pop_front(), Some((Some(1), "a2")));
        assert!(!q.push(Some(1), "a3"), "popped key is queued anew");
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
                    let replaced = if let Some(s) = slot { s.1 = v; true } else { model.push_back((key, v)); false };
                    prop_assert_eq!(q.push(key, v), replaced);
                }
                prop_assert_eq!(q.len(), model.len());
            }
        }
    }
}

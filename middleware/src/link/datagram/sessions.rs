//! A datagram link's table of peer sessions, keyed by the medium's address, in two classes so that anyone able
//! to send a datagram cannot fill it:
//! - **bound**: the node knows who is at the address (its Hello arrived, see
//!   [`crate::link::Link::confirm_peer`]). Kept until the node closes it; at most `max_bound`.
//! - **unbound**: an address we only answered (a heartbeat of a node we do not know yet) or
//!   that opened a session before its Hello arrived. At most `max_unbound`, the oldest pushed
//!   out by a newer one, and each gone `unbound_ttl` after it was made unless bound by then.
//!
//! An unbound session never pushes out a bound one: a flood of heartbeats with invented node
//! ids from many source ports churns the unbound class only, and a node arriving during it is
//! bound as soon as its Hello is read (that Hello is delivered from the very datagram that
//! opened the session, before anything can push it out).
//!
//! Pure: the caller passes `now`; what is pushed out or expires is returned for the caller to
//! fail.

use std::collections::{HashMap, VecDeque};
use std::hash::Hash;
use std::time::{Duration, Instant};

use crate::sync::SeededHash;

/// Bounds of a [`SessionTable`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct SessionLimits {
    /// Most bound sessions; a bind beyond it is refused.
    pub max_bound: usize,
    /// Most unbound sessions; a new one beyond it pushes out the oldest.
    pub max_unbound: usize,
    /// How long an unbound session lives unless bound.
    pub unbound_ttl: Duration,
}

struct Slot<V> {
    value: V,
    /// `None` once bound; else when it was made (its place in `unbound_order`).
    unbound_since: Option<Instant>,
}

/// Sessions by peer address (see the module docs).
pub(crate) struct SessionTable<K, V> {
    slots: HashMap<K, Slot<V>, SeededHash>,
    /// Unbound sessions oldest first, as (address, when made). Entries whose session was bound
    /// or removed since are skipped when met (and compacted when they pile up).
    unbound_order: VecDeque<(K, Instant)>,
    unbound: usize,
    limits: SessionLimits,
}

/// What [`SessionTable::get_or_insert`] did.
pub(crate) enum Lookup<K, V> {
    /// The session (found, made, or bound now), and a session pushed out to make room.
    Found(V, Option<(K, V)>),
    /// No room: the bound class is full (for a bind), or no session was wanted.
    Refused,
}

impl<K: Copy + Eq + Hash, V: Clone> SessionTable<K, V> {
    /// An empty table.
    pub(crate) fn new(limits: SessionLimits) -> Self {
        SessionTable {
            slots: HashMap::default(),
            unbound_order: VecDeque::new(),
            unbound: 0,
            limits,
        }
    }

    /// The session with `addr`, if any.
    pub(crate) fn get(&self, addr: &K) -> Option<&V> {
        self.slots.get(addr).map(|s| &s.value)
    }

    /// Whether the session with `addr` is bound.
    pub(crate) fn is_bound(&self, addr: &K) -> bool {
        self.slots
            .get(addr)
            .is_some_and(|s| s.unbound_since.is_none())
    }

    /// The session with `addr`, made with `make` if there is none and `create` is set; bound
    /// if `bind` is set (a bind of a new address when the bound class is full is refused; an
    /// existing unbound session then stays unbound).
    pub(crate) fn get_or_insert(
        &mut self,
        addr: K,
        now: Instant,
        create: bool,
        bind: bool,
        make: impl FnOnce() -> V,
    ) -> Lookup<K, V> {
        let bound_full = self.bound() >= self.limits.max_bound;
        if let Some(slot) = self.slots.get_mut(&addr) {
            if bind && slot.unbound_since.is_some() && !bound_full {
                slot.unbound_since = None;
                self.unbound -= 1;
            }
            return Lookup::Found(slot.value.clone(), None);
        }
        if !create && !bind {
            return Lookup::Refused;
        }
        if bind {
            if bound_full {
                return Lookup::Refused;
            }
            let value = make();
            self.slots.insert(
                addr,
                Slot {
                    value: value.clone(),
                    unbound_since: None,
                },
            );
            return Lookup::Found(value, None);
        }
        let pushed_out = if self.unbound >= self.limits.max_unbound.max(1) {
            self.pop_oldest_unbound(None)
        } else {
            None
        };
        let value = make();
        self.slots.insert(
            addr,
            Slot {
                value: value.clone(),
                unbound_since: Some(now),
            },
        );
        self.unbound += 1;
        self.unbound_order.push_back((addr, now));
        if self.unbound_order.len() > 2 * self.limits.max_unbound + 64 {
            let slots = &self.slots;
            self.unbound_order
                .retain(|(a, t)| slots.get(a).is_some_and(|s| s.unbound_since == Some(*t)));
        }
        Lookup::Found(value, pushed_out)
    }

    /// Removes the oldest unbound session (made before `before`, if given).
    fn pop_oldest_unbound(&mut self, before: Option<Instant>) -> Option<(K, V)> {
        while let Some(&(addr, made)) = self.unbound_order.front() {
            if before.is_some_and(|b| made > b) {
                return None;
            }
            self.unbound_order.pop_front();
            let current = self
                .slots
                .get(&addr)
                .is_some_and(|s| s.unbound_since == Some(made));
            if current {
                self.unbound -= 1;
                return self.slots.remove(&addr).map(|s| (addr, s.value));
            }
        }
        None
    }

    /// Removes the unbound sessions older than the time-to-live at `now`.
    pub(crate) fn expire(&mut self, now: Instant) -> Vec<(K, V)> {
        let Some(before) = now.checked_sub(self.limits.unbound_ttl) else {
            return Vec::new();
        };
        let mut gone = Vec::new();
        while let Some(g) = self.pop_oldest_unbound(Some(before)) {
            gone.push(g);
        }
        gone
    }

    /// When the oldest unbound session expires.
    pub(crate) fn next_expiry(&self) -> Option<Instant> {
        self.unbound_order
            .iter()
            .find(|(a, t)| {
                self.slots
                    .get(a)
                    .is_some_and(|s| s.unbound_since == Some(*t))
            })
            .map(|(_, t)| *t + self.limits.unbound_ttl)
    }

    /// Removes the session with `addr`.
    pub(crate) fn remove(&mut self, addr: &K) -> Option<V> {
        let slot = self.slots.remove(addr)?;
        if slot.unbound_since.is_some() {
            self.unbound -= 1;
        }
        Some(slot.value)
    }

    /// Removes every session.
    pub(crate) fn drain(&mut self) -> impl Iterator<Item = (K, V)> + '_ {
        self.unbound = 0;
        self.unbound_order.clear();
        self.slots.drain().map(|(a, s)| (a, s.value))
    }

    /// Every session's value.
    pub(crate) fn values(&self) -> impl Iterator<Item = &V> {
        self.slots.values().map(|s| &s.value)
    }

    /// Bound sessions now.
    pub(crate) fn bound(&self) -> usize {
        self.slots.len() - self.unbound
    }

    /// Unbound sessions now.
    #[cfg(test)]
    pub(crate) fn unbound(&self) -> usize {
        self.unbound
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::SocketAddr;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    fn limits() -> SessionLimits {
        SessionLimits {
            max_bound: 4,
            max_unbound: 3,
            unbound_ttl: Duration::from_secs(5),
        }
    }

    fn found(l: Lookup<SocketAddr, u32>) -> (u32, Option<(SocketAddr, u32)>) {
        match l {
            Lookup::Found(v, out) => (v, out),
            Lookup::Refused => panic!("refused"),
        }
    }

    #[test]
    fn a_flood_of_unbound_sessions_never_pushes_out_a_bound_one() {
        let t0 = Instant::now();
        let mut t = SessionTable::new(limits());
        // A real peer, bound.
        found(t.get_or_insert(addr(1), t0, true, true, || 1));
        // A flood from 1,000 ports: each new address pushes out the oldest unbound one.
        let mut pushed = 0;
        for p in 100..1100u16 {
            let (_, out) = found(t.get_or_insert(addr(p), t0, true, false, || u32::from(p)));
            if let Some((a, _)) = out {
                assert_ne!(a, addr(1), "a bound session was pushed out");
                pushed += 1;
            }
        }
        assert_eq!(pushed, 1000 - 3);
        assert_eq!((t.bound(), t.unbound()), (1, 3));
        assert!(t.is_bound(&addr(1)));
        // A fresh node arriving during the flood: its first datagram makes an unbound session
        // (pushing out a flooder), its Hello binds it, and the flood no longer touches it.
        found(t.get_or_insert(addr(2), t0, true, false, || 2));
        found(t.get_or_insert(addr(2), t0, false, true, || 0));
        for p in 2000..2100u16 {
            found(t.get_or_insert(addr(p), t0, true, false, || 0));
        }
        assert!(t.is_bound(&addr(2)) && t.get(&addr(2)) == Some(&2));
        assert_eq!((t.bound(), t.unbound()), (2, 3));
        // The bookkeeping of the order stays bounded however long the flood lasts.
        assert!(t.unbound_order.len() <= 2 * limits().max_unbound + 64);
    }

    #[test]
    fn unbound_sessions_expire_and_bound_ones_stay() {
        let t0 = Instant::now();
        let mut t = SessionTable::new(limits());
        found(t.get_or_insert(addr(1), t0, true, false, || 1));
        found(t.get_or_insert(addr(2), t0 + Duration::from_secs(1), true, false, || 2));
        found(t.get_or_insert(addr(3), t0, false, true, || 3));
        assert_eq!(t.next_expiry(), Some(t0 + Duration::from_secs(5)));
        assert!(t.expire(t0 + Duration::from_secs(4)).is_empty());
        let gone = t.expire(t0 + Duration::from_secs(5));
        assert_eq!(gone, vec![(addr(1), 1)]);
        assert_eq!(t.next_expiry(), Some(t0 + Duration::from_secs(6)));
        // Bound before it expires: it stays.
        found(t.get_or_insert(addr(2), t0, false, true, || 0));
        assert!(t.expire(t0 + Duration::from_secs(60)).is_empty());
        assert_eq!(t.next_expiry(), None);
        assert_eq!((t.bound(), t.unbound()), (2, 0));
        assert_eq!(t.remove(&addr(3)), Some(3));
        assert_eq!((t.bound(), t.unbound()), (1, 0));
    }

    #[test]
    fn binds_beyond_the_bound_cap_are_refused_and_no_lookup_creates_unasked() {
        let t0 = Instant::now();
        let mut t = SessionTable::new(limits());
        for p in 0..4 {
            found(t.get_or_insert(addr(p), t0, false, true, || 0));
        }
        assert!(matches!(
            t.get_or_insert(addr(9), t0, true, true, || 9),
            Lookup::Refused
        ));
        // An unbound session stays usable (unbound) when the bound class is full.
        found(t.get_or_insert(addr(9), t0, true, false, || 9));
        found(t.get_or_insert(addr(9), t0, false, true, || 0));
        assert!(!t.is_bound(&addr(9)));
        assert!(matches!(
            t.get_or_insert(addr(10), t0, false, false, || 10),
            Lookup::Refused
        ));
        assert_eq!(t.values().count(), 5);
        assert_eq!(t.values().count(), 5);
        assert_eq!(t.drain().count(), 5);
        assert_eq!((t.bound(), t.unbound()), (0, 0));
    }
}

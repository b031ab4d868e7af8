//! Messages larger than one datagram: sent as safe messages, its *parts*, and joined again by
//! the receiver. The ARQ delivers a session's safe messages once each and in order, so a
//! message's parts arrive in order, with the safe class's guarantees; urgent whole messages
//! (a call passing a camera frame) may come between two parts, never another message's parts.
//!
//! ```text
//! part := 0xFE bytes    a part, more follow
//!       | 0xFD bytes    the last part
//! ```
//! No protocol message begins with either byte (its first byte is its tag, see
//! [`crate::protocol::tag`]), so whole messages travel unmarked, as before.

use std::borrow::Cow;

/// First byte of a part that more parts follow.
pub const PART_MORE: u8 = 0xFE;
/// First byte of a message's last part.
pub const PART_LAST: u8 = 0xFD;

/// The smallest part a link makes (a tiny MTU still carries some bytes per part).
pub const MIN_ROOM: usize = 64;

/// Whether `msg` is a part (not a whole message).
pub fn is_part(msg: &[u8]) -> bool {
    matches!(msg.first(), Some(&(PART_MORE | PART_LAST)))
}

/// Splits `msg` into parts of at most `room` bytes each, marker included (`room` ≥ 2).
pub fn split(msg: &[u8], room: usize) -> Vec<Vec<u8>> {
    let chunk = room.max(2) - 1;
    let count = msg.len().div_ceil(chunk);
    msg.chunks(chunk)
        .enumerate()
        .map(|(k, c)| {
            let mut part = Vec::with_capacity(c.len() + 1);
            part.push(if k + 1 == count { PART_LAST } else { PART_MORE });
            part.extend_from_slice(c);
            part
        })
        .collect()
}

/// Why parts were dropped instead of joined.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JoinDrop {
    /// The message grew past the largest one taken: its parts are dropped up to its last.
    TooLarge,
}

/// Joins the parts of one session's messages.
#[derive(Debug, Default)]
pub struct Joiner {
    buf: Vec<u8>,
    /// Inside a message being dropped (too large), up to its last part.
    dropping: bool,
}

impl Joiner {
    /// Takes the next safe message in order; returns the whole message when `m` completes
    /// one (or is one: it passes a message being joined), and what was dropped on the way, if
    /// anything. Messages larger than `max` bytes are dropped. A sender that restarts its
    /// session mid-message is the caller's to notice ([`Joiner::reset`]).
    pub fn take<'a>(
        &mut self,
        m: Cow<'a, [u8]>,
        max: usize,
    ) -> (Option<Cow<'a, [u8]>>, Option<JoinDrop>) {
        let marker = m.first().copied();
        if !is_part(&m) {
            return (Some(m), None);
        }
        let last = marker == Some(PART_LAST);
        if self.dropping {
            self.dropping = !last;
            return (None, None);
        }
        let body = &m[1..];
        if self.buf.len() + body.len() > max {
            self.buf = Vec::new();
            self.dropping = !last;
            return (None, Some(JoinDrop::TooLarge));
        }
        if last && self.buf.is_empty() {
            return (Some(Cow::Owned(body.to_vec())), None);
        }
        self.buf.extend_from_slice(body);
        if last {
            (Some(Cow::Owned(std::mem::take(&mut self.buf))), None)
        } else {
            (None, None)
        }
    }

    /// Forgets a message being joined (the sender's session changed).
    pub fn reset(&mut self) {
        self.buf = Vec::new();
        self.dropping = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn join_all(j: &mut Joiner, parts: Vec<Vec<u8>>, max: usize) -> Vec<Vec<u8>> {
        parts
            .into_iter()
            .filter_map(|p| j.take(Cow::Owned(p), max).0.map(Cow::into_owned))
            .collect()
    }

    #[test]
    fn a_message_split_and_joined_is_the_same_message() {
        let msg: Vec<u8> = (0..10_000u32).map(|i| (i % 251) as u8).collect();
        for room in [2, 3, 1400, 9_999, 10_000, 10_001, 65_000] {
            let parts = split(&msg, room);
            assert!(parts.iter().all(|p| p.len() <= room), "room {room}");
            assert_eq!(parts.len(), msg.len().div_ceil(room - 1), "room {room}");
            let mut j = Joiner::default();
            assert_eq!(
                join_all(&mut j, parts, 1 << 20),
                vec![msg.clone()],
                "{room}"
            );
        }
    }

    #[test]
    fn whole_messages_pass_between_joined_ones() {
        let mut j = Joiner::default();
        let whole = vec![crate::protocol::tag::EVENT, 1, 2];
        let (out, drop) = j.take(Cow::Borrowed(&whole), 100);
        assert_eq!((out.as_deref(), drop), (Some(&whole[..]), None));
        let big = vec![7u8; 50];
        let mut got = join_all(&mut j, split(&big, 8), 100);
        got.extend(join_all(&mut j, vec![whole.clone()], 100));
        assert_eq!(got, vec![big, whole]);
    }

    #[test]
    fn a_message_over_the_limit_is_dropped_and_the_next_one_joined() {
        let mut j = Joiner::default();
        let mut drops = Vec::new();
        let mut got = Vec::new();
        for p in split(&[1u8; 300], 64)
            .into_iter()
            .chain(split(&[2u8; 90], 64))
        {
            let (out, drop) = j.take(Cow::Owned(p), 100);
            got.extend(out.map(Cow::into_owned));
            drops.extend(drop);
        }
        assert_eq!(drops, [JoinDrop::TooLarge]);
        assert_eq!(got, vec![vec![2u8; 90]]);
    }

    #[test]
    fn whole_messages_pass_between_the_parts_of_one_being_joined() {
        let mut j = Joiner::default();
        let big: Vec<u8> = (0..40u8).collect();
        let call = vec![crate::protocol::tag::CALL, 9];
        let mut parts = split(&big, 16).into_iter();
        let mut got = join_all(&mut j, parts.by_ref().take(2).collect(), 100);
        let (out, drop) = j.take(Cow::Borrowed(&call), 100);
        assert_eq!((out.as_deref(), drop), (Some(&call[..]), None));
        got.extend(join_all(&mut j, parts.collect(), 100));
        assert_eq!(
            got,
            vec![big],
            "joined whole, the call between its parts notwithstanding"
        );
        // A session restarted mid-message: the caller resets, the next message joins alone.
        let mut cut = split(&[3u8; 40], 16);
        cut.pop();
        assert!(join_all(&mut j, cut, 100).is_empty());
        j.reset();
        assert_eq!(
            join_all(&mut j, split(&[4u8; 20], 16), 100),
            vec![vec![4u8; 20]]
        );
    }
}

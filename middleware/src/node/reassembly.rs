//! The receiving side of one file transfer as a pure machine (no I/O, no clock): given the
//! size the sender announced and what is already on disk, it says for each chunk that arrives
//! whether to append it, when to acknowledge progress to the sender, and when a chunk going
//! past the announced size ends the transfer. `files.rs` drives it with the part file and the
//! channel of chunks; the fuzz harness `marea::fuzzing::file_chunks` drives it with a line that
//! drops, duplicates, reorders and forges chunks.
//!
//! Chunks are taken strictly in order: a chunk is appended only when it starts where the file
//! ends now, so a duplicate, a resend of what is written, or a chunk ahead of a gap is skipped
//! (the sender resends from the last acknowledged offset). Acknowledgements are end to end:
//! the sender's window moves on what the receiver wrote.

/// Chunks between two progress acknowledgements of a receiver (`FileAccept` with the bytes
/// written so far). Well below the sender's default window, so it never stalls on them.
pub(crate) const PROGRESS_EVERY: u32 = 16;
/// Bytes after which a receiver acknowledges progress even before [`PROGRESS_EVERY`] chunks:
/// large chunks (shared memory) would otherwise move the sender's window in big steps.
pub(crate) const PROGRESS_BYTES: u64 = 1 << 20;

/// What to do with one chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ChunkStep {
    /// Not the next bytes (a duplicate, a resend, one ahead of a gap, or the transfer is
    /// over): dropped.
    Skip,
    /// Append the chunk to the file; then acknowledge `ack` to the sender when set.
    Write {
        /// The offset to acknowledge (everything before it is written).
        ack: Option<u64>,
    },
    /// The chunk reaches past the size the sender announced: the transfer ends and nothing
    /// of it is kept.
    Overrun {
        /// Where the chunk would have ended.
        reached: u64,
    },
}

/// One transfer's reassembly state.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Reassembly {
    size: u64,
    expected: u64,
    acknowledged: u64,
    unacknowledged: u32,
    overrun: bool,
}

impl Reassembly {
    /// A transfer of `size` bytes of which the first `on_disk` are already written (a resume;
    /// the receiver acknowledged them when it accepted the offer).
    pub fn new(size: u64, on_disk: u64) -> Self {
        Reassembly {
            size,
            expected: on_disk,
            acknowledged: on_disk,
            unacknowledged: 0,
            overrun: false,
        }
    }

    /// Bytes written so far (the offset the next chunk must start at).
    #[cfg_attr(not(any(test, feature = "fuzzing")), allow(dead_code))]
    pub fn expected(&self) -> u64 {
        self.expected
    }

    /// Whether every announced byte is written.
    pub fn is_complete(&self) -> bool {
        !self.overrun && self.expected >= self.size
    }

    /// Whether a chunk went past the announced size (the transfer is over).
    #[cfg_attr(not(any(test, feature = "fuzzing")), allow(dead_code))]
    pub fn is_overrun(&self) -> bool {
        self.overrun
    }

    /// Takes a chunk of `len` bytes at offset `at`.
    pub fn on_chunk(&mut self, at: u64, len: usize) -> ChunkStep {
        if self.overrun || at != self.expected || self.is_complete() {
            return ChunkStep::Skip;
        }
        let reached = at.saturating_add(len as u64);
        if reached > self.size {
            self.overrun = true;
            return ChunkStep::Overrun { reached };
        }
        self.expected = reached;
        self.unacknowledged += 1;
        let ack = if self.unacknowledged >= PROGRESS_EVERY
            || self.expected - self.acknowledged >= PROGRESS_BYTES
            || self.expected == self.size
        {
            self.unacknowledged = 0;
            self.acknowledged = self.expected;
            Some(self.expected)
        } else {
            None
        };
        ChunkStep::Write { ack }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn in_order_chunks_are_written_and_acknowledged_at_the_end() {
        let mut r = Reassembly::new(10, 0);
        assert_eq!(r.on_chunk(0, 4), ChunkStep::Write { ack: None });
        // A duplicate and one ahead of a gap are skipped.
        assert_eq!(r.on_chunk(0, 4), ChunkStep::Skip);
        assert_eq!(r.on_chunk(8, 2), ChunkStep::Skip);
        assert_eq!(r.on_chunk(4, 6), ChunkStep::Write { ack: Some(10) });
        assert!(r.is_complete());
        assert_eq!(r.on_chunk(10, 0), ChunkStep::Skip);
    }

    #[test]
    fn progress_is_acknowledged_every_sixteen_chunks() {
        let mut r = Reassembly::new(100, 20);
        for i in 0..15 {
            assert_eq!(r.on_chunk(20 + i, 1), ChunkStep::Write { ack: None });
        }
        assert_eq!(r.on_chunk(35, 1), ChunkStep::Write { ack: Some(36) });
    }

    #[test]
    fn a_chunk_past_the_announced_size_ends_the_transfer() {
        let mut r = Reassembly::new(10, 8);
        assert_eq!(r.on_chunk(8, 3), ChunkStep::Overrun { reached: 11 });
        assert!(r.is_overrun() && !r.is_complete());
        assert_eq!(r.on_chunk(8, 2), ChunkStep::Skip);
        let mut r = Reassembly::new(10, 0);
        assert_eq!(
            r.on_chunk(0, usize::MAX),
            ChunkStep::Overrun {
                reached: usize::MAX as u64
            }
        );
    }
}

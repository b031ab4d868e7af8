//! Receiving files into a sink's directory: temp file, hash check, atomic rename, resume from
//! what is on disk; a sink's caps, refusals and the removal of stale partial files.
//!
//! A sink keeps its partial (`.part`) files in a private directory (`<dir>/.partial`, mode
//! 0700, owned by this user) and opens them without following symbolic links, so another user
//! cannot redirect what a sender writes. A stored file is synced before its rename and the
//! directories after it, so a crash leaves either the old state or the whole new file. Each sink
//! has caps ([`FileSinkOptions`]): file size (announced and actually sent), bytes on disk and
//! transfers at once; a refusal is a [`crate::protocol::FileVerdict`] the sender sees, logged and counted
//! ([`FileSinkStats`]). Partial files older than an age are removed at sink open and
//! periodically.

use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use tokio::io::AsyncWriteExt;
use tokio::sync::{mpsc, Notify};

use super::{hash_with, Incoming};
use crate::node::policy::Refusal;
use crate::node::reassembly::{ChunkStep, Reassembly};
use crate::node::{lock, NodeInner, OfferRole};
use crate::process::state_dir;
use crate::protocol::{FileOffer, FileVerdict, Message, NodeId};

/// Name of a sink's private directory of partial files (hidden: no sent file name may start
/// with a dot, so no transfer can target it).
pub(crate) const PARTIAL_DIR: &str = ".partial";

/// A file that arrived in a sink.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReceivedFile {
    /// Where it was stored.
    pub path: PathBuf,
    /// Its name as sent.
    pub name: String,
    /// Size in bytes.
    pub size: u64,
    /// The sending node.
    pub from: String,
    /// Bytes that were already on disk from an interrupted attempt.
    pub resumed_from: u64,
}

/// Completed files waiting for the sink's owner.
#[derive(Default)]
pub(crate) struct SinkMailbox {
    queue: Mutex<(VecDeque<ReceivedFile>, bool)>,
    notify: Notify,
}

impl SinkMailbox {
    pub fn push(&self, f: ReceivedFile) {
        lock(&self.queue).0.push_back(f);
        self.notify.notify_one();
    }

    pub fn close(&self) {
        lock(&self.queue).1 = true;
        self.notify.notify_one();
    }

    pub async fn pop(&self) -> Option<ReceivedFile> {
        loop {
            {
                let mut g = lock(&self.queue);
                if let Some(f) = g.0.pop_front() {
                    return Some(f);
                }
                if g.1 {
                    return None;
                }
            }
            self.notify.notified().await;
        }
    }
}

/// Limits and housekeeping of one file sink. The defaults suit flight plans and logs on a
/// vehicle's disk; set tighter ones for sinks open to many senders.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileSinkOptions {
    /// Where stored files go. `None`: `<state dir>/sinks/<full sink name>` (see [`state_dir`]),
    /// never a shared temporary directory.
    pub dir: Option<PathBuf>,
    /// Largest file accepted, checked against the size a sender announces and against the
    /// bytes it actually sends.
    pub max_file_size: u64,
    /// Most bytes the sink's directory may hold: stored files, partial files and the announced
    /// size of transfers in progress.
    pub quota_bytes: u64,
    /// Files received at once; one more is refused as busy.
    pub max_concurrent: u32,
    /// Partial files not written to for this long are removed (at sink open and periodically):
    /// an interrupted transfer may resume within this time.
    pub stale_part_age: Duration,
    /// Asked about each file received whole (hash verified) before it is stored: a refusal is
    /// the sender's verdict (`FileSendError::Rejected` with the reason) and nothing is stored.
    /// `None`: every file that arrives whole is stored.
    pub check: Option<FileCheck>,
}

/// A received file, complete and hash verified, not yet stored: what a [`FileCheck`] decides on.
#[derive(Debug, Clone)]
pub struct FileToCheck {
    /// File name (no directories).
    pub name: String,
    /// Where its content is now (a partial file of the sink; read it, do not keep the path).
    pub path: PathBuf,
    /// The sending node (the node behind a gateway).
    pub from: String,
}

/// The future a [`FileCheck`] returns.
pub type FileCheckFuture = Pin<Box<dyn Future<Output = Result<(), String>> + Send>>;

/// Decides whether a sink stores a file it received (see [`FileSinkOptions::check`]): `Ok` stores
/// it, `Err(reason)` refuses it with that reason. The sender waits for the decision, so a sink
/// that loads what it receives (a flight plan) can answer with the load's outcome.
#[derive(Clone)]
pub struct FileCheck(Arc<dyn Fn(FileToCheck) -> FileCheckFuture + Send + Sync>);

impl FileCheck {
    /// A check made of `f`.
    pub fn new<F, Fut>(f: F) -> Self
    where
        F: Fn(FileToCheck) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<(), String>> + Send + 'static,
    {
        FileCheck(Arc::new(move |file| Box::pin(f(file))))
    }

    fn run(&self, file: FileToCheck) -> FileCheckFuture {
        (self.0)(file)
    }
}

impl std::fmt::Debug for FileCheck {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FileCheck")
    }
}

/// Two checks are equal when they are the same one (clones of one `FileCheck`).
impl PartialEq for FileCheck {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Eq for FileCheck {}

impl Default for FileSinkOptions {
    fn default() -> Self {
        FileSinkOptions {
            dir: None,
            max_file_size: 256 << 20,
            quota_bytes: 1 << 30,
            max_concurrent: 4,
            stale_part_age: Duration::from_secs(24 * 3600),
            check: None,
        }
    }
}

/// What a sink did since it opened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FileSinkStats {
    /// Files stored.
    pub stored: u64,
    /// Transfers refused as too large (announced or actually sent).
    pub too_large: u64,
    /// Transfers refused for the quota.
    pub quota_exceeded: u64,
    /// Transfers refused because the sink was busy.
    pub busy: u64,
    /// Transfers that failed otherwise (bad name, hash mismatch, I/O).
    pub failed: u64,
    /// Stale partial files removed.
    pub stale_parts_removed: u64,
}

#[derive(Default)]
struct SinkCounters {
    stored: AtomicU64,
    too_large: AtomicU64,
    quota_exceeded: AtomicU64,
    busy: AtomicU64,
    failed: AtomicU64,
    stale_parts_removed: AtomicU64,
}

/// A transfer a sink is receiving.
struct Active {
    generation: u64,
    size: u64,
    part: PathBuf,
    /// Held by the task writing the part file: a task that replaces it waits for it to stop.
    writer: Arc<tokio::sync::Mutex<()>>,
}

/// A sink's directory, limits, transfers in progress and counters.
pub(crate) struct SinkState {
    pub name: Arc<str>,
    pub dir: PathBuf,
    partial: PathBuf,
    options: FileSinkOptions,
    active: Mutex<HashMap<u64, Active>>,
    counters: SinkCounters,
    /// When each sender's refusals of each kind were last logged.
    logged: Mutex<HashMap<(NodeId, std::mem::Discriminant<FileVerdict>), Instant>>,
}

/// Least time between two log lines for the same sender's refusals of the same kind: a
/// sender retrying in a loop is counted every time but logged once a minute.
const LOG_EVERY: Duration = Duration::from_secs(60);

/// Creates `dir` (and its parents) if missing, then its private subdirectory of partial files
/// with mode 0700. An existing one must be a real directory (not a link) that this user may
/// chmod, i.e. owns.
fn open_private_dir(dir: &Path) -> std::io::Result<PathBuf> {
    std::fs::create_dir_all(dir)?;
    let partial = dir.join(PARTIAL_DIR);
    match std::fs::DirBuilder::new().mode(0o700).create(&partial) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(e),
    }
    let meta = std::fs::symlink_metadata(&partial)?;
    if !meta.is_dir() {
        return Err(std::io::Error::other(format!(
            "{} is not a directory (a symbolic link?)",
            partial.display()
        )));
    }
    // Fails unless we own it: someone else's directory is never used for our partial files.
    std::fs::set_permissions(&partial, std::fs::Permissions::from_mode(0o700))?;
    Ok(partial)
}

/// Opens a directory to fsync it.
fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir)?.sync_all()
}

impl SinkState {
    /// Prepares the sink's directories and removes stale partial files.
    pub fn open(name: Arc<str>, options: FileSinkOptions) -> Result<Self, (PathBuf, String)> {
        let dir = match &options.dir {
            Some(d) => d.clone(),
            None => state_dir()
                .map(|s| s.join("sinks").join(name.replace('/', "_")))
                .ok_or_else(|| {
                    (
                        PathBuf::from("$XDG_STATE_HOME"),
                        "no state directory: neither XDG_STATE_HOME nor HOME is set".to_owned(),
                    )
                })?,
        };
        let partial = open_private_dir(&dir).map_err(|e| (dir.clone(), e.to_string()))?;
        let state = SinkState {
            name,
            dir,
            partial,
            options,
            active: Mutex::default(),
            counters: SinkCounters::default(),
            logged: Mutex::default(),
        };
        state.remove_stale_parts();
        Ok(state)
    }

    pub fn stats(&self) -> FileSinkStats {
        let c = &self.counters;
        let r = |a: &AtomicU64| a.load(Ordering::Relaxed);
        FileSinkStats {
            stored: r(&c.stored),
            too_large: r(&c.too_large),
            quota_exceeded: r(&c.quota_exceeded),
            busy: r(&c.busy),
            failed: r(&c.failed),
            stale_parts_removed: r(&c.stale_parts_removed),
        }
    }

    /// How often stale partial files are looked for.
    pub fn sweep_period(&self) -> Duration {
        (self.options.stale_part_age / 2)
            .clamp(Duration::from_millis(100), Duration::from_secs(600))
    }

    /// Removes the partial files not written to within the stale age (and anything in the
    /// private directory that is not a regular file), except those of transfers in progress.
    /// Returns how many were removed.
    pub fn remove_stale_parts(&self) -> usize {
        // Also the partial files earlier versions kept beside the stored ones
        // (`<dir>/.<name>.<transfer>.part`): never resumed now, they only take room.
        let legacy = std::fs::read_dir(&self.dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| {
                let n = e.file_name();
                let n = n.to_string_lossy();
                n.starts_with('.') && n.ends_with(".part")
            });
        let entries = std::fs::read_dir(&self.partial)
            .into_iter()
            .flatten()
            .flatten()
            .chain(legacy);
        let now = SystemTime::now();
        let mut removed = 0;
        for e in entries {
            let path = e.path();
            if lock(&self.active).values().any(|a| a.part == path) {
                continue;
            }
            let Ok(meta) = std::fs::symlink_metadata(&path) else {
                continue;
            };
            let age = meta
                .modified()
                .ok()
                .and_then(|m| now.duration_since(m).ok())
                .unwrap_or_default();
            if meta.is_dir() || (meta.is_file() && age < self.options.stale_part_age) {
                continue;
            }
            match std::fs::remove_file(&path) {
                Ok(()) => {
                    removed += 1;
                    tracing::info!(sink = %self.name, part = %path.display(), ?age, "stale partial file removed");
                }
                Err(e) => {
                    tracing::warn!(sink = %self.name, part = %path.display(), error = %e, "cannot remove stale partial file")
                }
            }
        }
        self.counters
            .stale_parts_removed
            .fetch_add(removed as u64, Ordering::Relaxed);
        removed
    }

    /// Bytes the sink would hold with the transfers in progress completed: stored files
    /// (except `replacing`, which the new file replaces), partial files of no transfer in
    /// progress, and the announced size of every transfer in progress.
    fn bytes_needed(&self, replacing: &str) -> u64 {
        let (reserved, parts): (u64, Vec<PathBuf>) = {
            let active = lock(&self.active);
            (
                active.values().map(|a| a.size).sum(),
                active.values().map(|a| a.part.clone()).collect(),
            )
        };
        let regular = |e: &std::fs::DirEntry| {
            std::fs::symlink_metadata(e.path())
                .ok()
                .filter(|m| m.is_file())
                .map(|m| m.len())
        };
        let stored: u64 = std::fs::read_dir(&self.dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.file_name() != *replacing)
            .filter_map(|e| regular(&e))
            .sum();
        let partial: u64 = std::fs::read_dir(&self.partial)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| !parts.contains(&e.path()))
            .filter_map(|e| regular(&e))
            .sum();
        stored.saturating_add(partial).saturating_add(reserved)
    }

    /// Whether a refusal of `verdict`'s kind from `node` should be logged now.
    fn should_log(&self, node: NodeId, verdict: &FileVerdict) -> bool {
        let now = Instant::now();
        let mut logged = lock(&self.logged);
        // Bounded by the number of senders seen within a minute.
        logged.retain(|_, at| now.duration_since(*at) < LOG_EVERY);
        let key = (node, std::mem::discriminant(verdict));
        if logged.contains_key(&key) {
            return false;
        }
        logged.insert(key, now);
        true
    }

    fn count(&self, verdict: &FileVerdict) {
        let c = &self.counters;
        let counter = match verdict {
            FileVerdict::Stored => &c.stored,
            FileVerdict::TooLarge { .. } => &c.too_large,
            FileVerdict::QuotaExceeded { .. } => &c.quota_exceeded,
            FileVerdict::Busy { .. } => &c.busy,
            _ => &c.failed,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Forgets a transfer, unless a newer offer of it took its place.
    fn finish(&self, transfer: u64, generation: u64) {
        let mut active = lock(&self.active);
        if active
            .get(&transfer)
            .is_some_and(|a| a.generation == generation)
        {
            active.remove(&transfer);
        }
    }
}

/// A plain file name: no directories, no parent references, not hidden.
fn safe_file_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 255
        && !name.starts_with('.')
        && !name.contains(['/', '\\', '\0'])
}

/// Where the partial file of a transfer lives, inside a sink's private directory.
pub(crate) fn part_path(partial: &Path, name: &str, transfer: u64) -> PathBuf {
    partial.join(format!(".{name}.{transfer:016x}.part"))
}

/// Opens (creates, or reopens to resume) a partial file without following a symbolic link
/// planted at its path. Returns the file, positioned at its end, and the bytes already in it
/// (kept only when they are a plausible prefix: a regular file no larger than the announced
/// size; anything else at the path is removed and the transfer starts over).
fn open_part(part: &Path, size: u64) -> std::io::Result<(std::fs::File, u64)> {
    use std::io::Seek;
    let existing = match std::fs::symlink_metadata(part) {
        Ok(m) if m.is_file() && m.len() > 0 && m.len() <= size => Some(m.len()),
        Ok(m) => {
            if !m.is_file() {
                tracing::warn!(part = %part.display(), "not a regular file at a partial file's path; removed");
            }
            std::fs::remove_file(part)?;
            None
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(e),
    };
    let mut o = std::fs::OpenOptions::new();
    o.write(true).mode(0o600).custom_flags(libc::O_NOFOLLOW);
    if existing.is_none() {
        // Fails if anything (a link included) appeared at the path meanwhile.
        o.create_new(true);
    }
    let mut f = o.open(part)?;
    let meta = f.metadata()?;
    if !meta.is_file() {
        return Err(std::io::Error::other("not a regular file"));
    }
    let offset = meta.len().min(existing.unwrap_or(0));
    f.set_len(offset)?;
    f.seek(std::io::SeekFrom::Start(offset))?;
    Ok((f, offset))
}

/// Why a receiving task stopped without storing the file.
enum Stop {
    /// Sender gone, replaced or node stopping: the partial file stays for a resume.
    Quiet,
    /// The sender is told this verdict.
    Verdict(FileVerdict),
}

impl From<String> for Stop {
    fn from(reason: String) -> Self {
        Stop::Verdict(FileVerdict::Failed(reason))
    }
}

impl NodeInner {
    fn reply_file(&self, node: NodeId, transfer: u64, verdict: FileVerdict) {
        self.send_safe_to_node(node, &Message::FileDone { transfer, verdict });
    }

    /// Tells the sender a sink refused its file, logs it and counts it (in the sink's stats
    /// and in the health of the sender's link).
    fn refuse_file(&self, sink: &SinkState, node: NodeId, transfer: u64, verdict: FileVerdict) {
        let (from, link) = self
            .peers
            .by_id
            .get(&node)
            .map(|p| (p.name.to_string(), Some(p.link)))
            .unwrap_or_default();
        if let Some(link) = link {
            self.policy.count(link, Refusal::File);
        }
        if sink.should_log(node, &verdict) {
            tracing::warn!(sink = %sink.name, %from, %verdict, "incoming file refused (logged once a minute per sender and kind; all counted)");
        }
        sink.count(&verdict);
        self.reply_file(node, transfer, verdict);
    }

    pub fn on_file_offer(self: &Arc<Self>, node: NodeId, offer: FileOffer) {
        let FileOffer {
            transfer,
            sink,
            name,
            size,
            hash,
            sender,
        } = offer;
        let sink_name = self.local.offers.get(&sink).map(|o| o.name.clone());
        if let Some(sink_name) = sink_name {
            let permitted = self.permitted(
                node,
                sender.as_ref(),
                crate::config::AccessKind::File,
                &sink_name,
            );
            if let Err(why) = permitted {
                let verdict = FileVerdict::Denied(match why {
                    Refusal::ForeignOrigin => format!(
                        "'{}' sent a file on behalf of another node but is no gateway",
                        self.peer_name(node)
                    ),
                    _ => {
                        format!("sending to '{sink_name}' is not allowed for this node by <access>")
                    }
                });
                self.reply_file(node, transfer, verdict);
                return;
            }
        }
        let relay = self.local.offers.get(&sink).and_then(|o| match o.role {
            OfferRole::Relay { origin, remote_id } => Some((origin, remote_id)),
            _ => None,
        });
        if let Some((receiver, remote_sink)) = relay {
            if !self.may_relay_for(node, &name) {
                let verdict = FileVerdict::Denied(format!(
                    "'{}' has not proven its identity: this gateway names no unproven sender to the next node",
                    self.peer_name(node)
                ));
                self.reply_file(node, transfer, verdict);
                return;
            }
            let offer = Message::FileOffer(FileOffer {
                transfer,
                sink: remote_sink,
                name,
                size,
                hash,
                sender: Some(self.caller_to_relay(node, sender.as_ref())),
            });
            self.relay_file_offer(node, receiver, transfer, &offer);
            return;
        }
        let Some((state, mailbox)) = self.local.offers.get(&sink).and_then(|o| match &o.role {
            OfferRole::File { state, mailbox } => Some((state.clone(), mailbox.clone())),
            _ => None,
        }) else {
            if let Some((link, name)) = self
                .peers
                .by_id
                .get(&node)
                .map(|p| (p.link, p.name.clone()))
            {
                self.policy
                    .refuse(link, node, &name, "file sink", Refusal::File);
            }
            self.reply_file(
                node,
                transfer,
                FileVerdict::Failed("no such file sink".into()),
            );
            return;
        };
        if !safe_file_name(&name) {
            let reason = format!("refused file name {name:?}: must be a plain file name");
            self.refuse_file(&state, node, transfer, FileVerdict::Failed(reason));
            return;
        }
        if size > state.options.max_file_size {
            let max = state.options.max_file_size;
            self.refuse_file(&state, node, transfer, FileVerdict::TooLarge { size, max });
            return;
        }
        let part = part_path(&state.partial, &name, transfer);
        let generation = self.transfers.generations.fetch_add(1, Ordering::Relaxed);
        let writer = {
            let mut active = lock(&state.active);
            // A new offer of the same transfer (the sender restarted) replaces the old one and
            // waits for its writer; any other offer counts against the limit.
            let replaced = active.get(&transfer).map(|a| a.writer.clone());
            if replaced.is_none() && active.len() >= state.options.max_concurrent as usize {
                drop(active);
                let max = state.options.max_concurrent;
                self.refuse_file(&state, node, transfer, FileVerdict::Busy { max });
                return;
            }
            let writer = replaced.unwrap_or_default();
            active.insert(
                transfer,
                Active {
                    generation,
                    size,
                    part: part.clone(),
                    writer: writer.clone(),
                },
            );
            writer
        };
        let (tx, mut rx) = mpsc::unbounded_channel::<(u64, Vec<u8>)>();
        // Replacing the entry drops the old task's channel: it stops and releases the writer.
        self.transfers.incoming.insert(
            transfer,
            Incoming {
                node,
                generation,
                chunks: tx,
            },
        );
        // The sender: the node a gateway relays for, or the peer itself.
        let from = match sender {
            Some(o) => o.name,
            None => self
                .peers
                .by_id
                .get(&node)
                .map(|p| p.name.to_string())
                .unwrap_or_default(),
        };
        let inner = self.clone();
        let sink_state = state.clone();
        crate::sync::spawn_tracked(&self.tasks, async move {
            let state = sink_state;
            let result: Result<ReceivedFile, Stop> = async {
                let _writing = writer.lock().await;
                let quota = state.options.quota_bytes;
                let check = state.clone();
                let dest_name = name.clone();
                let needed = tokio::task::spawn_blocking(move || check.bytes_needed(&dest_name))
                    .await
                    .unwrap_or(u64::MAX);
                if needed > quota {
                    return Err(Stop::Verdict(FileVerdict::QuotaExceeded { needed, quota }));
                }
                let opened = {
                    let part = part.clone();
                    tokio::task::spawn_blocking(move || open_part(&part, size))
                        .await
                        .map_err(std::io::Error::other)
                        .and_then(|r| r)
                };
                let (file, offset) =
                    opened.map_err(|e| format!("cannot open {}: {e}", part.display()))?;
                inner.send_safe_to_node(node, &Message::FileAccept { transfer, offset });
                let mut w =
                    tokio::io::BufWriter::with_capacity(1 << 18, tokio::fs::File::from_std(file));
                // What to write and acknowledge is decided by the pure machine; this loop only
                // does the I/O.
                let mut reassembly = Reassembly::new(size, offset);
                while !reassembly.is_complete() {
                    let next = tokio::select! {
                        _ = inner.cancel.cancelled() => None,
                        c = rx.recv() => c,
                    };
                    let Some((at, data)) = next else {
                        // Sender gone, replaced or node stopping: keep what we have for a resume.
                        let _ = w.flush().await;
                        return Err(Stop::Quiet);
                    };
                    match reassembly.on_chunk(at, data.len()) {
                        ChunkStep::Skip => continue,
                        ChunkStep::Overrun { reached } => {
                            // Past its own announcement: cut off, nothing of it is kept.
                            drop(w);
                            let _ = tokio::fs::remove_file(&part).await;
                            return Err(Stop::Verdict(FileVerdict::TooLarge {
                                size: reached,
                                max: size,
                            }));
                        }
                        ChunkStep::Write { ack } => {
                            w.write_all(&data)
                                .await
                                .map_err(|e| format!("cannot write {}: {e}", part.display()))?;
                            // End-to-end progress: the sender's window moves on what we wrote,
                            // not on what the first hop (maybe a gateway) acknowledged.
                            if let Some(offset) = ack {
                                inner.send_safe_to_node(
                                    node,
                                    &Message::FileAccept { transfer, offset },
                                );
                            }
                        }
                    }
                }
                w.flush()
                    .await
                    .map_err(|e| format!("cannot write {}: {e}", part.display()))?;
                let file = w.into_inner();
                // On disk before it is renamed into place: a crash never leaves a renamed but
                // incomplete file.
                file.sync_all()
                    .await
                    .map_err(|e| format!("cannot sync {}: {e}", part.display()))?;
                drop(file);
                let got = hash_with(part.clone(), true)
                    .await
                    .map_err(|e| format!("cannot read back {}: {e}", part.display()))?;
                if got != hash {
                    let _ = tokio::fs::remove_file(&part).await;
                    return Err("content hash mismatch; partial file discarded"
                        .to_owned()
                        .into());
                }
                if let Some(check) = &state.options.check {
                    let file = FileToCheck {
                        name: name.clone(),
                        path: part.clone(),
                        from: from.clone(),
                    };
                    if let Err(reason) = check.run(file).await {
                        let _ = tokio::fs::remove_file(&part).await;
                        return Err(reason.into());
                    }
                }
                let dest = state.dir.join(&name);
                tokio::fs::rename(&part, &dest)
                    .await
                    .map_err(|e| format!("cannot rename into {}: {e}", dest.display()))?;
                // The rename itself made durable: both directories changed.
                let (dir, partial) = (state.dir.clone(), state.partial.clone());
                tokio::task::spawn_blocking(move || {
                    sync_dir(&dir).and_then(|()| sync_dir(&partial))
                })
                .await
                .map_err(std::io::Error::other)
                .and_then(|r| r)
                .map_err(|e| format!("cannot sync {}: {e}", state.dir.display()))?;
                Ok(ReceivedFile {
                    path: dest,
                    name: name.clone(),
                    size,
                    from: from.clone(),
                    resumed_from: offset,
                })
            }
            .await;
            inner
                .transfers
                .incoming
                .remove_if(&transfer, |_, i| i.generation == generation);
            state.finish(transfer, generation);
            match result {
                Ok(f) => {
                    tracing::info!(file = %f.path.display(), size, from = %f.from, "file received");
                    state.count(&FileVerdict::Stored);
                    inner.reply_file(node, transfer, FileVerdict::Stored);
                    mailbox.push(f);
                }
                Err(Stop::Quiet) => {}
                Err(Stop::Verdict(verdict)) => inner.refuse_file(&state, node, transfer, verdict),
            }
        });
    }

    pub fn on_file_chunk(&self, node: NodeId, transfer: u64, offset: u64, data: Vec<u8>) {
        if let Some(i) = self.transfers.incoming.get(&transfer) {
            if i.node == node {
                let _ = i.chunks.send((offset, data));
            }
        }
    }

    pub fn on_file_cancel(&self, node: NodeId, transfer: u64) {
        self.transfers
            .incoming
            .remove_if(&transfer, |_, i| i.node == node);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn private_directory_is_0700_and_a_planted_link_is_refused() {
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("sink");
        let partial = open_private_dir(&dir).unwrap();
        let mode = std::fs::metadata(&partial).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o700);
        // A directory someone left open is closed again.
        std::fs::set_permissions(&partial, std::fs::Permissions::from_mode(0o777)).unwrap();
        open_private_dir(&dir).unwrap();
        let mode = std::fs::metadata(&partial).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o700);
        // A link in its place (to a directory of the attacker's choice) is not used.
        let other = t.path().join("elsewhere");
        std::fs::create_dir(&other).unwrap();
        let dir2 = t.path().join("sink2");
        std::fs::create_dir(&dir2).unwrap();
        std::os::unix::fs::symlink(&other, dir2.join(PARTIAL_DIR)).unwrap();
        let err = open_private_dir(&dir2).unwrap_err();
        assert!(err.to_string().contains("not a directory"), "{err}");
    }

    #[test]
    fn part_file_is_opened_without_following_a_link() {
        let t = tempfile::tempdir().unwrap();
        let target = t.path().join("target");
        std::fs::write(&target, b"secret").unwrap();
        let part = t.path().join(".x.part");
        std::os::unix::fs::symlink(&target, &part).unwrap();
        let (mut f, offset) = open_part(&part, 100).unwrap();
        assert_eq!(offset, 0, "resumed from the link's target");
        std::io::Write::write_all(&mut f, b"new").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"secret");
        let meta = std::fs::symlink_metadata(&part).unwrap();
        assert!(meta.is_file());
        assert_eq!(meta.permissions().mode() & 0o777, 0o600);
        // A regular partial file no larger than announced is resumed.
        let (_, offset) = open_part(&part, 100).unwrap();
        assert_eq!(offset, 3);
        // One larger than announced is from another file: start over.
        let (_, offset) = open_part(&part, 2).unwrap();
        assert_eq!(offset, 0);
        assert_eq!(std::fs::metadata(&part).unwrap().len(), 0);
    }

    #[test]
    fn refusals_are_logged_once_a_minute_per_sender_and_kind() {
        let t = tempfile::tempdir().unwrap();
        let sink = SinkState::open(
            "ns/svc/files".into(),
            FileSinkOptions {
                dir: Some(t.path().to_owned()),
                ..FileSinkOptions::default()
            },
        )
        .unwrap();
        let busy = FileVerdict::Busy { max: 1 };
        let big = FileVerdict::TooLarge { size: 2, max: 1 };
        assert!(sink.should_log(7, &busy));
        assert!(!sink.should_log(7, &busy), "logged twice within a minute");
        assert!(!sink.should_log(7, &FileVerdict::Busy { max: 9 }));
        assert!(sink.should_log(7, &big), "another kind is logged");
        assert!(sink.should_log(8, &busy), "another sender is logged");
    }

    #[test]
    fn only_plain_file_names_are_accepted() {
        assert!(safe_file_name("plan.xml"));
        assert!(!safe_file_name("../etc/passwd"));
        assert!(!safe_file_name("a/b"));
        assert!(!safe_file_name(".hidden"));
        assert!(!safe_file_name(""));
    }
}

//! Supervised child processes: each service of a mission runs as a child in its own process
//! group (so a terminal's Ctrl-C reaches only the launcher, which then stops the children in
//! order), its output merged into the launcher's with a `[node/service]` prefix, restarted with
//! backoff when it dies, and stopped with SIGTERM, then SIGKILL after a grace period. If the
//! launcher dies without stopping them (SIGKILL, a crash), the kernel sends each SIGTERM.

use std::path::PathBuf;
use std::process::{ExitStatus, Stdio};
use std::sync::Arc;
use std::time::Duration;

use serde_json::json;
use tokio::io::{AsyncBufReadExt, AsyncRead, BufReader};
use tokio::process::{Child, Command};
use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::ui::Ui;

/// First wait before a restart; doubled after each quick failure up to [`BACKOFF_MAX`].
const BACKOFF_START: Duration = Duration::from_millis(500);
/// Longest wait before a restart.
const BACKOFF_MAX: Duration = Duration::from_secs(8);
/// A child that ran this long is considered healthy again: the backoff starts over.
const STABLE: Duration = Duration::from_secs(20);
/// Consecutive quick failures after which the supervisor gives up on a child.
const MAX_QUICK_FAILURES: u32 = 5;
/// Time a child gets between SIGTERM and SIGKILL.
const GRACE: Duration = Duration::from_secs(5);

/// A value a child prints on stdout once started (`MAVSIM_UDP=127.0.0.1:40123`). It is
/// published on `tx`, and a restarted child is given it back after `rebind_flag`, so peers
/// configured with it keep working.
pub struct Announce {
    /// The line's prefix, e.g. `MAVSIM_UDP=`.
    pub prefix: &'static str,
    /// The flag whose value is replaced by the announced one on restart, e.g. `--udp`.
    pub rebind_flag: &'static str,
    /// Where the value is published.
    pub tx: watch::Sender<Option<String>>,
}

/// How to run one child.
pub struct ChildSpec {
    /// `node/service`, the prefix of its log lines.
    pub label: String,
    /// The service kind (`mavsim`, `vas`, `fpma`...).
    pub kind: &'static str,
    /// The executable.
    pub program: PathBuf,
    /// Its arguments.
    pub args: Vec<String>,
    /// A value it announces on stdout, if any.
    pub announce: Option<Announce>,
    /// A rehearsed crash: the child is killed (SIGKILL) this long after its first start, and
    /// restarted as after any death.
    pub crash_after: Option<Duration>,
    /// Environment variables it is given besides the launcher's own.
    pub env: Vec<(String, String)>,
    /// When it is started again after it ends.
    pub restart: Restart,
    /// The mission cannot fly without it: when it cannot be kept running, the run ends. A
    /// service of the user's is not: it is reported, and the mission flies on.
    pub essential: bool,
}

impl ChildSpec {
    /// A `marea-gateway` reading `config`, essential and restarted whenever it ends.
    pub fn gateway(label: String, program: PathBuf, config: &std::path::Path) -> Self {
        Self {
            label,
            kind: "gateway",
            program,
            args: vec!["--config".into(), config.display().to_string()],
            announce: None,
            crash_after: None,
            env: Vec::new(),
            restart: Restart::Always,
            essential: true,
        }
    }
}

/// When a child that ended is started again (`<service restart>`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Restart {
    /// Whatever ended it (the built-in services: a service ending is a failure).
    Always,
    /// Only when it failed (an exit status other than 0, or a signal).
    OnFailure,
    /// Never: it runs once.
    Never,
}

impl Restart {
    /// Its name in a mission file.
    pub fn name(self) -> &'static str {
        match self {
            Restart::Always => "always",
            Restart::OnFailure => "on-failure",
            Restart::Never => "never",
        }
    }
}

/// What the supervisor tells the rest of the launcher.
#[derive(Clone, Debug)]
pub enum Notice {
    /// A child was started again after it died.
    Restarted {
        /// `node/service`.
        label: String,
        /// Service kind.
        kind: &'static str,
        /// Its new pid.
        pid: u32,
    },
    /// A child cannot be kept running.
    GaveUp {
        /// Why, naming the child.
        reason: String,
        /// Whether the mission needs it ([`ChildSpec::essential`]).
        essential: bool,
    },
}

/// The running children, stopped in reverse start order by [`Supervisor::shutdown`].
pub struct Supervisor {
    ui: Arc<Ui>,
    notices: broadcast::Sender<Notice>,
    children: Vec<(String, CancellationToken, JoinHandle<()>)>,
}

impl Supervisor {
    /// A supervisor with no children yet.
    pub fn new(ui: Arc<Ui>) -> Supervisor {
        Supervisor {
            ui,
            notices: broadcast::channel(64).0,
            children: Vec::new(),
        }
    }

    /// Notices from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Notice> {
        self.notices.subscribe()
    }

    /// Starts `spec` and keeps it running until [`Supervisor::shutdown`].
    pub fn start(&mut self, spec: ChildSpec) {
        let stop = CancellationToken::new();
        let label = spec.label.clone();
        let task = tokio::spawn(supervise(
            spec,
            self.ui.clone(),
            self.notices.clone(),
            stop.clone(),
        ));
        self.children.push((label, stop, task));
    }

    /// Stops every child, the last started first, each with SIGTERM then SIGKILL after a grace
    /// period, and waits for them all.
    pub async fn shutdown(self) {
        for (label, stop, task) in self.children.into_iter().rev() {
            stop.cancel();
            if task.await.is_err() {
                self.ui.note(
                    &format!("{label}: its supervising task failed"),
                    json!({"event": "error", "service": label, "reason": "supervisor task failed"}),
                );
            }
        }
    }
}

/// Has the kernel send the child SIGTERM when the launcher dies, however it dies: killed with
/// SIGKILL, it cannot stop its children itself, and they would fly on as orphans.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn stop_with_launcher(cmd: &mut Command) {
    let launcher = std::process::id();
    // SAFETY: the closure runs in the child between fork and exec and calls only
    // async-signal-safe functions (prctl, getppid, _exit): no lock, no allocation.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM as libc::c_ulong) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The launcher died before the request took effect: nobody would signal us.
            if libc::getppid() as u32 != launcher {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

/// A request to start a child, and where its outcome goes.
type SpawnRequest = (
    Command,
    tokio::sync::oneshot::Sender<std::io::Result<Child>>,
);

/// Starts `cmd` from the launcher's spawning thread. The kernel's parent-death signal follows
/// the thread that started the child, not the process, so children are all started from one
/// thread that lives as long as the launcher: a runtime's threads may come and go (a worker
/// handed over by `block_in_place`, the blocking pool's idle threads), and a child started on
/// one of them would be stopped when it ends.
async fn spawn(cmd: Command) -> std::io::Result<Child> {
    type Spawner = Option<std::sync::Mutex<std::sync::mpsc::Sender<SpawnRequest>>>;
    static SPAWNER: std::sync::OnceLock<Spawner> = std::sync::OnceLock::new();
    let gone = || std::io::Error::other("the launcher's spawning thread is gone");
    let spawner = SPAWNER.get_or_init(|| {
        let (tx, rx) = std::sync::mpsc::channel::<SpawnRequest>();
        let runtime = tokio::runtime::Handle::current();
        std::thread::Builder::new()
            .name("usal-spawner".into())
            .spawn(move || {
                // tokio's child handles register with the runtime they are made in.
                let _entered = runtime.enter();
                for (mut cmd, reply) in rx {
                    let _ = reply.send(cmd.spawn());
                }
            })
            .ok()
            .map(|_| std::sync::Mutex::new(tx))
    });
    let spawner = spawner.as_ref().ok_or_else(gone)?;
    let (reply, outcome) = tokio::sync::oneshot::channel();
    marea::sync::lock(spawner)
        .send((cmd, reply))
        .map_err(|_| gone())?;
    outcome.await.unwrap_or_else(|_| Err(gone()))
}

async fn supervise(
    mut spec: ChildSpec,
    ui: Arc<Ui>,
    notices: broadcast::Sender<Notice>,
    stop: CancellationToken,
) {
    let label = spec.label.clone();
    let mut restarts = 0u32;
    let mut quick_failures = 0u32;
    let mut backoff = BACKOFF_START;
    loop {
        let mut cmd = Command::new(&spec.program);
        cmd.args(&spec.args)
            .envs(spec.env.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .kill_on_drop(true);
        #[cfg(unix)]
        cmd.process_group(0);
        #[cfg(target_os = "linux")]
        stop_with_launcher(&mut cmd);
        if !ui.is_tty() {
            // tracing colours its output unless told not to; escapes do not belong in a log file.
            cmd.env("NO_COLOR", "1");
        }
        let started = Instant::now();
        let mut child = match spawn(cmd).await {
            Ok(c) => c,
            Err(e) => {
                let reason = format!("cannot start {}: {e}", spec.program.display());
                ui.note(
                    &format!("{label}: {reason}"),
                    json!({"event": "gave_up", "service": label, "reason": reason}),
                );
                let _ = notices.send(Notice::GaveUp {
                    reason,
                    essential: spec.essential,
                });
                return;
            }
        };
        let pid = child.id().unwrap_or(0);
        ui.note(
            &format!("{label} started (pid {pid})"),
            json!({"event": "started", "service": label, "kind": spec.kind, "pid": pid, "restarts": restarts}),
        );
        if restarts > 0 {
            let _ = notices.send(Notice::Restarted {
                label: label.clone(),
                kind: spec.kind,
                pid,
            });
        }
        let announce_tx = spec.announce.as_ref().map(|a| (a.prefix, a.tx.clone()));
        let out = child
            .stdout
            .take()
            .map(|s| tokio::spawn(forward(s, label.clone(), ui.clone(), announce_tx)));
        let err = child
            .stderr
            .take()
            .map(|s| tokio::spawn(forward(s, label.clone(), ui.clone(), None)));

        // The rehearsed crash, once: of the first run only.
        let crash = spec.crash_after.take();
        let exited = tokio::select! {
            s = child.wait() => Some(s),
            () = stop.cancelled() => None,
            () = async {
                match crash {
                    Some(after) => tokio::time::sleep(after).await,
                    None => std::future::pending().await,
                }
            } => {
                ui.note(
                    &format!("{label}: killed with SIGKILL, as the mission rehearses"),
                    json!({"event": "crash", "service": label, "pid": pid}),
                );
                let _ = child.start_kill();
                Some(child.wait().await)
            }
        };
        let status = match exited {
            Some(s) => s,
            None => {
                let how = terminate(&mut child).await;
                drain(out, err).await;
                ui.note(
                    &format!("{label} stopped ({how})"),
                    json!({"event": "stopped", "service": label, "pid": pid, "how": how}),
                );
                return;
            }
        };
        drain(out, err).await;
        let succeeded = status.as_ref().is_ok_and(ExitStatus::success);
        let status = match status {
            Ok(s) => describe(s),
            Err(e) => format!("wait failed: {e}"),
        };
        if spec.restart == Restart::Never || (spec.restart == Restart::OnFailure && succeeded) {
            ui.note(
                &format!(
                    "{label} {status}; not restarted (restart=\"{}\")",
                    spec.restart.name()
                ),
                json!({"event": "ended", "service": label, "pid": pid, "status": status}),
            );
            return;
        }
        if started.elapsed() >= STABLE {
            quick_failures = 0;
            backoff = BACKOFF_START;
        }
        quick_failures += 1;
        if quick_failures > MAX_QUICK_FAILURES {
            let reason = format!(
                "{label} {status}; it failed {MAX_QUICK_FAILURES} times in a row, giving up"
            );
            ui.note(
                &reason,
                json!({"event": "gave_up", "service": label, "reason": reason}),
            );
            let _ = notices.send(Notice::GaveUp {
                reason,
                essential: spec.essential,
            });
            return;
        }
        restarts += 1;
        ui.note(
            &format!("{label} {status}; restarting in {backoff:.1?} (restart {restarts})"),
            json!({"event": "exited", "service": label, "pid": pid, "status": status, "restart_in_ms": backoff.as_millis() as u64}),
        );
        tokio::select! {
            () = tokio::time::sleep(backoff) => {}
            () = stop.cancelled() => return,
        }
        backoff = (backoff * 2).min(BACKOFF_MAX);
        if let Some(a) = &spec.announce {
            // A restarted child gets the address its peers were given.
            if let Some(v) = a.tx.borrow().clone() {
                if let Some(i) = spec.args.iter().position(|x| x == a.rebind_flag) {
                    if let Some(slot) = spec.args.get_mut(i + 1) {
                        *slot = v;
                    }
                }
            }
        }
    }
}

/// Copies a child's output lines to the launcher's stderr, with its label.
async fn forward(
    stream: impl AsyncRead + Unpin,
    label: String,
    ui: Arc<Ui>,
    announce: Option<(&'static str, watch::Sender<Option<String>>)>,
) {
    let mut lines = BufReader::new(stream).lines();
    // A read error ends the stream like EOF: the child is gone or its pipe broken either way.
    while let Ok(Some(line)) = lines.next_line().await {
        if let Some((prefix, tx)) = &announce {
            if let Some(v) = line.strip_prefix(prefix) {
                tx.send_replace(Some(v.trim().to_owned()));
            }
        }
        ui.child_line(&label, &line);
    }
}

/// Waits a little for the last lines of a child that exited.
async fn drain(out: Option<JoinHandle<()>>, err: Option<JoinHandle<()>>) {
    for h in [out, err].into_iter().flatten() {
        // A grandchild holding the pipe open must not hold up the supervisor.
        let _ = tokio::time::timeout(Duration::from_secs(1), h).await;
    }
}

/// SIGTERM, then SIGKILL after [`GRACE`]; says which ended the child.
async fn terminate(child: &mut Child) -> String {
    // `id()` is None once the child has been reaped: then there is nothing to signal and the pid
    // may already belong to another process.
    let Some(pid) = child.id() else {
        return "had already exited".into();
    };
    let termed = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .await
        .is_ok_and(|s| s.success());
    if termed {
        if let Ok(Ok(s)) = tokio::time::timeout(GRACE, child.wait()).await {
            return format!("SIGTERM, {}", describe(s));
        }
    }
    let _ = child.kill().await;
    if termed {
        format!("SIGKILL after {GRACE:?}")
    } else {
        "SIGKILL".into()
    }
}

fn describe(s: ExitStatus) -> String {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if let Some(sig) = s.signal() {
            return format!("killed by signal {sig}");
        }
    }
    match s.code() {
        Some(c) => format!("exited with status {c}"),
        None => "exited".into(),
    }
}

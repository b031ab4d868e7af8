//! Child processes for cross-process tests: started with their JSON lines read on a thread,
//! waited for with deadlines, killed and reaped when dropped so no test leaves one behind.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

/// A child process whose stdout lines are parsed as JSON (other lines are echoed to stderr,
/// tagged with its name), killed and reaped on drop.
pub struct Proc {
    /// The name its lines and failures are tagged with.
    pub name: String,
    child: Child,
    lines: mpsc::Receiver<Value>,
    /// Every line read so far.
    pub seen: Vec<Value>,
}

impl Proc {
    /// Starts `program` with `args`; stdin closed, stderr the test's.
    ///
    /// # Panics
    /// When it cannot start.
    pub fn spawn(name: &str, program: &str, args: &[String]) -> Proc {
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {program}: {e}"));
        let stdout = child.stdout.take().expect("stdout is piped");
        let (tx, rx) = mpsc::channel();
        let tag = name.to_owned();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str::<Value>(&line) {
                    Ok(v) => {
                        if tx.send(v).is_err() {
                            break;
                        }
                    }
                    Err(_) => eprintln!("[{tag}] {line}"),
                }
            }
        });
        Proc {
            name: name.to_owned(),
            child,
            lines: rx,
            seen: Vec::new(),
        }
    }

    /// Waits for a line satisfying `pred`, failing the test after `timeout`.
    ///
    /// # Panics
    /// When none comes in time (naming `what` and the lines seen).
    pub fn expect(
        &mut self,
        timeout: Duration,
        what: &str,
        pred: impl Fn(&Value) -> bool,
    ) -> Value {
        self.try_expect(timeout, pred).unwrap_or_else(|| {
            panic!(
                "{}: no line with {what} within {timeout:?}; saw {:?}",
                self.name, self.seen
            )
        })
    }

    /// Waits up to `timeout` for a line satisfying `pred`; `None` when none came (the lines
    /// that did come are kept in `seen`).
    pub fn try_expect(
        &mut self,
        timeout: Duration,
        pred: impl Fn(&Value) -> bool,
    ) -> Option<Value> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) => {
                    self.seen.push(v.clone());
                    if pred(&v) {
                        return Some(v);
                    }
                }
                Err(_) => return None,
            }
        }
    }

    /// Waits for a line having key `key`.
    ///
    /// # Panics
    /// As [`Proc::expect`].
    pub fn expect_key(&mut self, timeout: Duration, key: &str) -> Value {
        self.expect(timeout, key, |v| v.get(key).is_some())
    }

    /// Waits for the process to exit.
    ///
    /// # Panics
    /// When it has not exited after `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + timeout;
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return s;
            }
            if Instant::now() >= deadline {
                panic!("{} did not exit within {timeout:?}", self.name);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Collects every line left once the process exited and its stdout closed.
    pub fn drain(&mut self) {
        while let Ok(v) = self.lines.recv_timeout(Duration::from_secs(5)) {
            self.seen.push(v);
        }
    }

    /// Kills it (SIGKILL) and reaps it.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Asks it to stop (SIGTERM), without waiting.
    pub fn terminate(&mut self) {
        // SIGTERM lets the node say Bye.
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The outcome line of a `marea-probe` `call` (`ok` or `error`) or `send` (`done` or
/// `error`), waited for up to `within`.
///
/// # Panics
/// When none comes in time.
pub fn outcome_within(p: &mut Proc, within: Duration) -> Value {
    p.expect(within, "an outcome", |v| {
        v.get("ok").is_some() || v.get("done").is_some() || v.get("error").is_some()
    })
}

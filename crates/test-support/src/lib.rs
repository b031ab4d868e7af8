//! What the cross-process tests of every package share (a dev-dependency only).
//!
//! The services those tests start (`vas`, `mavsim`, `fpma`, `usal-router`, ...) are built by
//! one cargo command, the same for every test and the one the README's test command runs
//! first, so the first test to ask finds them built and no test waits on a compile:
//! - one selection ([`SERVICE_BUILD`]): cargo unifies features per selection, so a narrower
//!   `-p` list would compile marea and the services once more with other features;
//! - without the variables cargo sets for a test process (`CARGO_MANIFEST_DIR`,
//!   `CARGO_PKG_NAME`, ...): build scripts that read them (ring's does) are rerun when they
//!   change, and everything above them (rustls, Zenoh, marea, every service) is compiled again,
//!   test after test, each from another package's directory.

pub mod layering;
pub mod process;

/// A UDP port for a test's multicast group, from `key` (a hash of the test's name, or the
/// process id): in 20000..32000, below the kernel's ephemeral range (32768-60999 on Linux), so
/// no socket the system hands out meanwhile holds it without SO_REUSEADDR (a join then fails
/// with "Address already in use"). Tests sharing a port are kept apart by their domains.
pub fn multicast_port(key: u64) -> u16 {
    20_000 + (key % 12_000) as u16
}

/// A UDP port free on loopback a moment ago, for a child process to bind (the kernel hands
/// ports out in turn, so it is not handed out again soon). For a port the test binds itself,
/// bind port 0 instead.
///
/// # Panics
/// When no socket can be bound at all.
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .expect("a free UDP port")
}

/// [`free_udp_port`] for TCP.
///
/// # Panics
/// When no socket can be bound at all.
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free TCP port")
}

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

/// Whether the tests run under CI (`CI` set to anything but empty, `0` or `false`), where
/// `.ci/run` installed every tool a test needs.
pub fn under_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && !v.eq_ignore_ascii_case("false"))
}

/// A tool a test needs (`what`) is missing; `install` says how to get it. Under CI the test
/// fails here: a missing tool there is a broken install step, and a test that skips would pass
/// without testing anything. Elsewhere the test is skipped, saying so (the caller returns).
///
/// # Panics
/// Under CI, always.
pub fn tool_missing(what: &str, install: &str) {
    assert!(
        !under_ci(),
        "{what} is missing under CI, where `.ci/run` installs it ({install})"
    );
    eprintln!("SKIPPED: {what} is missing ({install})");
}

/// The services' build: every binary of the workspace but `usal`'s own (the test build makes
/// those).
pub const SERVICE_BUILD: [&str; 5] = ["build", "--workspace", "--exclude", "usal", "--bins"];

/// Variables cargo sets for the processes it runs, which a cargo started from a test must not
/// inherit (prefixes and names).
const CARGO_SET_PREFIXES: [&str; 4] = ["CARGO_PKG_", "CARGO_BIN_EXE_", "CARGO_CFG_", "NEXTEST_"];
const CARGO_SET: [&str; 9] = [
    "CARGO_MANIFEST_DIR",
    "CARGO_MANIFEST_PATH",
    "CARGO_MANIFEST_LINKS",
    "CARGO_CRATE_NAME",
    "CARGO_BIN_NAME",
    "CARGO_PRIMARY_PACKAGE",
    "CARGO_TARGET_TMPDIR",
    "CARGO_RUSTC_CURRENT_DIR",
    "OUT_DIR",
];

/// The workspace's root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The target directory of the running test binary (`<target>/<profile>/deps/<test>`).
pub fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    exe.ancestors()
        .nth(3)
        .expect("test binary inside <target>/<profile>/deps")
        .to_owned()
}

/// Builds the services into `target` ([`SERVICE_BUILD`]), once per test process; returns
/// `<target>/debug`, where they are.
///
/// # Panics
/// When cargo cannot run or the build fails: the test cannot go on.
pub fn build_services(target: &Path) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| cargo(&SERVICE_BUILD, target));
    target.join("debug")
}

/// `<target>/debug/<bin>`, a binary of the `usal` package (`marea-radio`, `marea-probe`): the
/// workspace's test build makes them; a test run of one package alone builds it here.
///
/// # Panics
/// When it is missing and cannot be built.
pub fn usal_bin(target: &Path, bin: &str) -> PathBuf {
    let path = target.join("debug").join(bin);
    if !path.is_file() {
        cargo(&["build", "-p", "usal", "--bin", bin], target);
    }
    path
}

/// A binary of the workspace (`vas`, `mavsim`, `fpma`, `marea-radio`...), built once per test
/// process into the running test's target directory: the services' build ([`build_services`]),
/// or the `usal` package's own binaries ([`usal_bin`]).
///
/// # Panics
/// When it is not there once built.
pub fn workspace_bin(bin: &str) -> PathBuf {
    let target = target_dir();
    let service = build_services(&target).join(bin);
    let path = if service.is_file() {
        service
    } else {
        usal_bin(&target, bin)
    };
    assert!(path.is_file(), "no {bin} at {}", path.display());
    path
}

/// Stops a child process: kills it and reaps it, waiting 20 s at most.
pub async fn stop(child: &mut tokio::process::Child) {
    let _ = child.start_kill();
    let _ = tokio::time::timeout(std::time::Duration::from_secs(20), child.wait()).await;
}

/// Runs cargo with `args` into `target`, from the workspace's root, without the variables
/// cargo set for this test process.
fn cargo(args: &[&str], target: &Path) {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.args(args)
        .current_dir(workspace_root())
        .env("CARGO_TARGET_DIR", target);
    for (name, _) in std::env::vars_os() {
        let Some(n) = name.to_str() else { continue };
        if CARGO_SET.contains(&n) || CARGO_SET_PREFIXES.iter().any(|p| n.starts_with(p)) {
            cmd.env_remove(&name);
        }
    }
    let status = cmd.status().expect("running cargo");
    assert!(status.success(), "cargo {} failed", args.join(" "));
}

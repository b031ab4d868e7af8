//! `usal router`: runs `usal-router`, the Zenoh router USAL systems meet through beyond one LAN.
//! It is a binary of its own so that Zenoh stays out of `usal`'s build; like the services a
//! mission starts, it is built once, saying so, the first time it is asked for.

use std::os::unix::process::CommandExt;
use std::process::ExitCode;

use super::ui::Ui;

/// Runs `usal-router` with `args` in place of this process (signals reach it directly).
pub fn main(args: &[String], json: bool) -> ExitCode {
    let ui = Ui::new(json);
    let bins = match super::find_or_build(&["usal-router"], &[], &ui) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("usal: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let mut cmd = std::process::Command::new(bins.path("usal-router"));
    cmd.args(args);
    if json {
        cmd.arg("--json");
    }
    let err = cmd.exec();
    eprintln!(
        "usal: cannot run {}: {err}",
        bins.path("usal-router").display()
    );
    ExitCode::FAILURE
}

//! What the daemon shares with the `moonhaul` CLI's mission tools and evaluation: their
//! `tracing` set-up, the async runtime, signal handling, the wall clock and the loading of
//! phase policies.

use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context, Result};
use moonhaul_core::observation::check_layout;
use moonhaul_core::policy::Policy;
use moonhaul_core::state::Phase;

use crate::tick::{unit_action_map, PhasePolicies};

/// `tracing` to stderr, level from `RUST_LOG` (default info): the daemon's and the mission
/// tools' logs.
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The async runtime the daemon and the mission tools run on: two workers, timers and I/O.
pub fn runtime() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
}

/// SIGINT and SIGTERM, caught from the moment [`Signals::install`] returns: a signal that
/// arrives while a process is still setting up is kept and taken at its first wait, so it
/// still ends in a hold and a finished log. Install it first thing.
pub struct Signals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl Signals {
    /// Needs a tokio runtime with its signal driver (see [`runtime`]).
    pub fn install() -> Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Signals {
            interrupt: signal(SignalKind::interrupt()).context("installing the SIGINT handler")?,
            terminate: signal(SignalKind::terminate()).context("installing the SIGTERM handler")?,
        })
    }

    /// The next signal: "SIGINT" or "SIGTERM".
    pub async fn recv(&mut self) -> &'static str {
        tokio::select! {
            _ = self.interrupt.recv() => "SIGINT",
            _ = self.terminate.recv() => "SIGTERM",
        }
    }
}

/// `phase`'s policy file in a policies folder: `lift.safetensors`, …
pub fn policy_file(folder: &Path, phase: Phase) -> PathBuf {
    folder.join(format!("{phase}.safetensors"))
}

/// Loads a phase policy and checks it is one a unit runs for `phase`: its phase, its
/// observation layout, its action map (the increment, this build's version) and its sizes.
pub fn load_policy(path: &Path, phase: Phase) -> Result<Policy> {
    let policy =
        Policy::from_file(path).with_context(|| format!("loading policy {}", path.display()))?;
    let meta = policy.metadata();
    if meta.phase != phase {
        bail!(
            "policy {} drives {}, not {}",
            path.display(),
            meta.phase,
            phase
        );
    }
    check_layout(&meta.extra).with_context(|| format!("policy {}", path.display()))?;
    unit_action_map(phase, &policy).with_context(|| format!("policy {}", path.display()))?;
    Ok(policy)
}

/// The three phase policies of a folder (`lift.safetensors`, …).
pub fn load_policies(folder: &Path) -> Result<PhasePolicies> {
    let load = |phase: Phase| load_policy(&policy_file(folder, phase), phase);
    Ok(PhasePolicies {
        lift: load(Phase::Lift)?,
        transport: load(Phase::Transport)?,
        place: load(Phase::Place)?,
    })
}

/// The system clock in µs since the Unix epoch (the team clock of units on real hardware).
pub fn wall_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use moonhaul_core::config::repo_file;

    /// A unit refuses a policy trained on observation layout 2 (the bundled lift before layout
    /// 3, kept as it was), naming the file and both layouts, before it flies anything.
    #[test]
    fn a_layout_2_policy_file_is_refused_by_name() {
        let path = repo_file("tests/data/lift_layout2.safetensors");
        let err = format!("{:#}", load_policy(&path, Phase::Lift).unwrap_err());
        assert!(err.contains("lift_layout2.safetensors"), "{err}");
        assert!(
            err.contains("observation layout") && err.contains("version 2"),
            "{err}"
        );
        assert!(err.contains(&format!(
            "version {}",
            moonhaul_core::observation::OBS_LAYOUT_VERSION
        )));
    }
}

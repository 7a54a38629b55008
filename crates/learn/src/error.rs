//! The library's one error type: every way training input (a config, a checkpoint, an
//! environment's output) can be wrong has its own variant naming what is at fault.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum LearnError {
    /// Reading or writing a file failed.
    #[error("cannot access {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file the trainer reads back (a run log) is missing, not a file, or too large.
    #[error(transparent)]
    Input(#[from] moonhaul_core::input::InputError),
    /// A training config cannot be read, parsed or validated.
    #[error(transparent)]
    Config(#[from] moonhaul_core::config::ConfigError),
    /// A config value parses but is out of range.
    #[error("config field `{field}` is invalid: {reason}")]
    InvalidConfig { field: String, reason: String },
    /// The simulated world cannot be built or stepped.
    #[error(transparent)]
    Sim(#[from] moonhaul_sim::SimError),
    #[error(transparent)]
    HandOvers(#[from] moonhaul_sim::handover::HandOverFileError),
    /// A batch passed to an environment has the wrong length.
    #[error("{what} has {found} values, expected {expected}")]
    Shape {
        what: &'static str,
        expected: usize,
        found: usize,
    },
    /// Expert labels were asked of an environment that cannot give them (a task without a
    /// scripted expert, or a phase task built without a mission plan), or in a way that would
    /// desynchronise its stateful scripts.
    #[error("no expert labels: {reason}")]
    NoExpert { reason: String },
    /// An environment or the learner produced NaN or infinity.
    #[error("{what} is not finite")]
    NonFinite { what: String },
    /// A checkpoint file is not one this build wrote, or does not fit the model.
    #[error("checkpoint {} is unusable: {reason}", path.display())]
    Checkpoint { path: PathBuf, reason: String },
    /// An existing `metrics.csv` to resume cannot be read back.
    #[error("{}:{line}: {reason}", path.display())]
    Metrics {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    /// Drawing a learning curve failed.
    #[error("cannot draw {}: {reason}", path.display())]
    Plot { path: PathBuf, reason: String },
    /// libtorch reported an error.
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    /// The exported policy was rejected by the onboard runtime's validation.
    #[error(transparent)]
    Policy(#[from] moonhaul_core::policy::PolicyError),
}

/// Each environment error becomes the variant of the same name, so callers (and their tests)
/// see an environment's error as they did when the environments lived in this crate.
impl From<moonhaul_env::EnvError> for LearnError {
    fn from(e: moonhaul_env::EnvError) -> Self {
        use moonhaul_env::EnvError;
        match e {
            EnvError::Config(e) => LearnError::Config(e),
            EnvError::InvalidConfig { field, reason } => {
                LearnError::InvalidConfig { field, reason }
            }
            EnvError::Sim(e) => LearnError::Sim(e),
            EnvError::HandOvers(e) => LearnError::HandOvers(e),
            EnvError::Shape {
                what,
                expected,
                found,
            } => LearnError::Shape {
                what,
                expected,
                found,
            },
            EnvError::NoExpert { reason } => LearnError::NoExpert { reason },
            EnvError::NonFinite { what } => LearnError::NonFinite { what },
            EnvError::Input(e) => LearnError::Input(e),
            EnvError::Policy(e) => LearnError::Policy(e),
        }
    }
}

impl LearnError {
    pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| LearnError::Io { path, source }
    }
}

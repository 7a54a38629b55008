//! The environments' one error type: every way an environment's input (a config, a hand-over
//! file, a batch handed to it) can be wrong has its own variant naming what is at fault.
//! `moonhaul_learn::LearnError` converts each variant into its own of the same name, so a
//! trainer reports an environment's error exactly as it did when the environments lived there.

#[derive(Debug, thiserror::Error)]
pub enum EnvError {
    /// A config cannot be read, parsed or validated.
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
    /// A file the environment reads (a config named by another, for its digest) is missing,
    /// not a file, or too large.
    #[error(transparent)]
    Input(#[from] moonhaul_core::input::InputError),
    /// An exported actor does not make a valid onboard policy (shapes, non-finite values).
    #[error(transparent)]
    Policy(#[from] moonhaul_core::policy::PolicyError),
    /// An environment was given, or produced, NaN or infinity.
    #[error("{what} is not finite")]
    NonFinite { what: String },
}

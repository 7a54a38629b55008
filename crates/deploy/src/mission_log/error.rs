//! What can go wrong writing or reading a mission log.

use std::io;
use std::path::PathBuf;

use moonhaul_core::input::InputError;

/// Why a mission log could not be written or read; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("cannot create mission log {}: {error}", path.display())]
    Create { path: PathBuf, error: String },
    #[error("cannot write mission log {}: {error}", path.display())]
    Write { path: PathBuf, error: String },
    #[error(
        "mission log {}: frame of tick {tick} has {bases} base poses, {orientations} base \
         orientations, {wheels} wheel and {arms} arm joint sets and {phases} unit phases; the \
         log is of a team of {units}",
        path.display()
    )]
    FrameShape {
        path: PathBuf,
        tick: u64,
        bases: usize,
        orientations: usize,
        wheels: usize,
        arms: usize,
        phases: usize,
        units: usize,
    },
    #[error("mission log: unit model {}: {error}", path.display())]
    Model { path: PathBuf, error: String },
    #[error(transparent)]
    Input(#[from] InputError),
    // The I/O error is part of the message, not a `source`, so a chain prints it once.
    #[error("cannot read mission log {}: {error}", path.display())]
    Read { path: PathBuf, error: io::Error },
    #[error("{} is not a valid MCAP mission log: record {record}: {reason}", path.display())]
    Corrupt {
        path: PathBuf,
        /// 1-based index of the record (counting those inside chunks) at fault.
        record: usize,
        reason: String,
    },
    #[error(
        "mission log {}: message {message} on {topic} (record {record}) is not a {kind}: {error}",
        path.display()
    )]
    BadMessage {
        path: PathBuf,
        topic: String,
        /// 1-based index of the message on its topic.
        message: usize,
        record: usize,
        kind: &'static str,
        error: String,
    },
    #[error("{} is not a {kind} log: it has no {expected} channel (topics: {topics:?})", path.display())]
    WrongKind {
        path: PathBuf,
        kind: &'static str,
        expected: String,
        topics: Vec<String>,
    },
}

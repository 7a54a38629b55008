//! What a log carries besides its records: the unit model it draws `/tf` with, and the run's
//! input files (that URDF and the configs) as MCAP attachments, so a log says what it was
//! recorded with.

use std::path::{Path, PathBuf};
use std::time::UNIX_EPOCH;

use moonhaul_core::input::{
    read_capped, read_capped_text, MAX_CONFIG_BYTES, MAX_POLICY_BYTES, MAX_URDF_BYTES,
};
use moonhaul_core::kinematics::{parse_urdf, KinematicTree};
use moonhaul_core::unit::UnitSpec;

use super::LogError;

/// One input file as the log attaches it.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Attachment {
    /// The path as the run was given it.
    pub(super) name: String,
    pub(super) media_type: &'static str,
    /// Last modification, ns since the Unix epoch (0 where the file system has none).
    pub(super) modified_ns: u64,
    pub(super) data: Vec<u8>,
}

/// The unit model and the attachments of a log, read before the log file is created.
pub struct LogInputs {
    pub(super) tree: KinematicTree,
    pub(super) spec: UnitSpec,
    /// The URDF first, then the configs in the order given, then any policy files.
    pub(super) attachments: Vec<Attachment>,
    /// What flew the unit (`scripted`, `learned`), the log's `controller` metadata; `None`
    /// for a log of no controller (a world's).
    pub(super) controller: Option<&'static str>,
}

impl LogInputs {
    /// Reads the unit URDF at `urdf` (what `/tf` is computed with) and each of `configs`
    /// (at most [`MAX_CONFIG_BYTES`] each); errors name the file.
    pub fn read(urdf: &Path, configs: &[PathBuf]) -> Result<Self, LogError> {
        let text = read_capped_text(urdf, MAX_URDF_BYTES)?;
        let model_error = |error: String| LogError::Model {
            path: urdf.to_owned(),
            error,
        };
        let robot = parse_urdf(&text).map_err(|e| model_error(e.to_string()))?;
        let tree = KinematicTree::from_robot(&robot).map_err(|e| model_error(e.to_string()))?;
        let spec = UnitSpec::from_robot(&robot).map_err(|e| model_error(e.to_string()))?;
        let mut attachments = vec![attachment(urdf, text.into_bytes())];
        for path in configs {
            attachments.push(attachment(path, read_capped(path, MAX_CONFIG_BYTES)?));
        }
        Ok(LogInputs {
            tree,
            spec,
            attachments,
            controller: None,
        })
    }

    /// Records what flies the unit as the log's `controller` metadata, and attaches the
    /// policy files it flies (at most [`MAX_POLICY_BYTES`] each), so a log says which
    /// policies a learned mission ran.
    pub fn flown_by(
        mut self,
        controller: &'static str,
        policies: &[PathBuf],
    ) -> Result<Self, LogError> {
        self.controller = Some(controller);
        for path in policies {
            self.attachments
                .push(attachment(path, read_capped(path, MAX_POLICY_BYTES)?));
        }
        Ok(self)
    }
}

fn attachment(path: &Path, data: Vec<u8>) -> Attachment {
    let media_type = match path.extension().and_then(|e| e.to_str()) {
        Some("urdf" | "xml") => "application/xml",
        Some("toml") => "application/toml",
        Some("json") => "application/json",
        _ => "application/octet-stream",
    };
    let modified_ns = std::fs::metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    Attachment {
        name: path.display().to_string(),
        media_type,
        modified_ns,
        data,
    }
}

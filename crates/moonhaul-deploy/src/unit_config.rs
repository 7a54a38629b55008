//! A unit's daemon settings, read from `configs/unit.toml` (one file per robot, flashed with
//! the daemon).

use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `configs/unit.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitConfig {
    /// This unit's index in the team, 0-based; peers and the stacked state use it.
    pub unit_index: usize,
    /// Number of units in the team (the paper's N = 2).
    pub team_size: usize,
    /// Team name: messages from another team are rejected.
    pub team: String,
    /// Control loop rate, Hz (paper: 50).
    pub control_rate_hz: f64,
    /// A peer whose newest state is older than this many control periods stops every unit.
    pub peer_staleness_periods: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum UnitConfigError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Parse {
        path: PathBuf,
        source: Box<toml::de::Error>,
    },
    #[error("{path}: field {field}: {reason}")]
    Invalid {
        path: PathBuf,
        field: &'static str,
        reason: String,
    },
}

impl UnitConfig {
    /// Reads and validates a unit config; errors name the file and the field.
    pub fn from_file(path: &Path) -> Result<Self, UnitConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| UnitConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        let config: UnitConfig = toml::from_str(&text).map_err(|e| UnitConfigError::Parse {
            path: path.to_owned(),
            source: Box::new(e),
        })?;
        config
            .validate()
            .map_err(|(field, reason)| UnitConfigError::Invalid {
                path: path.to_owned(),
                field,
                reason,
            })?;
        Ok(config)
    }

    fn validate(&self) -> Result<(), (&'static str, String)> {
        if self.team_size == 0 {
            return Err(("team_size", "a team needs at least one unit".into()));
        }
        if self.unit_index >= self.team_size {
            return Err((
                "unit_index",
                format!(
                    "{} is not below team_size {}",
                    self.unit_index, self.team_size
                ),
            ));
        }
        if self.team.trim().is_empty() {
            return Err(("team", "must not be empty".into()));
        }
        if !(self.control_rate_hz.is_finite() && self.control_rate_hz > 0.0) {
            return Err((
                "control_rate_hz",
                format!("{} must be finite and > 0", self.control_rate_hz),
            ));
        }
        if self.peer_staleness_periods == 0 {
            return Err(("peer_staleness_periods", "must be at least 1".into()));
        }
        Ok(())
    }

    /// One control period.
    pub fn control_period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.control_rate_hz)
    }

    /// Age beyond which a peer's state is stale.
    pub fn peer_staleness(&self) -> Duration {
        self.control_period() * self.peer_staleness_periods
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/unit.toml")
    }

    #[test]
    fn shipped_config_is_valid_with_papers_rate() {
        let config = UnitConfig::from_file(&shipped()).unwrap();
        assert_eq!(config.control_period(), Duration::from_millis(20));
        assert_eq!(config.peer_staleness(), Duration::from_millis(60));
        assert_eq!(config.team_size, 2);
    }

    #[test]
    fn bad_configs_name_file_and_field() {
        let good = std::fs::read_to_string(shipped()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (
                good.replace("unit_index = 0", "unit_index = 2"),
                "unit_index",
            ),
            (
                good.replace("control_rate_hz = 50.0", "control_rate_hz = 0.0"),
                "control_rate_hz",
            ),
            (
                good.replace("peer_staleness_periods = 3", "peer_staleness_periods = 0"),
                "peer_staleness_periods",
            ),
            (format!("{good}\nspeed = 3\n"), "speed"),
            (good.replace("team = \"moonhaul\"", ""), "team"),
        ];
        for (i, (text, field)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("unit{i}.toml"));
            std::fs::write(&path, text).unwrap();
            let message = UnitConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains(&format!("unit{i}.toml")),
                "{message}"
            );
        }
    }
}

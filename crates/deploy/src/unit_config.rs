//! A unit's daemon settings, read from `configs/unit.toml` (one file per robot, flashed with
//! the daemon).

use moonhaul_coord::config::{check, load, positive, ConfigError, InvalidConfig, Validate};
use moonhaul_coord::TeamSettings;
use serde::Deserialize;
use std::path::Path;
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

impl Validate for UnitConfig {
    /// The rate here; team membership and staleness by [`TeamSettings::validate`], the one
    /// check the coordination layer also relies on.
    fn validate(&self) -> Result<(), InvalidConfig> {
        check(
            "control_rate_hz",
            self.control_rate_hz,
            "finite and > 0",
            positive,
        )?;
        self.team_settings().validate()?;
        Ok(())
    }
}

impl UnitConfig {
    /// Reads and validates a unit config; errors name the file and the field.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        load(path)
    }

    /// What the coordination layer needs of this config.
    pub fn team_settings(&self) -> TeamSettings {
        TeamSettings {
            team: self.team.clone(),
            team_size: self.team_size,
            unit_index: self.unit_index,
            control_period_us: (1e6 / self.control_rate_hz).round() as u64,
            peer_staleness_periods: self.peer_staleness_periods,
        }
    }

    /// One control period.
    pub fn control_period(&self) -> Duration {
        Duration::from_micros(self.team_settings().control_period_us)
    }

    /// Age beyond which a peer's state is stale.
    pub fn peer_staleness(&self) -> Duration {
        Duration::from_micros(self.team_settings().staleness_us())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

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

//! A unit's CAN drive configuration (`configs/unit_can.toml`): bus timing, and per drive the
//! joint it moves, its node id, mode of operation and the counts ↔ rad conversion.

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::time::Duration;

use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use serde::Deserialize;

use super::cia402::OperationMode;

/// Why a unit CAN config cannot be used; every variant names the file, validation errors also
/// the field.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {source}", path.display())]
    Parse {
        path: PathBuf,
        #[source]
        source: toml::de::Error,
    },
    #[error("{}: field `{field}`: {reason}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        reason: String,
    },
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitCanConfig {
    /// SocketCAN interface name, e.g. `can0`.
    pub interface: String,
    /// SYNC period = control period, s.
    pub sync_period_s: f64,
    /// Heartbeat producer time written to each drive's 0x1017, ms.
    pub heartbeat_producer_ms: u16,
    /// A drive silent for longer is faulted, s.
    pub heartbeat_timeout_s: f64,
    /// A drive that sends no TPDO for longer while operational is faulted, s.
    pub feedback_timeout_s: f64,
    /// An SDO request without reply for longer fails, s.
    pub sdo_timeout_s: f64,
    /// Enable, disable and fault reset fail when drives need longer, s.
    pub state_change_timeout_s: f64,
    /// Left, right.
    pub wheels: [DriveConfig; WHEEL_JOINTS],
    /// Base to tip.
    pub arm: [DriveConfig; ARM_JOINTS],
    /// Behaviour of the emulated drives (`moonhaul can emulate`, tests); ignored on real buses.
    pub emulator: EmulatorConfig,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    /// Joint name, as in the URDF.
    pub joint: String,
    /// CANopen node id, 1–127.
    pub node_id: u8,
    /// `csv` for wheels, `csp` for arm joints.
    pub mode: OperationMode,
    /// Encoder counts per motor revolution.
    pub counts_per_rev: u32,
    /// Motor revolutions per joint revolution.
    pub gear_ratio: f64,
    pub direction: Direction,
    /// Motor rated torque (0x6076), N·m; the torque feedback (‰ of it) becomes effort when set.
    pub rated_torque_nm: Option<f64>,
}

/// Whether positive motor counts turn the joint in its positive URDF direction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    Normal,
    Inverted,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmulatorConfig {
    /// First-order time constant of the emulated motor's velocity (CSV) or position (CSP), s.
    pub time_constant_s: f64,
    /// Joint-side inertia for the emulated torque feedback, kg·m².
    pub inertia_kgm2: f64,
    /// Time step the virtual bus advances its clock and the emulated motors by, s.
    pub step_s: f64,
}

impl UnitCanConfig {
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml(&text, path)
    }

    /// Parses and validates; `path` only names the source in errors.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let config: UnitCanConfig = toml::from_str(text).map_err(|source| ConfigError::Parse {
            path: path.to_owned(),
            source,
        })?;
        config
            .validate()
            .map_err(|(field, reason)| ConfigError::Invalid {
                path: path.to_owned(),
                field,
                reason,
            })?;
        Ok(config)
    }

    /// Wheels then arm: the order of the nine drives everywhere in this crate.
    pub fn drives(&self) -> impl Iterator<Item = &DriveConfig> {
        self.wheels.iter().chain(&self.arm)
    }

    pub fn sync_period(&self) -> Duration {
        Duration::from_secs_f64(self.sync_period_s)
    }

    fn validate(&self) -> Result<(), (String, String)> {
        let positive = |field: &str, value: f64| {
            if value > 0.0 && Duration::try_from_secs_f64(value).is_ok() {
                Ok(())
            } else {
                Err((
                    field.to_owned(),
                    format!("must be a positive number of seconds, got {value}"),
                ))
            }
        };
        positive("sync_period_s", self.sync_period_s)?;
        positive("heartbeat_timeout_s", self.heartbeat_timeout_s)?;
        positive("feedback_timeout_s", self.feedback_timeout_s)?;
        positive("sdo_timeout_s", self.sdo_timeout_s)?;
        positive("state_change_timeout_s", self.state_change_timeout_s)?;
        positive("emulator.time_constant_s", self.emulator.time_constant_s)?;
        positive("emulator.step_s", self.emulator.step_s)?;
        if !(self.emulator.inertia_kgm2.is_finite() && self.emulator.inertia_kgm2 >= 0.0) {
            return Err(("emulator.inertia_kgm2".into(), "must be ≥ 0".into()));
        }
        if self.heartbeat_producer_ms == 0
            || f64::from(self.heartbeat_producer_ms) / 1000.0 >= self.heartbeat_timeout_s
        {
            return Err((
                "heartbeat_producer_ms".into(),
                "must be positive and shorter than heartbeat_timeout_s".into(),
            ));
        }
        let mut seen = [false; 128];
        let sides = [
            ("wheels", &self.wheels[..], OperationMode::Csv),
            ("arm", &self.arm[..], OperationMode::Csp),
        ];
        for (side, drives, mode) in sides {
            for (i, drive) in drives.iter().enumerate() {
                let field = |name: &str| format!("{side}[{i}].{name}");
                if !(1..=127).contains(&drive.node_id) {
                    return Err((
                        field("node_id"),
                        format!("{} is not in 1..=127", drive.node_id),
                    ));
                }
                if std::mem::replace(&mut seen[usize::from(drive.node_id)], true) {
                    return Err((
                        field("node_id"),
                        format!("node {} is used twice", drive.node_id),
                    ));
                }
                if drive.mode != mode {
                    return Err((field("mode"), format!("{side} drives must use {mode:?}")));
                }
                if drive.counts_per_rev == 0 {
                    return Err((field("counts_per_rev"), "must be positive".into()));
                }
                if !(drive.gear_ratio.is_finite() && drive.gear_ratio > 0.0) {
                    return Err((field("gear_ratio"), "must be a positive number".into()));
                }
                if drive
                    .rated_torque_nm
                    .is_some_and(|t| !(t.is_finite() && t > 0.0))
                {
                    return Err((field("rated_torque_nm"), "must be a positive number".into()));
                }
            }
        }
        Ok(())
    }
}

impl DriveConfig {
    /// Encoder counts per joint radian, signed by direction.
    fn counts_per_rad(&self) -> f64 {
        let sign = match self.direction {
            Direction::Normal => 1.0,
            Direction::Inverted => -1.0,
        };
        sign * f64::from(self.counts_per_rev) * self.gear_ratio / TAU
    }

    /// Joint rad (or rad/s) → counts (counts/s), rounded and saturated to i32.
    pub fn to_counts(&self, rad: f64) -> i32 {
        (rad * self.counts_per_rad()).round() as i32
    }

    /// Counts (counts/s) → joint rad (rad/s).
    pub fn to_rad(&self, counts: f64) -> f64 {
        counts / self.counts_per_rad()
    }

    /// Torque feedback in ‰ of the motor's rated torque → joint torque, N·m.
    pub fn to_effort_nm(&self, permille: i16) -> Option<f64> {
        let sign = self.counts_per_rad().signum();
        self.rated_torque_nm
            .map(|rated| sign * f64::from(permille) / 1000.0 * rated * self.gear_ratio)
    }

    /// Joint torque → ‰ of the motor's rated torque (0 when the drive reports no torque).
    pub fn to_permille(&self, effort_nm: f64) -> i16 {
        let sign = self.counts_per_rad().signum();
        self.rated_torque_nm.map_or(0, |rated| {
            (sign * effort_nm / (rated * self.gear_ratio) * 1000.0).round() as i16
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) const UNIT_CAN: &str =
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/unit_can.toml");

    pub(crate) fn unit_config() -> UnitCanConfig {
        UnitCanConfig::from_file(UNIT_CAN).unwrap()
    }

    fn with(replace: &str, by: &str) -> Result<UnitCanConfig, ConfigError> {
        let text = std::fs::read_to_string(UNIT_CAN).unwrap();
        assert!(text.contains(replace), "{replace}");
        UnitCanConfig::from_toml(&text.replacen(replace, by, 1), Path::new("unit_can.toml"))
    }

    #[test]
    fn shipped_config_loads() {
        let config = unit_config();
        assert_eq!(config.drives().count(), 9);
        assert_eq!(config.wheels[0].mode, OperationMode::Csv);
    }

    #[test]
    fn errors_name_file_and_field() {
        let err = with("node_id = 3", "node_id = 1").unwrap_err().to_string();
        assert!(
            err.contains("unit_can.toml") && err.contains("arm[0].node_id"),
            "{err}"
        );
        let err = with("mode = \"csp\"", "mode = \"csv\"")
            .unwrap_err()
            .to_string();
        assert!(err.contains("arm[0].mode"), "{err}");
        let err = with("sync_period_s", "bogus = 1\nsync_period_s")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("unit_can.toml") && err.contains("bogus"),
            "{err}"
        );
        let err = with("gear_ratio = 50.0", "gear_ratio = -1.0")
            .unwrap_err()
            .to_string();
        assert!(err.contains("wheels[0].gear_ratio"), "{err}");
        let err = with("sdo_timeout_s = 0.05", "sdo_timeout_s = 1e300")
            .unwrap_err()
            .to_string();
        assert!(err.contains("sdo_timeout_s"), "{err}");
        let err = UnitCanConfig::from_file("/nonexistent/unit.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains("/nonexistent/unit.toml"), "{err}");
    }

    #[test]
    fn conversions_invert() {
        let mut drive = unit_config().arm[0].clone();
        for direction in [Direction::Normal, Direction::Inverted] {
            drive.direction = direction;
            let counts = drive.to_counts(0.5);
            assert!((drive.to_rad(f64::from(counts)) - 0.5).abs() < 1e-4);
            assert!((drive.to_effort_nm(drive.to_permille(3.0)).unwrap() - 3.0).abs() < 0.1);
        }
        assert_eq!(drive.to_counts(f64::INFINITY), i32::MIN); // inverted, saturated
        let counts_per_joint_rev = f64::from(drive.counts_per_rev) * drive.gear_ratio;
        assert_eq!(drive.to_counts(-TAU), counts_per_joint_rev.round() as i32);
    }
}

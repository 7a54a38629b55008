//! A unit's CAN drive configuration (`configs/unit_can.toml`): bus timing, and per drive the
//! joint it moves, its node id, mode of operation and the counts ↔ rad conversion. Read by
//! core's one loader ([`moonhaul_core::config`]); the SYNC period is the control period of the
//! `configs/control.toml` the file names, and the drives' joints must be the unit URDF's, in
//! its order (wheels left, right; arm base to tip).

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::time::Duration;

use moonhaul_core::config::{
    self, count, in_range, positive, section, ControlConfig, FieldError, Validate,
};
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::UnitSpec;
use serde::Deserialize;

use super::cia402::OperationMode;

pub use moonhaul_core::config::ConfigError;

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitCanConfig {
    /// The control-rate file (`configs/control.toml`), relative to this file's folder.
    pub control: PathBuf,
    /// The unit URDF whose joints the drives move, relative to this file's folder.
    pub unit_urdf: PathBuf,
    /// SocketCAN interface name, e.g. `can0`.
    pub interface: String,
    /// SYNC period = control period, s: from `control` when the file is loaded.
    #[serde(skip)]
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
    #[serde(deserialize_with = "config::exact_array")]
    pub wheels: [DriveConfig; WHEEL_JOINTS],
    /// Base to tip.
    #[serde(deserialize_with = "config::exact_array")]
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
    /// Reads and validates a unit's CAN config, its control rate and the URDF joints it
    /// names; errors name the file and the field.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// Parses and validates; `path` names the source in errors and anchors relative paths.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        config::parse(text, path)
    }

    /// Wheels then arm: the order of the nine drives everywhere in this crate.
    pub fn drives(&self) -> impl Iterator<Item = &DriveConfig> {
        self.wheels.iter().chain(&self.arm)
    }

    pub fn sync_period(&self) -> Duration {
        Duration::from_secs_f64(self.sync_period_s)
    }

    /// The drives' joints must be `spec`'s, in its order (the error names both), and every
    /// joint's whole range must fit the drive's 32-bit counts: an arm joint's position limits
    /// (CSP), a wheel's velocity limit (CSV), each times counts per radian.
    pub fn check_joints(&self, spec: &UnitSpec) -> Result<(), FieldError> {
        let sides = [
            (
                "wheels",
                &self.wheels[..],
                &spec.wheel_joints[..],
                &spec.wheel_limits[..],
            ),
            (
                "arm",
                &self.arm[..],
                &spec.arm_joints[..],
                &spec.arm_limits[..],
            ),
        ];
        for (side, drives, joints, limits) in sides {
            for (i, ((drive, joint), limit)) in drives.iter().zip(joints).zip(limits).enumerate() {
                let field = |name: &str| format!("{side}[{i}].{name}");
                if drive.joint != *joint {
                    return Err(FieldError::new(
                        field("joint"),
                        format!(
                            "\"{}\" is not the unit URDF's {side} joint {i}, \"{joint}\"",
                            drive.joint
                        ),
                    ));
                }
                let extreme = match drive.mode {
                    OperationMode::Csp => limit.lower.abs().max(limit.upper.abs()),
                    OperationMode::Csv => limit.velocity,
                };
                let counts = extreme * drive.counts_per_rad().abs();
                if counts > f64::from(i32::MAX) {
                    return Err(FieldError::new(
                        field("gear_ratio"),
                        format!(
                            "counts_per_rev × gear_ratio turns \"{joint}\"'s URDF limit \
                             {extreme:?} into {counts:.3e} counts, beyond a drive's 32-bit range"
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Longest time-out, s: a drive silent for a minute is gone, not slow.
const MAX_TIMEOUT_S: f64 = 60.0;
/// Shortest SDO time-out, s: a request and its reply are two frames (about 0.25 ms at
/// 1 Mbit/s) plus the drive's own handling, which CiA 301 drives take up to a few ms for; a
/// shorter time-out fails every SDO of a healthy bus.
const MIN_SDO_TIMEOUT_S: f64 = 0.001;

impl Validate for UnitCanConfig {
    fn resolve(&mut self, path: &Path) -> Result<(), ConfigError> {
        self.sync_period_s = ControlConfig::load_referenced(path, &self.control)?.period_s();
        self.unit_urdf = config::resolve(path, &self.unit_urdf);
        let spec = UnitSpec::from_file(&self.unit_urdf).map_err(|e| ConfigError::Invalid {
            path: path.to_owned(),
            error: FieldError::new("unit_urdf", e.to_string()),
        })?;
        self.check_joints(&spec)
            .map_err(|error| ConfigError::Invalid {
                path: path.to_owned(),
                error,
            })
    }

    fn validate(&self) -> Result<(), FieldError> {
        // IFNAMSIZ - 1: Linux interface names have at most 15 bytes, and never '/', ':',
        // whitespace or the names "." and "..".
        let name_ok = (1..=15).contains(&self.interface.len())
            && self.interface != "."
            && self.interface != ".."
            && self
                .interface
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b));
        if !name_ok {
            return Err(FieldError::new(
                "interface",
                format!(
                    "{:?} must be 1 to 15 ASCII letters, digits, '_', '-' or '.'",
                    self.interface
                ),
            ));
        }
        let period = self.sync_period_s;
        count(
            "heartbeat_producer_ms",
            self.heartbeat_producer_ms.into(),
            1,
            10_000,
        )?;
        let producer_s = f64::from(self.heartbeat_producer_ms) / 1000.0;
        // Each watchdog must outlast what it watches, or healthy drives fault.
        in_range(
            "heartbeat_timeout_s",
            self.heartbeat_timeout_s,
            producer_s,
            MAX_TIMEOUT_S,
        )
        .and_then(|()| {
            strictly_longer(
                "heartbeat_timeout_s",
                self.heartbeat_timeout_s,
                producer_s,
                "heartbeat_producer_ms",
            )
        })?;
        in_range(
            "feedback_timeout_s",
            self.feedback_timeout_s,
            period,
            MAX_TIMEOUT_S,
        )
        .and_then(|()| {
            strictly_longer(
                "feedback_timeout_s",
                self.feedback_timeout_s,
                period,
                "the control period",
            )
        })?;
        in_range(
            "sdo_timeout_s",
            self.sdo_timeout_s,
            MIN_SDO_TIMEOUT_S,
            MAX_TIMEOUT_S,
        )?;
        positive(
            "state_change_timeout_s",
            self.state_change_timeout_s,
            MAX_TIMEOUT_S,
        )?;
        strictly_longer(
            "state_change_timeout_s",
            self.state_change_timeout_s,
            period,
            "the control period",
        )?;
        section("emulator", || {
            let e = &self.emulator;
            positive("time_constant_s", e.time_constant_s, 10.0)?;
            in_range("inertia_kgm2", e.inertia_kgm2, 0.0, 100.0)?;
            // The virtual clock advances by at least 1 µs and at most one control period.
            in_range("step_s", e.step_s, 1e-6, period)
        })?;
        let mut seen = [false; 128];
        let sides = [
            ("wheels", &self.wheels[..], OperationMode::Csv),
            ("arm", &self.arm[..], OperationMode::Csp),
        ];
        for (side, drives, mode) in sides {
            for (i, drive) in drives.iter().enumerate() {
                section(&format!("{side}[{i}]"), || {
                    count("node_id", drive.node_id.into(), 1, 127)?;
                    if std::mem::replace(&mut seen[usize::from(drive.node_id)], true) {
                        return Err(FieldError::new(
                            "node_id",
                            format!("node {} is used twice", drive.node_id),
                        ));
                    }
                    if drive.mode != mode {
                        return Err(FieldError::new(
                            "mode",
                            format!("{side} drives must use {mode:?}"),
                        ));
                    }
                    count("counts_per_rev", drive.counts_per_rev.into(), 1, 1 << 24)?;
                    positive("gear_ratio", drive.gear_ratio, 10_000.0)?;
                    drive
                        .rated_torque_nm
                        .map_or(Ok(()), |t| positive("rated_torque_nm", t, 1000.0))
                })?;
            }
        }
        Ok(())
    }
}

fn strictly_longer(field: &str, value: f64, than: f64, what: &str) -> Result<(), FieldError> {
    if value > than {
        Ok(())
    } else {
        Err(FieldError::new(
            field,
            format!("{value} s must be longer than {what} ({than} s)"),
        ))
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
        UnitCanConfig::from_toml(
            &text.replacen(replace, by, 1),
            &config::repo_file("configs/unit_can.toml"),
        )
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
        let err = with("heartbeat_producer_ms", "bogus = 1\nheartbeat_producer_ms")
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
        for tiny in ["1e-12", "0.0", "-0.05", "nan"] {
            let err = with("sdo_timeout_s = 0.05", &format!("sdo_timeout_s = {tiny}"))
                .unwrap_err()
                .to_string();
            assert!(err.contains("sdo_timeout_s"), "{tiny}: {err}");
        }
        // The drives' joints are the URDF's: a rename names both.
        let err = with("joint = \"arm_joint_3\"", "joint = \"elbow\"")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("arm[2].joint") && err.contains("elbow") && err.contains("arm_joint_3"),
            "{err}"
        );
        // An eighth arm drive is an error, not silently dropped.
        let extra = "[[arm]]\njoint = \"arm_joint_8\"\nnode_id = 10\nmode = \"csp\"\n\
                     counts_per_rev = 16384\ngear_ratio = 50.0\ndirection = \"normal\"\n\
                     rated_torque_nm = 0.32\n\n# Emulated drives";
        let err = with("# Emulated drives", extra).unwrap_err().to_string();
        assert!(err.contains("arm") && err.contains("8"), "{err}");
        let err = with(
            "counts_per_rev = 16384\ngear_ratio = 100.0",
            "counts_per_rev = 16777216\ngear_ratio = 1000.0",
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("arm[0].gear_ratio") && err.contains("32-bit"),
            "{err}"
        );
        let err = with("interface = \"can0\"", "interface = \"can0/../x\"")
            .unwrap_err()
            .to_string();
        assert!(err.contains("interface"), "{err}");
        // A watchdog shorter than what it watches.
        let err = with("feedback_timeout_s = 0.1", "feedback_timeout_s = 0.01")
            .unwrap_err()
            .to_string();
        assert!(err.contains("feedback_timeout_s"), "{err}");
        let err = with("heartbeat_producer_ms = 100", "heartbeat_producer_ms = 400")
            .unwrap_err()
            .to_string();
        assert!(err.contains("heartbeat_timeout_s"), "{err}");
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

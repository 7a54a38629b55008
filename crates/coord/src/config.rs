//! The coordination layer's settings: `configs/sync.toml` (clamp), `configs/gate.toml` (phase
//! gate and team agreement) and a unit-model file (the robot's arm and wheel module).
//!
//! Sync and gate settings default to the paper's values (or, where the paper gives none, to the
//! values `configs/gate.toml` justifies); the unit model is robot-specific and has no defaults.

use moonhaul_core::stacked::{StackedError, SyncTolerances};
use serde::de::DeserializeOwned;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// `configs/sync.toml`. Missing keys take the paper's values.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyncConfig {
    pub tolerances: SyncTolerances,
    pub search: SearchConfig,
}

/// How the clamp searches t_max (see `configs/sync.toml`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SearchConfig {
    /// Cells of the downward scan over t ∈ [0, 1].
    pub scan_cells: u32,
    /// Most evaluations of d the search for narrow admissible stretches inside inadmissible
    /// scan cells may spend in one tick.
    pub max_evaluations: u32,
    /// Width at which bisection of the bracketing cell stops: t_max's resolution.
    pub bisection_tolerance: f64,
}

impl Default for SearchConfig {
    fn default() -> Self {
        SearchConfig {
            scan_cells: 64,
            max_evaluations: 200,
            bisection_tolerance: 1e-7,
        }
    }
}

/// `configs/gate.toml`: the measured events of the phase gate and the agreement window.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GateConfig {
    pub lift: LiftConfig,
    pub transport: TransportConfig,
    pub place: PlaceConfig,
    pub agreement: AgreementConfig,
}

/// Lift → Transport when payload height ≥ h_min.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LiftConfig {
    /// h_min, m above the ground.
    pub payload_height_min_m: f64,
    /// Once asserted, the event stays asserted down to h_min − hysteresis.
    pub hysteresis_m: f64,
    pub debounce_ticks: u32,
}

impl Default for LiftConfig {
    fn default() -> Self {
        LiftConfig {
            payload_height_min_m: 0.27,
            hysteresis_m: 0.01,
            debounce_ticks: 10,
        }
    }
}

/// Transport → Place when the payload's distance to the goal ≤ τ_place.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TransportConfig {
    /// τ_place, m (horizontal distance of the payload to its goal).
    pub goal_distance_max_m: f64,
    /// Once asserted, the event stays asserted up to τ_place + hysteresis.
    pub hysteresis_m: f64,
    pub debounce_ticks: u32,
}

impl Default for TransportConfig {
    fn default() -> Self {
        TransportConfig {
            goal_distance_max_m: 0.05,
            hysteresis_m: 0.01,
            debounce_ticks: 10,
        }
    }
}

/// Place → Idle when released: payload resting on the ground and every grasp unloaded.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlaceConfig {
    /// Payload height above the ground at or below which it rests (h0_tol of Table II), m.
    pub payload_height_max_m: f64,
    pub height_hysteresis_m: f64,
    /// Largest grasp force, over all units, at or below which the grasps count as let go, N.
    pub grasp_force_max_n: f64,
    pub force_hysteresis_n: f64,
    pub debounce_ticks: u32,
}

impl Default for PlaceConfig {
    fn default() -> Self {
        PlaceConfig {
            payload_height_max_m: 0.02,
            height_hysteresis_m: 0.005,
            grasp_force_max_n: 5.0,
            force_hysteresis_n: 1.0,
            debounce_ticks: 25,
        }
    }
}

/// How long the team may wait for a phase change to be proposed by every unit.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AgreementConfig {
    pub pending_window_ticks: u32,
}

impl Default for AgreementConfig {
    fn default() -> Self {
        AgreementConfig {
            pending_window_ticks: 10,
        }
    }
}

/// A unit-model file: where the arm's kinematics come from and the wheel module's geometry.
/// Robot-specific, so every key is required.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitModelConfig {
    /// The arm's URDF, relative to the directory of the config file.
    pub urdf: PathBuf,
    /// Link the arm is mounted by; joints between it and `arm_tip_link` are the 7 arm joints.
    pub arm_base_link: String,
    /// The end-effector link whose pose the clamp watches.
    pub arm_tip_link: String,
    /// Pose of `arm_base_link` in the wheel-base frame (origin on the ground between the wheels,
    /// x forward, z up): translation, m.
    pub arm_mount_xyz_m: [f64; 3],
    /// …and fixed-axis roll, pitch, yaw, rad (URDF convention).
    pub arm_mount_rpy_rad: [f64; 3],
    pub wheel_radius_m: f64,
    /// Distance between the two wheels' contact points, m.
    pub wheel_track_m: f64,
}

/// A config value outside its valid range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} = {value} must be {expected}")]
pub struct FieldError {
    pub field: &'static str,
    pub value: f64,
    pub expected: &'static str,
}

/// Why a settings file's values are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidConfig {
    #[error(transparent)]
    Field(#[from] FieldError),
    #[error(transparent)]
    Tolerance(#[from] StackedError),
    #[error(transparent)]
    Team(#[from] crate::team::TeamError),
}

/// Checks a field: `ok(value)` or an error naming it.
pub fn check(
    field: &'static str,
    value: f64,
    expected: &'static str,
    ok: impl Fn(f64) -> bool,
) -> Result<(), FieldError> {
    if ok(value) {
        Ok(())
    } else {
        Err(FieldError {
            field,
            value,
            expected,
        })
    }
}

pub fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

pub(crate) fn non_negative(v: f64) -> bool {
    v.is_finite() && v >= 0.0
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
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
    #[error("{path}: {source}")]
    Invalid {
        path: PathBuf,
        source: InvalidConfig,
    },
    #[error("{path}: {source}")]
    Model {
        path: PathBuf,
        source: crate::model::ModelError,
    },
}

/// A settings file that can check its own values.
pub trait Validate {
    /// The first invalid field, if any.
    fn validate(&self) -> Result<(), InvalidConfig>;
}

/// Reads, parses and validates a TOML settings file; errors name the file and the field.
pub fn load<T: DeserializeOwned + Validate>(path: &Path) -> Result<T, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.to_owned(),
        source,
    })?;
    let config: T = toml::from_str(&text).map_err(|e| ConfigError::Parse {
        path: path.to_owned(),
        source: Box::new(e),
    })?;
    config.validate().map_err(|source| ConfigError::Invalid {
        path: path.to_owned(),
        source,
    })?;
    Ok(config)
}

impl SyncConfig {
    /// Reads and validates a sync config.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        load(path)
    }
}

impl GateConfig {
    /// Reads and validates a gate config.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        load(path)
    }
}

impl Validate for SyncConfig {
    fn validate(&self) -> Result<(), InvalidConfig> {
        self.tolerances.validate()?;
        check(
            "search.scan_cells",
            self.search.scan_cells.into(),
            "at least 1",
            |v| v >= 1.0,
        )?;
        check(
            "search.max_evaluations",
            self.search.max_evaluations.into(),
            "at least 1",
            |v| v >= 1.0,
        )?;
        check(
            "search.bisection_tolerance",
            self.search.bisection_tolerance,
            "in (0, 1)",
            |v| positive(v) && v < 1.0,
        )?;
        Ok(())
    }
}

impl Validate for GateConfig {
    fn validate(&self) -> Result<(), InvalidConfig> {
        let (l, t, p) = (&self.lift, &self.transport, &self.place);
        check(
            "lift.payload_height_min_m",
            l.payload_height_min_m,
            "finite and positive",
            positive,
        )?;
        check(
            "lift.hysteresis_m",
            l.hysteresis_m,
            "finite, >= 0",
            non_negative,
        )?;
        check(
            "transport.goal_distance_max_m",
            t.goal_distance_max_m,
            "finite and positive",
            positive,
        )?;
        check(
            "transport.hysteresis_m",
            t.hysteresis_m,
            "finite, >= 0",
            non_negative,
        )?;
        check(
            "place.payload_height_max_m",
            p.payload_height_max_m,
            "finite, >= 0",
            non_negative,
        )?;
        check(
            "place.height_hysteresis_m",
            p.height_hysteresis_m,
            "finite, >= 0",
            non_negative,
        )?;
        check(
            "place.grasp_force_max_n",
            p.grasp_force_max_n,
            "finite, >= 0",
            non_negative,
        )?;
        check(
            "place.force_hysteresis_n",
            p.force_hysteresis_n,
            "finite, >= 0",
            non_negative,
        )?;
        // A payload that counts as lifted must not count as resting, or Place could end at once.
        check(
            "lift.payload_height_min_m",
            l.payload_height_min_m - l.hysteresis_m,
            "above place.payload_height_max_m + place.height_hysteresis_m (after subtracting lift.hysteresis_m)",
            |v| v > p.payload_height_max_m + p.height_hysteresis_m,
        )?;
        for (field, ticks) in [
            ("lift.debounce_ticks", l.debounce_ticks),
            ("transport.debounce_ticks", t.debounce_ticks),
            ("place.debounce_ticks", p.debounce_ticks),
            (
                "agreement.pending_window_ticks",
                self.agreement.pending_window_ticks,
            ),
        ] {
            check(field, ticks.into(), "at least 1", |v| v >= 1.0)?;
        }
        Ok(())
    }
}

impl Validate for UnitModelConfig {
    fn validate(&self) -> Result<(), InvalidConfig> {
        check(
            "wheel_radius_m",
            self.wheel_radius_m,
            "finite and positive",
            positive,
        )?;
        check(
            "wheel_track_m",
            self.wheel_track_m,
            "finite and positive",
            positive,
        )?;
        let names = ["arm_mount_xyz_m", "arm_mount_rpy_rad"];
        for (field, values) in names
            .into_iter()
            .zip([self.arm_mount_xyz_m, self.arm_mount_rpy_rad])
        {
            for v in values {
                check(field, v, "finite", f64::is_finite)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../configs")
            .join(name)
    }

    #[test]
    fn shipped_configs_hold_the_defaults() {
        assert_eq!(
            SyncConfig::from_file(&shipped("sync.toml")).unwrap(),
            SyncConfig::default()
        );
        assert_eq!(
            GateConfig::from_file(&shipped("gate.toml")).unwrap(),
            GateConfig::default()
        );
    }

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn bad_configs_name_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let sync_cases = [
            (
                "[tolerances]\narm_translation_mm = 30.0\n",
                "arm_translation_mm",
            ),
            (
                "[tolerances]\narm_translation_m = -0.03\n",
                "arm_translation_m",
            ),
            ("[tolerances]\nbase_xy_m = [0.02]\n", "base_xy_m"),
            ("[search]\nscan_cells = 0\n", "search.scan_cells"),
            (
                "[search]\nbisection_tolerance = 0.0\n",
                "search.bisection_tolerance",
            ),
        ];
        for (i, (text, field)) in sync_cases.into_iter().enumerate() {
            let path = write(dir.path(), &format!("bad_sync{i}.toml"), text);
            let message = SyncConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains("bad_sync"),
                "{message}"
            );
        }
        let gate_cases = [
            ("[lift]\nh_min = 0.3\n", "h_min"),
            (
                "[lift]\npayload_height_min_m = nan\n",
                "lift.payload_height_min_m",
            ),
            (
                "[lift]\npayload_height_min_m = 0.02\n",
                "lift.payload_height_min_m",
            ),
            (
                "[transport]\ngoal_distance_max_m = 0.0\n",
                "transport.goal_distance_max_m",
            ),
            (
                "[place]\nforce_hysteresis_n = -1.0\n",
                "place.force_hysteresis_n",
            ),
            ("[place]\ndebounce_ticks = 0\n", "place.debounce_ticks"),
            (
                "[agreement]\npending_window_ticks = 0\n",
                "agreement.pending_window_ticks",
            ),
        ];
        for (i, (text, field)) in gate_cases.into_iter().enumerate() {
            let path = write(dir.path(), &format!("bad_gate{i}.toml"), text);
            let message = GateConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains("bad_gate"),
                "{message}"
            );
        }
        let missing = SyncConfig::from_file(&dir.path().join("absent.toml"))
            .unwrap_err()
            .to_string();
        assert!(missing.contains("absent.toml"), "{missing}");
    }
}

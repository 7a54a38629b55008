//! The simulator's configuration, `configs/sim.toml`: physics rates and solver settings, motor
//! gains, the grasp's break limits, the scene layout and the domain randomization. Every field is
//! required in the file (`deny_unknown_fields`, no serde defaults) so a typo cannot silently fall
//! back; [`SimConfig::default`] holds the same values for tests and tools.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::randomization::Randomization;
use crate::scripted::MissionPlan;
use crate::SimError;

/// Physics and control rates and the rapier solver settings.
///
/// The dynamics are integrated at `physics_hz` (rapier's solver substeps); contacts are
/// detected, and the grasp wrench checked, at `collision_hz` (one rapier pipeline step of
/// `physics_hz / collision_hz` substeps). Collision detection and the pipeline's per-step
/// bookkeeping cost more than a substep here, and contacts change little within 20 ms at the
/// mission's speeds (see `moonhaul sim bench` for the accuracy against a fine reference).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Integration steps per second (default 200 Hz).
    pub physics_hz: f64,
    /// Collision-detection passes per second; divides `physics_hz` and is a multiple of
    /// `control_hz`.
    pub collision_hz: f64,
    /// Control steps per second (default 50 Hz, the onboard rate).
    pub control_hz: f64,
    /// Gravity along world Z, m/s².
    pub gravity_mps2: f64,
    /// Gauss–Seidel sweeps per substep (`IntegrationParameters::num_internal_pgs_iterations`).
    pub num_internal_pgs_iterations: usize,
    /// Position-correction sweeps per substep
    /// (`IntegrationParameters::num_internal_stabilization_iterations`).
    pub num_internal_stabilization_iterations: usize,
    /// Distance within which contacts are predicted, m (rapier's default is 0.02). Each
    /// predicted wheel or caster contact adds constraint rows that need a multibody mass-matrix
    /// solve; 2 mm keeps only the touching ones.
    pub prediction_distance_m: f64,
}

/// The integer ratio `num / den` of two rates, or an error naming `field`.
fn ratio(num: f64, den: f64, field: &'static str) -> Result<usize, SimError> {
    let r = num / den;
    let rounded = r.round();
    if r.is_finite() && rounded >= 1.0 && (r - rounded).abs() < 1e-9 {
        Ok(rounded as usize)
    } else {
        Err(SimError::Config {
            field,
            reason: format!("{num} / {den} = {r} is not a positive integer"),
        })
    }
}

impl PhysicsConfig {
    /// Substeps per collision pass.
    pub fn substeps(&self) -> Result<usize, SimError> {
        ratio(self.physics_hz, self.collision_hz, "physics.collision_hz")
    }

    /// Collision passes (rapier pipeline steps) per control step.
    pub fn pipeline_steps_per_control(&self) -> Result<usize, SimError> {
        ratio(self.collision_hz, self.control_hz, "physics.control_hz")
    }

    /// Integration steps per control step.
    pub fn decimation(&self) -> Result<usize, SimError> {
        ratio(self.physics_hz, self.control_hz, "physics.control_hz")
    }
}

/// Joint motor gains; torques stay within each joint's URDF effort limit.
///
/// Arm position motors use rapier's acceleration-based model, which scales the gains by each
/// joint's effective inertia within its own arm: one pair serves the 4 kg shoulder and the
/// 0.3 kg wrist alike, each joint a spring–damper of natural frequency √stiffness rad/s. The
/// payload is not part of that inertia, so a held payload makes the arms sag a little.
/// Wheel velocity motors are force-based, torque = gain · (ω_cmd − ω): an acceleration-based
/// wheel motor would be scaled by the wheel's own tiny inertia and could not push the base.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotorConfig {
    /// Arm position-motor stiffness, 1/s².
    pub arm_stiffness_per_s2: f64,
    /// Arm position-motor damping, 1/s.
    pub arm_damping_per_s: f64,
    /// Wheel velocity-motor gain, N·m·s/rad.
    pub wheel_gain_nms_per_rad: f64,
}

/// When a rigid grasp lets go: the wrench a real clamp could hold. The defaults are about twice
/// the largest grasp wrench seen in 30 randomized scripted missions (320 N, 115 N·m; holding
/// the 9.5 kg payload still takes ~50 N per arm): a break means a policy fought the other
/// unit, not ordinary carrying.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspConfig {
    /// A grasp breaks when its force exceeds this, N.
    pub break_force_n: f64,
    /// A grasp breaks when its torque exceeds this, N·m.
    pub break_torque_nm: f64,
}

/// Where things are. The formation itself is fixed by design (see [`crate::scene`]); these
/// are its dimensions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneConfig {
    /// Folder holding `unit.urdf` and `payload_<name>.urdf`; relative paths in a config file
    /// are resolved against the file's folder.
    pub assets_dir: PathBuf,
    /// Horizontal distance from a unit's base origin to the payload face it grasps, m.
    pub reach_m: f64,
    /// Payload–ground friction coefficient.
    pub payload_friction: f64,
    /// Side of the square terrain heightfield, m.
    pub terrain_size_m: f64,
    /// Heightfield grid spacing, m: fine enough to resolve the shortest correlation length.
    pub terrain_spacing_m: f64,
    /// X of the terrain's centre, m: the mission drives toward +X from the origin.
    pub terrain_center_x_m: f64,
}

/// The whole simulator configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    pub physics: PhysicsConfig,
    pub motors: MotorConfig,
    pub grasp: GraspConfig,
    pub scene: SceneConfig,
    pub randomization: Randomization,
    /// The scripted mission flown by `moonhaul sim demo` and replayed by `sim bench`.
    pub mission: MissionPlan,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            physics: PhysicsConfig {
                physics_hz: 200.0,
                collision_hz: 50.0,
                control_hz: 50.0,
                gravity_mps2: -9.81,
                num_internal_pgs_iterations: 2,
                num_internal_stabilization_iterations: 1,
                prediction_distance_m: 0.002,
            },
            motors: MotorConfig {
                arm_stiffness_per_s2: 2500.0,
                arm_damping_per_s: 100.0,
                wheel_gain_nms_per_rad: 50.0,
            },
            grasp: GraspConfig {
                break_force_n: 600.0,
                break_torque_nm: 200.0,
            },
            scene: SceneConfig {
                assets_dir: Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets"),
                reach_m: 0.57,
                payload_friction: 0.8,
                terrain_size_m: 5.0,
                terrain_spacing_m: 0.025,
                terrain_center_x_m: 1.0,
            },
            randomization: Randomization::default(),
            mission: MissionPlan::default(),
        }
    }
}

impl SimConfig {
    /// Reads and validates a TOML config; errors name the file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| SimError::Io {
            path: path.to_owned(),
            source,
        })?;
        let mut config: SimConfig = toml::from_str(&text).map_err(|source| SimError::Toml {
            path: path.to_owned(),
            source: Box::new(source),
        })?;
        if config.scene.assets_dir.is_relative() {
            let dir = path.parent().unwrap_or(Path::new("."));
            config.scene.assets_dir = dir.join(&config.scene.assets_dir);
        }
        config.validate()?;
        Ok(config)
    }

    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), SimError> {
        let positive = |field: &'static str, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(SimError::Config {
                    field,
                    reason: format!("{value} must be finite and > 0"),
                })
            }
        };
        positive("physics.physics_hz", self.physics.physics_hz)?;
        positive("physics.collision_hz", self.physics.collision_hz)?;
        positive("physics.control_hz", self.physics.control_hz)?;
        positive(
            "physics.prediction_distance_m",
            self.physics.prediction_distance_m,
        )?;
        self.physics.substeps()?;
        self.physics.pipeline_steps_per_control()?;
        if self.physics.num_internal_pgs_iterations == 0 {
            return Err(SimError::Config {
                field: "physics.num_internal_pgs_iterations",
                reason: "must be >= 1".into(),
            });
        }
        positive(
            "motors.arm_stiffness_per_s2",
            self.motors.arm_stiffness_per_s2,
        )?;
        positive("motors.arm_damping_per_s", self.motors.arm_damping_per_s)?;
        positive(
            "motors.wheel_gain_nms_per_rad",
            self.motors.wheel_gain_nms_per_rad,
        )?;
        positive("grasp.break_force_n", self.grasp.break_force_n)?;
        positive("grasp.break_torque_nm", self.grasp.break_torque_nm)?;
        positive("scene.reach_m", self.scene.reach_m)?;
        positive("scene.payload_friction", self.scene.payload_friction)?;
        positive("scene.terrain_size_m", self.scene.terrain_size_m)?;
        positive("scene.terrain_spacing_m", self.scene.terrain_spacing_m)?;
        let m = &self.mission;
        positive("mission.lift_height_m", m.lift_height_m)?;
        positive("mission.lift_duration_s", m.lift_duration_s)?;
        positive("mission.speed_mps", m.speed_mps)?;
        positive("mission.accel_mps2", m.accel_mps2)?;
        positive("mission.place_duration_s", m.place_duration_s)?;
        positive("mission.touchdown_speed_mps", m.touchdown_speed_mps)?;
        self.randomization.validate()
    }

    /// The unit URDF.
    pub fn unit_urdf(&self) -> PathBuf {
        self.scene.assets_dir.join("unit.urdf")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn repo_config() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim.toml")
    }

    #[test]
    fn the_repo_config_equals_the_defaults() {
        let mut file = SimConfig::load(repo_config()).unwrap();
        let default = SimConfig::default();
        assert_eq!(
            file.scene.assets_dir.canonicalize().unwrap(),
            default.scene.assets_dir.canonicalize().unwrap()
        );
        file.scene.assets_dir = default.scene.assets_dir.clone();
        assert_eq!(file, default);
    }

    #[test]
    fn unknown_fields_and_bad_rates_are_rejected_by_name() {
        let text = std::fs::read_to_string(repo_config()).unwrap();
        let typo = text.replace("physics_hz", "physics_hertz");
        assert!(toml::from_str::<SimConfig>(&typo)
            .unwrap_err()
            .to_string()
            .contains("physics_hertz"));
        let mut config = SimConfig::default();
        config.physics.control_hz = 60.0;
        assert!(config
            .validate()
            .unwrap_err()
            .to_string()
            .contains("physics.control_hz"));
        config.physics.control_hz = 50.0;
        config.physics.collision_hz = 75.0;
        assert!(config
            .validate()
            .unwrap_err()
            .to_string()
            .contains("physics.collision_hz"));
    }
}

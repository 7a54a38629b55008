//! The simulator's configuration, `configs/sim.toml`: physics rates and solver settings, motor
//! gains, the grasp's break limits, the scene layout and the domain randomization, read by
//! core's one loader ([`moonhaul_core::config`]): every key required, every number checked
//! against a range whose upper bound keeps a world buildable in bounded time and memory. The
//! control rate comes from the `configs/control.toml` the file names.

use std::path::{Path, PathBuf};

use moonhaul_core::config::{
    self, count, in_range, integer_ratio, positive, section, ConfigError, ControlConfig,
    FieldError, Validate,
};
use serde::{Deserialize, Serialize};

use crate::randomization::Randomization;

/// Physics and control rates and the rapier solver settings.
///
/// The dynamics are integrated at `physics_hz` (rapier's solver substeps); contacts are
/// detected, and the grasp wrench checked, at `collision_hz` (one rapier pipeline step of
/// `physics_hz / collision_hz` substeps). Collision detection and the pipeline's per-step
/// bookkeeping cost more than a substep here, and contacts change little within 20 ms at the
/// mission's speeds (see `moonhaul sim bench` for the accuracy against a fine reference).
///
/// Fewer substeps were measured and refused (issue 20): at 100 Hz with three Gauss–Seidel
/// sweeps a lift training iteration's physics cost 0.77 of today's and the payload height
/// stayed within 3.9 mm RMS of the fine reference, but the loaded arm drives then held their
/// command only to 4.4 mm / 0.68° (150 Hz: 3.8 mm / 0.49°), past `tests/drives.rs`'s 3 mm /
/// 0.5° (bricks at 1.2× mass; 200 Hz passes it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Integration steps per second (shipped: 200 Hz).
    pub physics_hz: f64,
    /// Collision-detection passes per second; divides `physics_hz` and is a whole multiple of
    /// the control rate.
    pub collision_hz: f64,
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

/// Joint drive gains; torques stay within each joint's URDF effort limit.
///
/// Each arm joint is a position servo with velocity and gravity feed-forward (see
/// `scene/actuation.rs`): a force-based spring–damper, torque = K·(q_cmd − q) + D·(q̇_cmd − q̇),
/// whose stiffness is the joint's URDF effort limit over `arm_full_effort_error_rad` (the
/// shoulder 1600 N·m/rad, the wrist 200 N·m/rad at the default) and whose damping is
/// `arm_damping_time_s` × K. A stiffness proportional to the joint's torque rating is what a
/// real arm's joint controllers have; rapier's acceleration-based motor would scale it by the
/// joint's own link inertia instead, which left the 0.002 kg·m² wrist at ~5 N·m/rad and let the
/// closed chain twist it by 5°. Wheel velocity motors are force-based, torque =
/// gain · (ω_cmd − ω).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotorConfig {
    /// Position error at which an arm joint's spring reaches the joint's URDF effort limit,
    /// rad (default 0.2).
    pub arm_full_effort_error_rad: f64,
    /// Arm damping as a time constant of the spring, s (default 0.02, one control period):
    /// D = K · this.
    pub arm_damping_time_s: f64,
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
    /// The control-rate file (`configs/control.toml`), relative to this file's folder.
    pub control: PathBuf,
    /// Control steps per second, read from `control` when the file is loaded.
    #[serde(skip)]
    pub control_hz: f64,
    pub physics: PhysicsConfig,
    pub motors: MotorConfig,
    pub grasp: GraspConfig,
    pub scene: SceneConfig,
    pub randomization: Randomization,
}

impl SimConfig {
    /// Reads and validates `configs/sim.toml` and the control rate it names; errors name the
    /// file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// The shipped `configs/sim.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::load(config::repo_file("configs/sim.toml"))
    }

    /// The unit URDF.
    pub fn unit_urdf(&self) -> PathBuf {
        self.scene.assets_dir.join("unit.urdf")
    }

    /// Integration substeps per collision pass.
    pub fn substeps(&self) -> usize {
        // Checked whole at load; `max(1)` only guards hand-built configs.
        (self.physics.physics_hz / self.physics.collision_hz)
            .round()
            .max(1.0) as usize
    }

    /// Collision passes (rapier pipeline steps) per control step.
    pub fn pipeline_steps_per_control(&self) -> usize {
        (self.physics.collision_hz / self.control_hz)
            .round()
            .max(1.0) as usize
    }

    /// Integration steps per control step.
    pub fn decimation(&self) -> usize {
        self.substeps() * self.pipeline_steps_per_control()
    }
}

/// Most heightfield cells along one side: 4096² cells are 64 MiB of f32 per world.
const MAX_TERRAIN_CELLS: f64 = 4096.0;

impl Validate for SimConfig {
    fn resolve(&mut self, path: &Path) -> Result<(), ConfigError> {
        self.control_hz = ControlConfig::load_referenced(path, &self.control)?.control_rate_hz;
        self.scene.assets_dir = config::resolve(path, &self.scene.assets_dir);
        Ok(())
    }

    fn validate(&self) -> Result<(), FieldError> {
        section("physics", || {
            let p = &self.physics;
            // 10 kHz integration is far finer than any accuracy check needs; above it a
            // training run would take days.
            positive("physics_hz", p.physics_hz, 10_000.0)?;
            positive("collision_hz", p.collision_hz, p.physics_hz)?;
            integer_ratio("collision_hz", p.physics_hz, p.collision_hz).map_err(|e| {
                FieldError::new(e.field, format!("physics_hz / collision_hz: {}", e.reason))
            })?;
            integer_ratio("collision_hz", p.collision_hz, self.control_hz).map_err(|e| {
                FieldError::new(
                    e.field,
                    format!(
                        "collision_hz / the control rate ({} Hz): {}",
                        self.control_hz, e.reason
                    ),
                )
            })?;
            // Downward, from the Moon's -1.62 to well past Earth's: a world without gravity
            // has no ground contact to learn from.
            in_range("gravity_mps2", p.gravity_mps2, -30.0, -0.1)?;
            count(
                "num_internal_pgs_iterations",
                p.num_internal_pgs_iterations as u64,
                1,
                100,
            )?;
            count(
                "num_internal_stabilization_iterations",
                p.num_internal_stabilization_iterations as u64,
                0,
                100,
            )?;
            positive("prediction_distance_m", p.prediction_distance_m, 0.1)
        })?;
        section("motors", || {
            let m = &self.motors;
            positive(
                "arm_full_effort_error_rad",
                m.arm_full_effort_error_rad,
                3.2,
            )?;
            positive("arm_damping_time_s", m.arm_damping_time_s, 1.0)?;
            positive("wheel_gain_nms_per_rad", m.wheel_gain_nms_per_rad, 1e4)
        })?;
        section("grasp", || {
            positive("break_force_n", self.grasp.break_force_n, 1e5)?;
            positive("break_torque_nm", self.grasp.break_torque_nm, 1e5)
        })?;
        section("scene", || {
            let s = &self.scene;
            positive("reach_m", s.reach_m, 2.0)?;
            positive("payload_friction", s.payload_friction, 2.0)?;
            positive("terrain_size_m", s.terrain_size_m, 100.0)?;
            positive("terrain_spacing_m", s.terrain_spacing_m, s.terrain_size_m)?;
            if s.terrain_size_m / s.terrain_spacing_m > MAX_TERRAIN_CELLS {
                return Err(FieldError::new(
                    "terrain_spacing_m",
                    format!(
                        "{} m gives more than {MAX_TERRAIN_CELLS} cells along the {} m terrain",
                        s.terrain_spacing_m, s.terrain_size_m
                    ),
                ));
            }
            in_range("terrain_center_x_m", s.terrain_center_x_m, -100.0, 100.0)
        })?;
        section("randomization", || {
            self.randomization.validate(self.scene.terrain_spacing_m)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_repo_config_loads_with_the_shared_control_rate() {
        let config = SimConfig::shipped().unwrap();
        assert_eq!(config.control_hz, 50.0);
        assert_eq!(
            (config.substeps(), config.pipeline_steps_per_control()),
            (4, 1)
        );
        assert_eq!(config.decimation(), 4);
        assert!(config.unit_urdf().exists());
    }

    #[test]
    fn bad_values_are_rejected_by_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::copy(
            config::repo_file("configs/control.toml"),
            dir.path().join("control.toml"),
        )
        .unwrap();
        let text = std::fs::read_to_string(config::repo_file("configs/sim.toml"))
            .unwrap()
            .replace(
                "\"../assets\"",
                &format!("{:?}", config::repo_file("assets")),
            );
        // The shipped file with `key`'s line set to `key = value` (whatever the shipped value).
        let set = |key: &str, value: &str| {
            let prefix = format!("{key} = ");
            let lines: Vec<String> = text
                .lines()
                .map(|l| match l.starts_with(&prefix) {
                    true => format!("{prefix}{value}"),
                    false => l.to_owned(),
                })
                .collect();
            assert!(lines.iter().any(|l| l.starts_with(&prefix)), "no {key}");
            lines.join("\n")
        };
        let cases = [
            (text.replace("physics_hz", "physics_hertz"), "physics_hertz"),
            (
                text.replace("collision_hz = 50.0", "collision_hz = 75.0"),
                "physics.collision_hz",
            ),
            (
                text.replace("collision_hz = 50.0", "collision_hz = 40.0"),
                "physics.collision_hz",
            ),
            (set("physics_hz", "1e12"), "physics.physics_hz"),
            (
                set("num_internal_pgs_iterations", "1000000000"),
                "physics.num_internal_pgs_iterations",
            ),
            (
                text.replace("terrain_spacing_m = 0.025", "terrain_spacing_m = 1e-6"),
                "scene.terrain_spacing_m",
            ),
            (
                text.replace("terrain_size_m = 5.0", "terrain_size_m = inf"),
                "scene.terrain_size_m",
            ),
            (
                text.replace(
                    "wheel_friction = [0.6, 1.0]",
                    "wheel_friction = [0.6, 1.0, 1.2]",
                ),
                "randomization.wheel_friction",
            ),
            (
                text.replace(
                    "correlation_length_m = [0.05, 0.15]",
                    "correlation_length_m = [0.05, 1e9]",
                ),
                "randomization.terrain.correlation_length_m",
            ),
            (
                text.replace("control = \"control.toml\"", "control = \"absent.toml\""),
                "absent.toml",
            ),
            // A custom payload is a file given in code, never a config name.
            (
                text.replace(
                    "payloads = [\"box\", \"bricks\"]",
                    "payloads = [\"box\", \"custom\"]",
                ),
                "randomization.payloads",
            ),
        ];
        for (i, (text, field)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("sim{i}.toml"));
            std::fs::write(&path, text).unwrap();
            let message = SimConfig::load(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains(".toml"),
                "{field}: {message}"
            );
        }
        // The shared control rate takes part in the cross-field check.
        std::fs::write(dir.path().join("control.toml"), "control_rate_hz = 60.0\n").unwrap();
        let path = dir.path().join("sim.toml");
        std::fs::write(&path, text).unwrap();
        let message = SimConfig::load(&path).unwrap_err().to_string();
        assert!(
            message.contains("physics.collision_hz") && message.contains("60"),
            "{message}"
        );
    }
}

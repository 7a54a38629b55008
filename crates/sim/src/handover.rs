//! Hand-over starts: training episodes of transport and place that begin where a deployed
//! mission handed over, not settled with U = Y and the payload still.
//!
//! A [`HandOver`] is captured in a mission flown through the deployed stack (`moonhaul
//! handovers`: the onboard tick, gate and clamp, scripted or learned): the world's seed, every
//! command both units issued from its start through the tick at which the team committed to
//! the phase, and each unit's onboard state then ([`UnitHandOver`]: U_{k−1}, the pipeline's
//! last step and hold count, odometry, rest grasp). The world is not stored: rapier is
//! deterministic, so [`Env::replay`] rebuilds the world from its seed and replays the
//! commands, arriving in the captured state (the payload still rising or swinging, the bases
//! still rolling, the arms' following error), and checks it against the captured truth. The
//! replayed world then becomes the one its resets restore, so every episode of that world
//! starts at the hand-over; [`crate::task::PhaseTask::begin_handover`] starts the episode
//! with the captured onboard state.
//!
//! Files are JSON (`format`/`version` checked), read size-capped; a file that does not parse,
//! a capture whose replay ends elsewhere than captured, or one of another phase is an error
//! naming the file and the capture.

use std::path::{Path, PathBuf};

use moonhaul_coord::message::MessageBounds;
use moonhaul_core::handover::UnitHandOver;
use moonhaul_core::state::{Phase, UnitCommand, ARM_JOINTS};
use serde::{Deserialize, Serialize};

use crate::scene::{Env, EnvOptions, EnvState, SceneModel, UNITS};
use crate::{PayloadKind, SimError};

/// The `format` of a hand-over file.
pub const FORMAT: &str = "moonhaul-handovers";
/// The `version` of a hand-over file this build reads and writes.
pub const VERSION: u32 = 1;
/// Largest hand-over file read, bytes (a mission's commands are ~100 kB of JSON).
const MAX_FILE_BYTES: u64 = 256 << 20;
/// How far a replayed payload may end from where it was captured, m, and a replayed arm joint
/// from its captured position, rad. Replays on the machine and build that captured are exact;
/// the tolerance admits another build's rounding, not another world.
pub const REPLAY_TOLERANCE_M: f64 = 0.005;
pub const REPLAY_TOLERANCE_RAD: f64 = 0.01;
/// The most commands a capture may hold: 200 s at 50 Hz, beyond any mission (the deployed
/// evaluation ends one at 60 s). Bounds the work a replay can be asked to do.
pub const MAX_REPLAY_TICKS: usize = 10_000;

/// One mission's hand-over into `phase`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HandOver {
    /// The phase the team committed to (transport or place).
    pub phase: Phase,
    /// The world: [`Env::new`]'s seed and options (lift 0: a mission starts on the ground).
    pub world_seed: u64,
    pub randomize: bool,
    pub payload: PayloadKind,
    /// Both units' commands of every tick from the world's start through the hand-over tick,
    /// as the world was stepped with them.
    pub commands: Vec<[UnitCommand; UNITS]>,
    /// Each unit's onboard state after the hand-over tick.
    pub units: [UnitHandOver; UNITS],
    /// The world after the hand-over tick (simulator truth), for the replay's check: the
    /// payload's position, m, and each unit's arm joints, rad.
    pub payload_position_m: [f64; 3],
    pub arm_position_rad: [[f64; ARM_JOINTS]; UNITS],
}

/// A hand-over file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HandOverFile {
    pub format: String,
    pub version: u32,
    pub handovers: Vec<HandOver>,
}

impl HandOver {
    /// The capture of `state`, the world after the hand-over tick.
    pub fn new(
        phase: Phase,
        (world_seed, options): (u64, EnvOptions),
        commands: Vec<[UnitCommand; UNITS]>,
        units: [UnitHandOver; UNITS],
        state: &EnvState,
    ) -> Self {
        HandOver {
            phase,
            world_seed,
            randomize: options.randomize,
            payload: options.payload.unwrap_or(PayloadKind::Box),
            commands,
            units,
            payload_position_m: state.payload.pose.translation.vector.into(),
            arm_position_rad: state.units.map(|u| u.state.arm.position_rad),
        }
    }

    /// The options the captured world was built with.
    pub fn env_options(&self) -> EnvOptions {
        EnvOptions {
            randomize: self.randomize,
            payload: Some(self.payload),
            start_lift_m: 0.0,
        }
    }

    /// Refuses a capture no deployed mission can have produced: more commands than
    /// [`MAX_REPLAY_TICKS`], a command beyond the unit's joint or wheel-speed bounds (those a
    /// peer holds messages to, [`MessageBounds`]), or a non-finite number in the onboard state or
    /// the captured truth. The replay then steps only physical commands.
    pub fn check(&self, scene: &SceneModel) -> Result<(), String> {
        if self.commands.len() > MAX_REPLAY_TICKS {
            return Err(format!(
                "{} ticks of commands, more than the {MAX_REPLAY_TICKS} a mission can last",
                self.commands.len()
            ));
        }
        let bounds = MessageBounds::of_unit(&scene.spec);
        let command_ok = |c: &UnitCommand| {
            c.arm_position_rad
                .iter()
                .zip(&bounds.arm_position_rad)
                .all(|(q, (lo, hi))| (*lo..=*hi).contains(q))
                && c.wheel_velocity_radps
                    .iter()
                    .zip(&bounds.wheel_velocity_radps)
                    .all(|(w, max)| w.abs() <= *max)
        };
        for (tick, commands) in self.commands.iter().enumerate() {
            if let Some(unit) = commands.iter().position(|c| !command_ok(c)) {
                return Err(format!(
                    "tick {tick}: unit {unit}'s command is beyond its joint or wheel-speed bounds"
                ));
            }
        }
        for (i, u) in self.units.iter().enumerate() {
            let r = &u.reference;
            let finite = command_ok(&u.command)
                && u.sensed.arm.position_rad.iter().all(|v| v.is_finite())
                && u.sensed.arm.velocity_radps.iter().all(|v| v.is_finite())
                && u.sensed.wheels.velocity_radps.iter().all(|v| v.is_finite())
                && (0.0..=1.0).contains(&u.last_t_max)
                && [
                    u.odometry,
                    u.phase_start_base,
                    u.sensed.base_pose,
                    r.peer_base_rest,
                ]
                .iter()
                .all(|p| p.x_m.is_finite() && p.y_m.is_finite() && p.yaw_rad.is_finite())
                && [r.ee_rest_in_base, r.peer_ee_rest_in_base]
                    .iter()
                    .all(|pose| {
                        pose.translation.vector.iter().all(|v| v.is_finite())
                            && pose.rotation.coords.iter().all(|v| v.is_finite())
                    });
            if !finite {
                return Err(format!(
                    "unit {i}'s onboard state holds a non-finite or impossible value"
                ));
            }
        }
        let truth = self
            .payload_position_m
            .iter()
            .chain(self.arm_position_rad.iter().flatten());
        if !truth.clone().all(|v| v.is_finite()) {
            return Err("the captured world holds a non-finite value".into());
        }
        Ok(())
    }

    /// How far `state` lies from the captured world: the payload's distance, m, and the
    /// largest arm joint difference, rad.
    pub fn distance_to(&self, state: &EnvState) -> (f64, f64) {
        let at = nalgebra::Vector3::from(self.payload_position_m);
        let payload = (state.payload.pose.translation.vector - at).norm();
        let mut joints: f64 = 0.0;
        for (unit, captured) in state.units.iter().zip(&self.arm_position_rad) {
            for (q, c) in unit.state.arm.position_rad.iter().zip(captured) {
                joints = joints.max((q - c).abs());
            }
        }
        (payload, joints)
    }
}

impl Env {
    /// The world of `handover`, rebuilt from its seed and replayed through the hand-over tick,
    /// checked against the captured truth; its resets restore the hand-over.
    pub fn replay(scene: &SceneModel, handover: &HandOver) -> Result<Env, SimError> {
        handover.check(scene).map_err(|reason| SimError::Config {
            field: "handover",
            reason,
        })?;
        let mut env = Env::new(scene, handover.world_seed, handover.env_options())?;
        for commands in &handover.commands {
            env.step(scene, commands);
        }
        let state = env.state(scene);
        let (payload_m, joint_rad) = handover.distance_to(&state);
        if !(payload_m <= REPLAY_TOLERANCE_M && joint_rad <= REPLAY_TOLERANCE_RAD) {
            return Err(SimError::Config {
                field: "handover",
                reason: format!(
                    "the replay of world {} ({} ticks) ends {payload_m:.4} m and {joint_rad:.4} \
                     rad from the captured world (tolerance {REPLAY_TOLERANCE_M} m, \
                     {REPLAY_TOLERANCE_RAD} rad): captured with other sim settings or payload \
                     files; capture again",
                    handover.world_seed,
                    handover.commands.len()
                ),
            });
        }
        env.rebase();
        Ok(env)
    }
}

/// Why a hand-over file cannot be used; names the file.
#[derive(Debug, thiserror::Error)]
#[error("hand-over file {}: {reason}", path.display())]
pub struct HandOverFileError {
    pub path: PathBuf,
    pub reason: String,
}

impl HandOverFile {
    pub fn new(handovers: Vec<HandOver>) -> Self {
        HandOverFile {
            format: FORMAT.into(),
            version: VERSION,
            handovers,
        }
    }

    /// Reads `path`, keeping the hand-overs into `phase`; an error without any.
    pub fn load(path: &Path, phase: Phase) -> Result<Vec<HandOver>, HandOverFileError> {
        let fail = |reason: String| HandOverFileError {
            path: path.to_owned(),
            reason,
        };
        let text = moonhaul_core::input::read_capped_text(path, MAX_FILE_BYTES).map_err(|e| {
            fail(format!(
                "{e} (`moonhaul sim handovers --out FILE` captures one; `cargo xtask \
                 train-all` makes the configs' runs/handovers/scripted.json)"
            ))
        })?;
        let de = &mut serde_json::Deserializer::from_str(&text);
        let file: HandOverFile = serde_path_to_error::deserialize(de)
            .map_err(|e| fail(format!("at `{}`: {}", e.path(), e.inner())))?;
        if file.format != FORMAT || file.version != VERSION {
            let mut format = file.format;
            moonhaul_core::input::clip_for_message(&mut format, 64);
            return Err(fail(format!(
                "format {format:?} version {}, expected {FORMAT:?} version {VERSION}",
                file.version
            )));
        }
        let total = file.handovers.len();
        let kept: Vec<HandOver> = file
            .handovers
            .into_iter()
            .filter(|h| h.phase == phase)
            .collect();
        if kept.is_empty() {
            return Err(fail(format!(
                "none of its {total} hand-overs is into {phase}"
            )));
        }
        Ok(kept)
    }
}

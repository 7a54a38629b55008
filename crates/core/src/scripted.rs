//! The scripted (model-based, non-learned) controller: settle, lift to a target height, drive a
//! distance, set the payload down and release.
//!
//! Two forms share one plan ([`MissionPlan`], `configs/mission.toml`) and one base tracking law
//! ([`MissionPlan::track`]):
//! - the simulator's time-scheduled mission (`moonhaul_sim::scripted`), which proves the
//!   physics before any learning and drives `moonhaul sim demo`;
//! - [`PhaseScript`], a controller of the deployed stack: driven by the phase gate like the
//!   policies, from what a unit knows onboard only (its encoders and odometry, the rest grasp's
//!   FK reference, the phase goal), its output turned into the paper's increment and passed
//!   through the same clamp ([`crate::action`]). It is the model-based baseline beside the
//!   policies, and the proof that gate, clamp and drives complete a mission.
//!
//! The arms move their end effectors straight up or down in their own base frames (IK on
//! core's FK, warm-started from the previous command) along a minimum-jerk profile, both by the
//! same amount, so the closed chain is never asked to stretch. The bases follow a reference
//! that moves along +X at a trapezoidal speed profile, each with a unicycle tracking law on
//! its along-track, cross-track and heading errors: driven open-loop, two rigidly coupled
//! bases drift apart within seconds (their wheels slip and load differently) and the grasps
//! would take the strain. Unit 1 faces −X, so it tracks the reference driving backwards.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::{self, in_range, positive, ConfigError, FieldError, Validate};
use crate::ik::{self, IkError, IkSettings};
use nalgebra::{UnitQuaternion, Vector2, Vector3};

use crate::observation::{ee_in_base, relative_pose, GraspReference, PhaseGoal};
use crate::state::{Phase, PlanarPose, PlanarVelocity, UnitCommand, UnitState, WHEEL_JOINTS};
use crate::task_config::VelocityProfile;
use crate::unit::UnitSpec;

/// Timing and geometry of the scripted mission: `configs/mission.toml`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MissionPlan {
    /// Time standing still before lifting, s.
    pub settle_s: f64,
    /// Lift of the end effectors, m (the paper's lift targets are 0.3, 0.5 and 0.75 m).
    pub lift_height_m: f64,
    pub lift_duration_s: f64,
    /// Pause after lifting and after driving, s.
    pub hold_s: f64,
    pub distance_m: f64,
    pub speed_mps: f64,
    pub accel_mps2: f64,
    /// Extra time holding the payload aloft after driving (long stability runs), s.
    pub carry_hold_s: f64,
    /// Time to lower the payload to `approach_height_m`, s.
    pub place_duration_s: f64,
    /// Lift at which the fast descent ends and the slow touchdown descent starts, m: enough
    /// to cover arm sag and terrain bumps.
    pub approach_height_m: f64,
    /// Descent speed below `approach_height_m`, m/s (the paper's touchdown speed is 0.03).
    pub touchdown_speed_mps: f64,
    /// How far the end effectors press once the payload rests, m: the scheduled mission aims
    /// this far below the start height, so the payload surely touches down on uneven ground;
    /// the onboard script descends until the chain stops, then keeps its command this far
    /// below the sensed end effector, the press its touchdown is detected by
    /// ([`crate::touchdown`]; more than `tasks.toml [place] contact_press_m`).
    pub place_press_m: f64,
    /// Time after release until the mission ends, s.
    pub after_release_s: f64,
    /// Placement releases the grasps once the payload has touched the ground this long, s
    /// (or at the end of the placement at the latest).
    pub release_after_contact_s: f64,
    /// Base tracking gains: along-track 1/s, heading 1/s, cross-track rad/(m·s).
    pub along_gain_per_s: f64,
    pub heading_gain_per_s: f64,
    pub cross_gain_per_ms: f64,
    /// Compliance of the onboard scripted controller's arm targets to the closed chain (its
    /// admittance gain), per tick, 0–1: each tick, this fraction of the sensed end effector's
    /// horizontal and rotational deviation from the last command is added to the target. Two
    /// units carry one rigid payload on bases whose odometry drifts apart (wheel slip) and
    /// whose arms disagree slightly about its attitude; what the chain imposes is followed,
    /// not fought. Height stays commanded. 0 is a rigid target.
    pub comply_gain_per_tick: f64,
    /// Largest *shared* rotation the compliance may follow, degrees: the payload's attitude as
    /// both units see it (the mean of the two arms' FK views). Beyond it the drives resist:
    /// following the shared rotation without bound would follow the payload's own weight (an
    /// off-centre load tips itself about the grasp line, measured 58°) instead of resisting it.
    /// Once the payload rests on the ground in place (the script presses), the ground holds its
    /// attitude and the shared part is followed up to `comply_max_internal_rotation_deg` too.
    pub comply_max_rotation_deg: f64,
    /// Largest *internal* rotation the compliance may follow, degrees: half the two arms'
    /// disagreement about the payload's attitude (own view minus the peer's, from its published
    /// joints). One rigid payload has one attitude; the views differ by the bases' unmeasured
    /// pitch and roll on uneven ground and their odometric yaw, and a wrist that resisted its
    /// share would fight the other through the payload. Followed fully up to this bound, which
    /// only guards against a peer's nonsense.
    pub comply_max_internal_rotation_deg: f64,
}

impl MissionPlan {
    /// Reads and validates a mission plan; errors name the file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// The shipped `configs/mission.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::load(config::repo_file("configs/mission.toml"))
    }
}

/// Longest phase or pause of the plan, s: anything longer than ten minutes is a typo.
const MAX_PHASE_S: f64 = 600.0;
/// Longest whole scripted mission, s.
const MAX_MISSION_S: f64 = 1800.0;

impl Validate for MissionPlan {
    fn validate(&self) -> Result<(), FieldError> {
        for (field, value) in [
            ("settle_s", self.settle_s),
            ("hold_s", self.hold_s),
            ("carry_hold_s", self.carry_hold_s),
            ("after_release_s", self.after_release_s),
            ("release_after_contact_s", self.release_after_contact_s),
        ] {
            in_range(field, value, 0.0, MAX_PHASE_S)?;
        }
        positive("lift_height_m", self.lift_height_m, 1.0)?;
        positive("lift_duration_s", self.lift_duration_s, MAX_PHASE_S)?;
        positive("distance_m", self.distance_m, 100.0)?;
        positive("speed_mps", self.speed_mps, 2.0)?;
        positive("accel_mps2", self.accel_mps2, 10.0)?;
        positive("place_duration_s", self.place_duration_s, MAX_PHASE_S)?;
        in_range(
            "approach_height_m",
            self.approach_height_m,
            0.0,
            self.lift_height_m,
        )?;
        positive("touchdown_speed_mps", self.touchdown_speed_mps, 1.0)?;
        in_range("place_press_m", self.place_press_m, 0.0, 0.1)?;
        positive("along_gain_per_s", self.along_gain_per_s, 100.0)?;
        positive("heading_gain_per_s", self.heading_gain_per_s, 100.0)?;
        positive("cross_gain_per_ms", self.cross_gain_per_ms, 100.0)?;
        in_range("comply_gain_per_tick", self.comply_gain_per_tick, 0.0, 1.0)?;
        in_range(
            "comply_max_rotation_deg",
            self.comply_max_rotation_deg,
            0.0,
            30.0,
        )?;
        in_range(
            "comply_max_internal_rotation_deg",
            self.comply_max_internal_rotation_deg,
            0.0,
            30.0,
        )?;
        // Each value may be in range and the mission still last for days: bound the whole.
        let duration_s = self.duration_s();
        if duration_s > MAX_MISSION_S {
            return Err(FieldError::new(
                "distance_m",
                format!(
                    "the plan lasts {duration_s:.0} s (distance / speed, descent / touchdown \
                     speed and every pause), more than {MAX_MISSION_S} s"
                ),
            ));
        }
        Ok(())
    }
}

/// Minimum-jerk progress 0 → 1 over τ ∈ [0, 1].
fn min_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

impl MissionPlan {
    /// The base reference's speed profile while driving.
    fn profile(&self) -> VelocityProfile {
        VelocityProfile {
            distance_m: self.distance_m,
            speed_mps: self.speed_mps,
            accel_mps2: self.accel_mps2,
        }
    }

    fn drive_s(&self) -> f64 {
        self.profile().duration_s()
    }

    /// Start times of lift, hold, transport, hold, place, and the release time.
    fn schedule(&self) -> [f64; 6] {
        let lift = self.settle_s;
        let hold1 = lift + self.lift_duration_s;
        let drive = hold1 + self.hold_s;
        let hold2 = drive + self.drive_s();
        let place = hold2 + self.hold_s + self.carry_hold_s;
        let slow_s = (self.approach_height_m + self.place_press_m) / self.touchdown_speed_mps;
        [
            lift,
            hold1,
            drive,
            hold2,
            place,
            place + self.place_duration_s + slow_s,
        ]
    }

    /// Total mission time, s.
    pub fn duration_s(&self) -> f64 {
        self.schedule()[5] + self.after_release_s
    }

    /// Distance the base reference has covered at time `t`, m (the integral of the speed
    /// profile of [`MissionPlan::at`]).
    pub fn travelled_m(&self, t: f64) -> f64 {
        let [_, _, drive, ..] = self.schedule();
        self.profile().travelled_at(t - drive)
    }

    /// Phase, end-effector lift (m) and base ground speed (m/s) at time `t`.
    pub fn at(&self, t: f64) -> (Phase, f64, f64) {
        let [lift, hold1, drive, hold2, place, release] = self.schedule();
        if t < lift {
            (Phase::Idle, 0.0, 0.0)
        } else if t < hold1 {
            (
                Phase::Lift,
                self.lift_height_m * min_jerk((t - lift) / self.lift_duration_s),
                0.0,
            )
        } else if t < drive {
            (Phase::Lift, self.lift_height_m, 0.0)
        } else if t < hold2 {
            (
                Phase::Transport,
                self.lift_height_m,
                self.profile().speed_at(t - drive),
            )
        } else if t < place {
            (Phase::Transport, self.lift_height_m, 0.0)
        } else if t < place + self.place_duration_s {
            let depth = self.lift_height_m - self.approach_height_m;
            let s = min_jerk((t - place) / self.place_duration_s);
            (Phase::Place, self.lift_height_m - depth * s, 0.0)
        } else if t < release {
            let slow = t - place - self.place_duration_s;
            (
                Phase::Place,
                self.approach_height_m - self.touchdown_speed_mps * slow,
                0.0,
            )
        } else {
            (Phase::Idle, -self.place_press_m, 0.0)
        }
    }

    /// When the grasps are released, s.
    pub fn release_s(&self) -> f64 {
        self.schedule()[5]
    }
}

impl MissionPlan {
    /// Wheel speeds (left, right) that steer a base at `pose` onto its reference: `start` moved
    /// `travelled_m` along +X at `speed_mps`. Corrections are capped at `cap_mps` (the cruise
    /// speed), so a base that slipped behind catches up at most at twice the speed instead of
    /// spinning its wheels.
    pub fn track(
        &self,
        spec: &UnitSpec,
        start: &PlanarPose,
        pose: &PlanarPose,
        travelled_m: f64,
        speed_mps: f64,
        cap_mps: f64,
    ) -> [f64; WHEEL_JOINTS] {
        let (dx, dy) = (start.x_m + travelled_m - pose.x_m, start.y_m - pose.y_m);
        let (sin, cos) = pose.yaw_rad.sin_cos();
        let along = dx * cos + dy * sin;
        let cross = -dx * sin + dy * cos;
        let heading = crate::observation::wrap_angle(start.yaw_rad - pose.yaw_rad);
        // The reference moves along +X; in the base's own frame that is ±forward.
        let forward_ref = speed_mps * cos.signum();
        let v = forward_ref + (self.along_gain_per_s * along).clamp(-cap_mps, cap_mps);
        let yaw_cap = cap_mps / spec.half_track_m();
        let yaw_rate = (self.heading_gain_per_s * heading
            + self.cross_gain_per_ms * cross * if forward_ref < 0.0 { -1.0 } else { 1.0 })
        .clamp(-yaw_cap, yaw_cap);
        spec.wheel_velocities(&PlanarVelocity {
            forward_mps: v,
            yaw_rate_radps: yaw_rate,
        })
    }

    /// Lift of the end effectors `t_s` into a placement that starts at `from_m`, m:
    /// minimum-jerk down to `approach_height_m` over `place_duration_s`, then on down at
    /// `touchdown_speed_mps` (the ground under the goal may lie lower than under the start;
    /// the caller stops the descent where the chain does).
    fn place_lift_m(&self, from_m: f64, t_s: f64) -> f64 {
        let approach = self.approach_height_m.min(from_m);
        if t_s < self.place_duration_s {
            from_m - (from_m - approach) * min_jerk(t_s / self.place_duration_s)
        } else {
            let slow = t_s - self.place_duration_s;
            approach - self.touchdown_speed_mps * slow
        }
    }
}

/// What the onboard scripted controller is given each tick: only what a unit knows.
#[derive(Debug, Clone, Copy)]
pub struct ScriptInput<'a> {
    pub spec: &'a UnitSpec,
    /// The committed phase (never Idle: the gate holds there) and its age, s.
    pub phase: Phase,
    pub phase_time_s: f64,
    /// The rest grasp captured when the lift began.
    pub reference: &'a GraspReference,
    /// Own encoders, and the base pose by odometry.
    pub own: &'a UnitState,
    /// The peer's last published state (its encoders and odometric base pose): its arm's view
    /// of the payload's attitude.
    pub peer: &'a UnitState,
    /// Own odometric base pose when the phase began.
    pub phase_start_base: &'a PlanarPose,
    pub goal: &'a PhaseGoal,
    /// The transport's velocity profile (the goal's v_cmd follows it).
    pub profile: &'a VelocityProfile,
    /// U_{k−1}: IK is warm-started from it.
    pub previous: &'a UnitCommand,
    /// This unit's gripper has opened.
    pub grasp_open: bool,
}

/// The scripted controller as a controller of the deployed stack; see the module docs. One per
/// unit; [`PhaseScript::command`] gives the absolute command it wants, which the caller turns
/// into the bounded increment ([`crate::action::ActionMap::toward`]).
#[derive(Debug, Clone)]
pub struct PhaseScript {
    plan: MissionPlan,
    ik: IkSettings,
    /// The lift the script asked for last tick, m: transport holds it, place descends from it.
    lift_m: f64,
    /// The targets' accumulated compliance, in the base frame: horizontal offset (m), and the
    /// rotation vectors (rad) of the attitude both units share and of their disagreement.
    comply_xy_m: Vector2<f64>,
    comply_shared_rotation: Vector3<f64>,
    comply_internal_rotation: Vector3<f64>,
    place_from_m: f64,
    /// In place, the chain stopped the descent: the ground carries the payload.
    pressing: bool,
    phase: Phase,
}

impl PhaseScript {
    pub fn new(plan: MissionPlan) -> Self {
        PhaseScript {
            plan,
            // A tenth of a millimetre and a milliradian: far inside the clamp's tolerances and
            // the drives' tracking, reached in a few iterations from last tick's command (the
            // default's 1 µm is for the grasp solutions, which every lift path starts from).
            ik: IkSettings {
                tolerance_m: 1e-4,
                tolerance_rad: 1e-3,
                ..IkSettings::default()
            },
            lift_m: 0.0,
            place_from_m: 0.0,
            pressing: false,
            comply_xy_m: Vector2::zeros(),
            comply_shared_rotation: Vector3::zeros(),
            comply_internal_rotation: Vector3::zeros(),
            phase: Phase::Idle,
        }
    }

    /// A script taking over `phase` already under way with its end effectors `lift_m` above
    /// the rest grasp (a lifted training start, a hand-over from another controller): transport
    /// holds that lift, place descends from it; lift starts from rest whatever `lift_m`.
    pub fn resume(plan: MissionPlan, phase: Phase, lift_m: f64) -> Self {
        let mut script = Self::new(plan);
        if phase != Phase::Lift {
            script.phase = phase;
            script.lift_m = lift_m;
            script.place_from_m = lift_m;
        }
        script
    }

    /// The command the script wants this tick.
    pub fn command(&mut self, input: &ScriptInput) -> Result<UnitCommand, IkError> {
        if input.phase != self.phase {
            match input.phase {
                Phase::Lift => {
                    self.lift_m = 0.0;
                    self.comply_xy_m = Vector2::zeros();
                    self.comply_shared_rotation = Vector3::zeros();
                    self.comply_internal_rotation = Vector3::zeros();
                }
                Phase::Place => {
                    self.place_from_m = self.lift_m;
                    self.pressing = false;
                }
                Phase::Transport | Phase::Idle => {}
            }
            self.phase = input.phase;
        }
        // Released, the arm holds still until the mission ends: there is no chain left to
        // comply with, and a free wrist following its own drift would carry the lift
        // estimate (the payload's point through the grasp, up to 0.5 m away) above the gate's
        // resting height, so the placement never completes (measured with a 1 m load).
        if input.grasp_open && input.phase == Phase::Place {
            return Ok(UnitCommand {
                wheel_velocity_radps: [0.0; WHEEL_JOINTS],
                arm_position_rad: input.previous.arm_position_rad,
            });
        }
        let p = &self.plan;
        let t = input.phase_time_s;
        let sensed = ee_in_base(input.spec, &input.own.arm.position_rad)?;
        let rest = &input.reference.ee_rest_in_base;
        let mut wheels = [0.0; WHEEL_JOINTS];
        self.lift_m = match input.phase {
            Phase::Lift => {
                // The plan's lift duration is for its lift height; higher goals take longer,
                // by the square root of the height ratio: at the same pace the paper's 0.75 m
                // would take 10 s, past the 8 s lift episode the expert labels training in
                // (`tasks.toml [lift] duration_s`); this way 6.3 s, its peak end-effector
                // speed 0.22 m/s, a third of the increment bound's. Deployed lifts aim at the
                // plan's height and are unchanged.
                let h = input.goal.height_m;
                let duration_s = p.lift_duration_s * (h / p.lift_height_m).max(1.0).sqrt();
                h * min_jerk(t / duration_s)
            }
            Phase::Transport => {
                let profile = input.profile;
                wheels = p.track(
                    input.spec,
                    input.phase_start_base,
                    &input.own.base_pose,
                    profile.travelled_at(t),
                    profile.speed_at(t),
                    profile.speed_mps,
                );
                self.lift_m
            }
            // Once the ground carries the payload the end effectors stop: press on them by
            // `place_press_m`, no more (the drives would strain and the clamp stop the team).
            // Only in the slow touchdown descent: in the fast one the arms lag their command
            // by about as much, and the bound would slow it to a press the touchdown rule
            // cannot tell from contact. The bound stops the descent and never raises it: once
            // the ground carries the load, the drives' gravity feed-forward (sized for half the
            // payload) pushes the end effector up past its command, and a command following the
            // sensed height up lifted one end of a long heavy load off the ground, tipping it
            // 12° and never releasing (measured, tests/data/payload_long_heavy.urdf).
            Phase::Place if t >= p.place_duration_s => {
                let planned = p.place_lift_m(self.place_from_m, t);
                let pressed = sensed.translation.z - rest.translation.z - p.place_press_m;
                self.pressing |= pressed > planned;
                planned.max(pressed).min(self.lift_m)
            }
            Phase::Place => p.place_lift_m(self.place_from_m, t),
            Phase::Idle => self.lift_m,
        };
        // Admittance: follow the chain where it moved the arm away from its last command.
        let commanded = ee_in_base(input.spec, &input.previous.arm_position_rad)?;
        let g = p.comply_gain_per_tick;
        let moved = sensed.translation.vector - commanded.translation.vector;
        self.comply_xy_m += g * moved.xy();
        // Attitude: the payload's rotation since the rest grasp by FK of each arm, the peer's
        // turned into this base frame by the bases' relative yaw (small rotations: the vectors
        // add). The shared part (their mean) is followed up to `comply_max_rotation_deg`, the
        // internal part (half their difference, opposite on the two units) up to the internal
        // bound; each target low-passes what the chain imposes at the admittance gain.
        let own_turn = (sensed.rotation * rest.rotation.inverse()).scaled_axis();
        let peer_sensed = ee_in_base(input.spec, &input.peer.arm.position_rad)?;
        let peer_rest = &input.reference.peer_ee_rest_in_base;
        let peer_yaw = relative_pose(&input.own.base_pose, &input.peer.base_pose).yaw_rad;
        let peer_turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), peer_yaw)
            * (peer_sensed.rotation * peer_rest.rotation.inverse()).scaled_axis();
        let internal = 0.5 * (own_turn - peer_turn);
        let shared = own_turn - internal;
        let internal_max_rad = p.comply_max_internal_rotation_deg.to_radians();
        let shared_max_rad = if self.pressing {
            internal_max_rad
        } else {
            p.comply_max_rotation_deg.to_radians()
        };
        let follow = |comply: Vector3<f64>, sensed: Vector3<f64>, max_rad: f64| {
            (comply + g * (sensed - comply)).cap_magnitude(max_rad)
        };
        self.comply_shared_rotation = follow(self.comply_shared_rotation, shared, shared_max_rad);
        self.comply_internal_rotation =
            follow(self.comply_internal_rotation, internal, internal_max_rad);
        let mut target = *rest;
        target.translation.vector +=
            Vector3::new(self.comply_xy_m.x, self.comply_xy_m.y, self.lift_m);
        target.rotation = UnitQuaternion::from_scaled_axis(
            self.comply_shared_rotation + self.comply_internal_rotation,
        ) * target.rotation;
        let in_chain = input.spec.ground_to_base().inverse() * target;
        // Where the target lies beyond a joint limit (the box's grasp sits at two), the arm
        // goes as far as the limits allow; the clamp judges the result like any other.
        let arm = match ik::solve(
            &input.spec.arm,
            &in_chain,
            &input.previous.arm_position_rad,
            &self.ik,
        ) {
            Ok(q) | Err(IkError::NotReached { best_q: q, .. }) => q,
            Err(e) => return Err(e),
        };
        Ok(UnitCommand {
            wheel_velocity_radps: wheels,
            arm_position_rad: arm,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::repo_file;

    #[test]
    fn bad_plans_are_named_by_file_and_field() {
        let path = repo_file("configs/mission.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let cases = [
            ("speed_mps = 0.2", "speed_mps = 0.0", "speed_mps"),
            ("speed_mps = 0.2", "speed_mps = 1e-6", "distance_m"),
            ("distance_m = 2.0", "distance_m = -2.0", "distance_m"),
            (
                "lift_height_m = 0.3",
                "lift_height_m = nan",
                "lift_height_m",
            ),
            ("hold_s = 1.0", "hold_s = 1e9", "hold_s"),
            (
                "approach_height_m = 0.04",
                "approach_height_m = 0.5",
                "approach_height_m",
            ),
            (
                "settle_s = 1.0",
                "settle_s = 1.0\nsettle_time = 2.0",
                "settle_time",
            ),
        ];
        for (from, to, field) in cases {
            assert!(text.contains(from), "{from}");
            let err = config::parse::<MissionPlan>(&text.replace(from, to), &path).unwrap_err();
            let message = err.to_string();
            assert!(
                message.contains(field) && message.contains("mission.toml"),
                "{field}: {message}"
            );
        }
    }

    /// Arm joints whose end effector is `rest` (in the base frame) turned by `turn` about the
    /// base's axes.
    fn turned(spec: &UnitSpec, q_rest: &[f64; 7], turn: Vector3<f64>) -> [f64; 7] {
        let mut target = ee_in_base(spec, q_rest).unwrap();
        target.rotation = UnitQuaternion::from_scaled_axis(turn) * target.rotation;
        let in_chain = spec.ground_to_base().inverse() * target;
        ik::solve(&spec.arm, &in_chain, q_rest, &IkSettings::default()).unwrap()
    }

    /// Where the script's commands settle against an arm the chain holds turned by
    /// `own_turn` while the peer's is turned by `peer_turn` (each about its own base axes):
    /// the commanded attitude's angle from the rest grasp, degrees.
    fn settled_command_deg(own_turn: Vector3<f64>, peer_turn: Vector3<f64>) -> f64 {
        let spec = UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap();
        let plan = MissionPlan::shipped().unwrap();
        let q_rest = [0.3, 0.5, -0.1, 1.2, 0.0, 0.7, 0.1];
        let at = UnitState::at;
        let own_rest = at(0.0, -0.8, 0.0, q_rest);
        let peer_rest = at(0.0, 0.8, std::f64::consts::PI, q_rest);
        let reference = GraspReference::capture(&spec, &own_rest, &peer_rest).unwrap();
        let own = at(0.0, -0.8, 0.0, turned(&spec, &q_rest, own_turn));
        let peer = at(
            0.0,
            0.8,
            std::f64::consts::PI,
            turned(&spec, &q_rest, peer_turn),
        );
        let mut script = PhaseScript::new(plan);
        let mut previous = UnitCommand {
            arm_position_rad: q_rest,
            ..Default::default()
        };
        for tick in 0..300 {
            let input = ScriptInput {
                spec: &spec,
                phase: Phase::Lift,
                phase_time_s: 10.0 + tick as f64 * 0.02,
                reference: &reference,
                own: &own,
                peer: &peer,
                phase_start_base: &own_rest.base_pose,
                goal: &PhaseGoal::default(),
                profile: &VelocityProfile {
                    distance_m: 1.0,
                    speed_mps: 0.2,
                    accel_mps2: 0.2,
                },
                previous: &previous,
                grasp_open: false,
            };
            previous = script.command(&input).unwrap();
        }
        let commanded = ee_in_base(&spec, &previous.arm_position_rad).unwrap();
        let rest = reference.ee_rest_in_base;
        (commanded.rotation * rest.rotation.inverse())
            .angle()
            .to_degrees()
    }

    /// The two arms' views of one payload's attitude differ by the bases' unmeasured tilt: a
    /// wrist follows its half of the disagreement beyond `comply_max_rotation_deg` (it would
    /// fight the other wrist through the payload), while a tip both arms see — the payload's
    /// own weight — is followed only up to that bound.
    #[test]
    fn the_wrists_follow_their_disagreement_and_resist_a_shared_tip() {
        let plan = MissionPlan::shipped().unwrap();
        let roll = Vector3::new(8f64.to_radians(), 0.0, 0.0);
        // Own arm turned 8°, the peer's level: 4° of it is the disagreement, 4° shared (3° of
        // which is followed).
        let disagreeing = settled_command_deg(roll, Vector3::zeros());
        let expected = 4.0 + plan.comply_max_rotation_deg;
        assert!(
            (disagreeing - expected).abs() < 0.3,
            "{disagreeing}° (expected {expected}°)"
        );
        // Both arms see the same 8° roll about the world's x axis (the peer faces −X, so about
        // its own x it is −8°): all shared, followed up to the bound.
        let shared = settled_command_deg(roll, -roll);
        let bound = plan.comply_max_rotation_deg;
        assert!(
            (shared - bound).abs() < 0.3,
            "{shared}° (expected {bound}°)"
        );
    }

    /// In the slow touchdown descent the press bound stops the command where the chain
    /// stopped, and never raises it when the drives push the end effector up (the ground
    /// carries the load the gravity feed-forward still lifts); once the gripper opens the arm
    /// holds its last command and the wheels stop.
    #[test]
    fn touchdown_never_raises_the_command_and_a_released_arm_holds() {
        let spec = UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap();
        let plan = MissionPlan::shipped().unwrap();
        let q_rest = [0.3, 0.5, -0.1, 1.2, 0.0, 0.7, 0.1];
        let rest_state = UnitState::at(0.0, 0.0, 0.0, q_rest);
        let peer_state = UnitState::at(0.0, 1.6, std::f64::consts::PI, q_rest);
        let reference = GraspReference::capture(&spec, &rest_state, &peer_state).unwrap();
        let rest = reference.ee_rest_in_base;
        // The end effector pushed up from 2 cm to 6 cm above its rest height, tick by tick.
        let raised = |dz: f64| {
            let mut target = rest;
            target.translation.z += dz;
            let in_chain = spec.ground_to_base().inverse() * target;
            let mut s = rest_state;
            s.arm.position_rad =
                ik::solve(&spec.arm, &in_chain, &q_rest, &IkSettings::default()).unwrap();
            s
        };
        let profile = VelocityProfile {
            distance_m: 1.0,
            speed_mps: 0.2,
            accel_mps2: 0.2,
        };
        let mut script = PhaseScript::new(plan);
        let mut previous = UnitCommand {
            arm_position_rad: q_rest,
            ..Default::default()
        };
        // The slow descent `after_s` in, the own arm at `own`.
        let mut command =
            |own: &UnitState, after_s: f64, grasp_open: bool, previous: &UnitCommand| {
                script.command(&ScriptInput {
                    spec: &spec,
                    phase: Phase::Place,
                    phase_time_s: plan.place_duration_s + after_s,
                    reference: &reference,
                    own,
                    peer: &peer_state,
                    phase_start_base: &rest_state.base_pose,
                    goal: &PhaseGoal::default(),
                    profile: &profile,
                    previous,
                    grasp_open,
                })
            };
        let mut heights = Vec::new();
        for tick in 0..40 {
            let own = raised(0.02 + 0.001 * tick as f64);
            previous = command(&own, 0.02 * tick as f64, false, &previous).unwrap();
            heights.push(
                ee_in_base(&spec, &previous.arm_position_rad)
                    .unwrap()
                    .translation
                    .z,
            );
        }
        for pair in heights.windows(2) {
            assert!(pair[1] <= pair[0] + 2e-4, "the command rose: {heights:?}");
        }
        let held = command(&raised(0.08), 1.0, true, &previous).unwrap();
        assert_eq!(held.arm_position_rad, previous.arm_position_rad);
        assert_eq!(held.wheel_velocity_radps, [0.0; WHEEL_JOINTS]);
    }

    #[test]
    fn the_plan_lifts_drives_the_distance_and_comes_back_down() {
        let plan = MissionPlan::shipped().unwrap();
        let dt = 0.02;
        let steps = (plan.duration_s() / dt) as usize;
        let distance: f64 = (0..steps).map(|k| plan.at(k as f64 * dt).2 * dt).sum();
        assert!((distance - plan.distance_m).abs() < 0.01, "{distance}");
        let (phase, lift, _) = plan.at(plan.schedule()[1] + 0.1);
        assert_eq!((phase, lift), (Phase::Lift, plan.lift_height_m));
        assert_eq!(plan.at(plan.duration_s()).1, -plan.place_press_m);
        assert_eq!(min_jerk(0.5), 0.5);
        assert!((plan.travelled_m(plan.duration_s()) - plan.distance_m).abs() < 1e-9);
        let mid = plan.schedule()[2] + plan.drive_s() / 2.0;
        let numeric: f64 = (0..100_000)
            .map(|k| plan.at(k as f64 * mid / 1e5).2 * mid / 1e5)
            .sum();
        assert!((plan.travelled_m(mid) - numeric).abs() < 1e-3);
    }
}

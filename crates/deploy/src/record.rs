//! What a mission log records: one [`TickRecord`] per unit per control tick, and one
//! [`WorldFrame`] per simulated step of the world (the external tracker's ground truth, the
//! paper's OptiTrack, which no unit ever sees). Plain data shared by the writers (the daemon,
//! the world process) and the readers (`moonhaul log summary`, the integration tests, anyone
//! checking a logged command against the clamp independently).

use moonhaul_coord::message::RejectCounts;
use moonhaul_coord::HoldReason;
use moonhaul_core::stacked::StackedDistance;
use moonhaul_core::state::{Phase, UnitCommand, UnitState, ARM_JOINTS, WHEEL_JOINTS};
use serde::{Deserialize, Serialize};

/// One control tick of one unit, everything needed to replay its decision.
///
/// The tick fills one record in place every tick (`peer_age_us` keeps its capacity), so
/// recording does not allocate; encoding it for the log does, off the control path's critical
/// section (after the hardware write).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TickRecord {
    pub unit: usize,
    /// Ticks since the daemon started, from 1.
    pub tick: u64,
    /// The unit's (team-synchronized) clock at the tick, µs; the world's time in a simulated
    /// mission.
    pub stamp_us: u64,
    /// The committed phase.
    pub phase: Phase,
    /// Why the clamp issued a hold; `None` when it issued T(t_max).
    pub hold: Option<HoldReason>,
    /// t_max of the issued step (0 on a hold).
    pub t_max: f64,
    /// d of the issued step and the subsystem that binds it, when the clamp evaluated one.
    pub distance: Option<StackedDistance>,
    /// This unit's own d(U_{k-1}, Y_k) in tolerance units (how far its drives are from the
    /// command they were given); `None` when the pipeline did not run.
    pub tracking_d: Option<f64>,
    /// This unit's state from its own encoders and odometry.
    pub sensed: UnitState,
    /// The gate's payload-height estimate (mean FK lift of the cargo over the units), m;
    /// `None` before the mission's rest grasp is captured.
    pub payload_height_estimate_m: Option<f64>,
    /// The team's press, the touchdown signal (`moonhaul_core::touchdown`): the most any
    /// unit's sensed end effector stands above its command, m; `None` outside Place.
    pub press_m: Option<f64>,
    /// The gate's goal distance (the payload's: the units' mean odometric offset from their
    /// phase goals), m.
    pub goal_distance_m: f64,
    /// The clamp's inputs as this unit saw them, one entry per unit of the team: Y_k (the
    /// sensed states: its own, and each peer's newest published one) and S_k = U_{k-1} (its own
    /// last command, each peer's last published one, which is also that peer's F_k). With
    /// `target` and `issued` they let anyone recheck that the issued command lies in V_k.
    pub team_sensed: Vec<UnitState>,
    pub team_previous: Vec<UnitCommand>,
    /// Grasp force estimate the gate used, N (`None`: the hardware has no such sensing).
    pub grasp_force_n: Option<f64>,
    /// Whether this unit's gripper is commanded open.
    pub grasp_open: bool,
    /// The active policy's target F_k for this unit (the hold command on a hold).
    pub target: UnitCommand,
    /// What was written to the hardware: the clamp's T(t_max) or hold.
    pub issued: UnitCommand,
    /// Per unit of the team: age of its newest accepted state at this tick, µs (`None`: never
    /// heard, or this unit itself).
    pub peer_age_us: Vec<Option<u64>>,
    /// This unit's own latched fault, as text (drive, sensor, policy); borrowed while
    /// recording so a faulted tick does not allocate either.
    pub fault: Option<std::borrow::Cow<'static, str>>,
    /// Messages rejected since start, by reason.
    pub rejected: RejectCounts,
    /// Ticks since start whose work overran the control period.
    pub deadline_misses: u64,
    /// Time this tick's work took (hal read to hal write), µs.
    pub work_us: u64,
}

/// One world step in a simulated mission: ground truth, as an external motion-capture system
/// would log it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldFrame {
    /// Control ticks since the world started, from 0.
    pub tick: u64,
    /// Simulated time, µs.
    pub stamp_us: u64,
    /// Payload pose in the world frame: position m, orientation quaternion (x, y, z, w).
    pub payload_position_m: [f64; 3],
    pub payload_orientation_xyzw: [f64; 4],
    /// Height of the payload's underside above the ground beneath it, m.
    pub payload_height_m: f64,
    /// Payload tilt from upright, degrees.
    pub payload_tilt_deg: f64,
    pub payload_ground_contact: bool,
    /// Each unit's base pose in the world frame (same layout as the payload's).
    pub base_position_m: Vec<[f64; 3]>,
    pub base_orientation_xyzw: Vec<[f64; 4]>,
    /// Each unit's true joint positions, rad (wheels left, right; arm base to tip): where the
    /// world log's `/tf` draws its links. Absent from logs written before they were recorded.
    #[serde(default)]
    pub wheel_position_rad: Vec<[f64; WHEEL_JOINTS]>,
    #[serde(default)]
    pub arm_position_rad: Vec<[f64; ARM_JOINTS]>,
    /// The phase each unit reported with its last command (`None`: no command this step).
    pub unit_phase: Vec<Option<Phase>>,
    /// Whether each unit's gripper is still closed (its unit has not opened it). A grasp the
    /// simulator broke by overload stays closed, on nothing: only an opened gripper is a release.
    pub grasp_closed: Vec<bool>,
}

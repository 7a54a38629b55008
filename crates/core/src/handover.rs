//! What one unit's onboard tick holds when the phase gate hands the mission to the next phase:
//! the state a training episode needs to begin where deployment does (its U_{k−1}, its
//! pipeline's last step and hold count, its odometry and rest grasp), not settled with U = Y.
//! The deployed tick produces it (`moonhaul_deploy::tick::Onboard::hand_over`); the simulator's
//! phase tasks start from it (`moonhaul_sim::handover`).

use serde::{Deserialize, Serialize};

use crate::observation::GraspReference;
use crate::state::{PlanarPose, UnitCommand, UnitState};

/// One unit's onboard state after the tick at which its team committed to the new phase.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitHandOver {
    /// U_k issued at that tick: the next tick's U_{k−1}.
    pub command: UnitCommand,
    /// What the unit sensed at that tick and published to its peer (base pose by odometry).
    pub sensed: UnitState,
    /// t_max of the pipeline's step at that tick.
    pub last_t_max: f64,
    /// Whether that step held.
    pub last_held: bool,
    /// The hold rule's count: consecutive ticks the unit's own command stood beyond tolerance.
    pub beyond_ticks: u32,
    /// The unit's wheel odometry at that tick.
    pub odometry: PlanarPose,
    /// Where the new phase's goals are measured from: the odometry when the unit committed.
    pub phase_start_base: PlanarPose,
    /// The rest grasp the unit recorded when its lift began.
    pub reference: GraspReference,
}

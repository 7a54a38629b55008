//! The one action pipeline of a unit: controller increment a_k → raw target
//! F_k = U_{k−1} ⊕ Δ(U_{k−1}, a_k) ([`ActionMap::target`]) → synchronization clamp → U_k, with
//! the hold rule. The training environments, `moonhaul eval` and the onboard tick all call
//! [`ActionPipeline::step`]: what is trained is what flies.
//!
//! **The unit's view.** Unit i runs the clamp on the whole stacked state: for itself S = U_{k−1}
//! and F = its target; for each peer S = F = the command the peer last published (a peer's
//! target of this tick is unknowable onboard). Training runs one pipeline per unit in the same
//! way, so the clamp a policy learns under is the one it flies under.
//!
//! **The hold rule** (not in the paper, which only says "hold"): a hold stops the wheels and
//! keeps the arm at U_{k−1} ([`crate::clamp::hold_command`]), so a position servo keeps the
//! payload where it is. A hold is admissible only while U_{k−1} is within tolerance of the
//! sensed state; when it is not, the drives are still catching up, and the team waits for them.
//! If this unit's own d(U_{k−1}, Y_k) stays above 1 for `hold.tracking_stop_ticks` consecutive
//! ticks its drives cannot reach their command (blocked, overloaded, a fault the drive does not
//! report): the pipeline reports [`PipelineReport::tracking_lost`], the caller raises a safety
//! stop for it, and the hold re-anchors on the sensed joints ([`crate::clamp::anchor_command`])
//! so the servos stop pushing toward a command they cannot reach.

use moonhaul_core::action::ActionMap;
use moonhaul_core::state::{UnitCommand, UnitState, UNIT_ACTION_DIM};

use crate::clamp::{anchor_command, Clamp, ClampError, ClampInput, ClampReport, HoldReason};
use crate::config::{HoldConfig, SyncConfig};
use crate::model::UnitModel;

/// What one unit's controller asks for this tick.
#[derive(Debug, Clone, Copy)]
pub struct Increment<'a> {
    pub map: &'a ActionMap,
    /// a_k: the controller's increment on U_{k−1}, bounded by `map`.
    pub delta: &'a [f64; UNIT_ACTION_DIM],
}

/// The inputs of one pipeline step, one entry per unit of the team.
#[derive(Debug, Clone, Copy)]
pub struct PipelineInput<'a> {
    /// Y_k: sensed joints and base pose (own: this tick; peers: their last published state).
    pub sensed: &'a [UnitState],
    /// U_{k−1} (own: last issued; peers: their last published command).
    pub previous: &'a [UnitCommand],
    /// This unit's increment; `None` when the caller holds (then `hold` says why).
    pub increment: Option<Increment<'a>>,
}

/// What the pipeline did this tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PipelineReport {
    pub clamp: ClampReport,
    /// This unit's own d(U_{k−1}, Y_k) in tolerance units: how far its drives are from the
    /// command they were given (the clamp's distance of T(0) for this unit alone).
    pub tracking_d: f64,
    /// This tick, the own tracking distance had stayed above 1 for the configured ticks: the
    /// caller raises a safety stop; the hold issued is re-anchored on the sensed joints.
    pub tracking_lost: bool,
}

/// One unit's pipeline: the clamp of its team and the hold rule's state. Create once; a step
/// allocates nothing.
#[derive(Debug, Clone)]
pub struct ActionPipeline {
    clamp: Clamp,
    hold: HoldConfig,
    unit: usize,
    /// Consecutive ticks this unit's own U_{k−1} was beyond tolerance.
    beyond_ticks: u32,
    /// F_k per unit, reused every tick.
    targets: Vec<UnitCommand>,
}

impl ActionPipeline {
    pub fn new(
        model: UnitModel,
        config: &SyncConfig,
        period_s: f64,
        team_size: usize,
        unit: usize,
    ) -> Result<Self, ClampError> {
        let clamp = Clamp::new(model, config, period_s, team_size)?;
        if unit >= team_size {
            return Err(ClampError::UnitCount {
                what: "unit index",
                got: unit,
                expected: team_size,
            });
        }
        Ok(ActionPipeline {
            clamp,
            hold: config.hold,
            unit,
            beyond_ticks: 0,
            targets: vec![UnitCommand::default(); team_size],
        })
    }

    /// The unit this pipeline belongs to.
    pub fn unit(&self) -> usize {
        self.unit
    }

    /// F_k of this unit from the last step (U_{k−1} when it held).
    pub fn target(&self) -> &UnitCommand {
        &self.targets[self.unit]
    }

    /// Consecutive ticks, up to this one, that this unit's own U_{k−1} was beyond tolerance of
    /// its sensed state, over the hold rule's `tracking_stop_ticks` (1: the safety stop fires).
    pub fn tracking_stop_progress(&self) -> f64 {
        f64::from(self.beyond_ticks) / f64::from(self.hold.tracking_stop_ticks.max(1))
    }

    /// Forgets the hold rule's count (a new mission, or the drives were re-enabled).
    pub fn reset(&mut self) {
        self.beyond_ticks = 0;
    }

    /// The hold rule's count: consecutive ticks this unit's own U_{k−1} was beyond tolerance.
    pub fn beyond_ticks(&self) -> u32 {
        self.beyond_ticks
    }

    /// Continues a pipeline whose hold rule had counted `beyond_ticks` (a training episode
    /// that starts where a deployed mission handed over).
    pub fn resume(&mut self, beyond_ticks: u32) {
        self.beyond_ticks = beyond_ticks;
    }

    /// One tick: writes U_k of every unit into `issued` (only this unit's entry is meant to be
    /// sent to drives; the peers' are what this unit's clamp would have let them do).
    pub fn step(
        &mut self,
        input: &PipelineInput,
        hold: Option<HoldReason>,
        issued: &mut [UnitCommand],
    ) -> Result<PipelineReport, ClampError> {
        let own = self.unit;
        let (Some(sensed), Some(previous)) = (input.sensed.get(own), input.previous.get(own))
        else {
            return Err(ClampError::UnitCount {
                what: "sensed",
                got: input.sensed.len().min(input.previous.len()),
                expected: self.targets.len(),
            });
        };
        let tracking_d = self.tracking_distance(sensed, previous)?;
        self.beyond_ticks = if tracking_d > 1.0 {
            self.beyond_ticks.saturating_add(1)
        } else {
            0
        };
        let tracking_lost = self.beyond_ticks == self.hold.tracking_stop_ticks;
        if input.previous.len() == self.targets.len() {
            self.targets.copy_from_slice(input.previous);
        }
        let hold = match (hold, input.increment) {
            (Some(reason), _) => Some(reason),
            (None, Some(inc)) => {
                self.targets[own] = inc
                    .map
                    .target(self.clamp.model().spec(), previous, inc.delta);
                None
            }
            (None, None) => Some(HoldReason::Idle),
        };
        let clamp = self.clamp.step(
            &ClampInput {
                sensed: input.sensed,
                previous: input.previous,
                target: &self.targets,
            },
            hold,
            issued,
        )?;
        if tracking_lost {
            issued[own] = anchor_command(sensed);
        }
        Ok(PipelineReport {
            clamp,
            tracking_d,
            tracking_lost,
        })
    }

    /// d of this unit alone between the image of U_{k−1} and the sensed state: the clamp's
    /// T(0) term for this unit.
    fn tracking_distance(
        &self,
        sensed: &UnitState,
        previous: &UnitCommand,
    ) -> Result<f64, ClampError> {
        let model = self.clamp.model();
        let x = model.command_image(sensed, previous, self.clamp.control_period_s())?;
        let y = model.sensed_image(sensed)?;
        let (arm, base) = x.distances(&y, self.clamp.tolerances());
        Ok(arm.max(base))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clamp::hold_command;
    use crate::model::tests::shipped_unit;
    use moonhaul_core::state::{PlanarPose, ARM_JOINTS};

    const HOME: [f64; ARM_JOINTS] = [0.0, 0.3, 0.0, -1.8, 0.0, 2.1, 0.8];

    fn config() -> SyncConfig {
        SyncConfig::shipped().unwrap()
    }

    fn team() -> [UnitState; 2] {
        let mut a = UnitState::default();
        a.arm.position_rad = HOME;
        let mut b = a;
        b.base_pose = PlanarPose {
            x_m: 0.0,
            y_m: 1.5,
            yaw_rad: std::f64::consts::PI,
        };
        [a, b]
    }

    fn anchored(sensed: &[UnitState; 2]) -> [UnitCommand; 2] {
        sensed.map(|s| anchor_command(&s))
    }

    fn map() -> ActionMap {
        ActionMap {
            step: [0.1, 0.1, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01],
        }
    }

    #[test]
    fn an_increment_moves_the_previous_command_by_one_bounded_step() {
        let mut pipeline = ActionPipeline::new(shipped_unit(), &config(), 0.02, 2, 0).unwrap();
        let sensed = team();
        let previous = anchored(&sensed);
        let map = map();
        let mut delta = [0.0; UNIT_ACTION_DIM];
        delta[3] = 0.5; // bounded to 0.01 rad
        let mut issued = [UnitCommand::default(); 2];
        let report = pipeline
            .step(
                &PipelineInput {
                    sensed: &sensed,
                    previous: &previous,
                    increment: Some(Increment {
                        map: &map,
                        delta: &delta,
                    }),
                },
                None,
                &mut issued,
            )
            .unwrap();
        assert_eq!(report.clamp.t_max, 1.0);
        assert!(report.tracking_d < 1e-9 && !report.tracking_lost);
        assert!((issued[0].arm_position_rad[1] - (HOME[1] + 0.01)).abs() < 1e-12);
        // The peer's entry is its previous command (S = F).
        assert_eq!(issued[1], previous[1]);
    }

    #[test]
    fn a_hold_keeps_the_previous_command_and_a_drive_that_never_catches_up_stops_the_unit() {
        let config = config();
        let mut pipeline = ActionPipeline::new(shipped_unit(), &config, 0.02, 2, 0).unwrap();
        let sensed = team();
        // Unit 0's last command is 0.2 rad ahead on the shoulder: far beyond tolerance.
        let mut previous = anchored(&sensed);
        previous[0].arm_position_rad[1] += 0.2;
        let map = map();
        let delta = [0.0; UNIT_ACTION_DIM];
        let mut issued = [UnitCommand::default(); 2];
        let input = PipelineInput {
            sensed: &sensed,
            previous: &previous,
            increment: Some(Increment {
                map: &map,
                delta: &delta,
            }),
        };
        let n = config.hold.tracking_stop_ticks;
        for tick in 1..=n {
            let report = pipeline.step(&input, None, &mut issued).unwrap();
            assert!(report.tracking_d > 1.0);
            assert_eq!(report.clamp.hold, Some(HoldReason::NoAdmissibleStep));
            if tick < n {
                // Holding U_{k-1}: the payload is not let down while the drives catch up.
                assert!(!report.tracking_lost, "tick {tick}");
                assert_eq!(issued[0], hold_command(&previous[0]));
            } else {
                assert!(report.tracking_lost);
                assert_eq!(issued[0], anchor_command(&sensed[0]));
            }
        }
        // Once the drives are there again the count starts over and steps are admitted.
        let caught_up = anchored(&sensed);
        let report = pipeline
            .step(
                &PipelineInput {
                    previous: &caught_up,
                    ..input
                },
                None,
                &mut issued,
            )
            .unwrap();
        assert!(!report.tracking_lost && report.clamp.hold.is_none());
    }

    #[test]
    fn a_drive_that_catches_up_is_waited_for_without_a_stop() {
        let config = config();
        let mut pipeline = ActionPipeline::new(shipped_unit(), &config, 0.02, 2, 0).unwrap();
        let mut sensed = team();
        let mut previous = anchored(&sensed);
        previous[0].arm_position_rad[1] += 0.2;
        let target_q = previous[0].arm_position_rad[1];
        let mut issued = [UnitCommand::default(); 2];
        let mut held = 0;
        for _ in 0..(3 * config.hold.tracking_stop_ticks) {
            // A drive that closes 20 % of its error per tick (a servo of ~50 ms time constant).
            let q = &mut sensed[0].arm.position_rad[1];
            *q += 0.2 * (target_q - *q);
            let report = pipeline
                .step(
                    &PipelineInput {
                        sensed: &sensed,
                        previous: &previous,
                        increment: None,
                    },
                    Some(HoldReason::Idle),
                    &mut issued,
                )
                .unwrap();
            assert!(!report.tracking_lost);
            held += u32::from(report.tracking_d > 1.0);
            previous[0] = issued[0];
        }
        assert!(held > 0 && held < config.hold.tracking_stop_ticks, "{held}");
        assert_eq!(previous[0].arm_position_rad[1], target_q);
    }
}

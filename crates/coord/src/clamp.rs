//! The synchronization clamp (paper, Sec. V-B): issue the largest step toward the policies'
//! target that keeps every subsystem of the team within its tolerance of the sensed state.
//!
//! With S_k = U_{k-1} (last tick's commands) and F_k (this tick's target), for t ∈ [0, 1]:
//! - T(t, S_k, F_k) interpolates every unit's command in **joint space**: (1 − t)·S + t·F on the
//!   two wheel velocities and the seven arm joint positions. F_k = U_{k-1} ⊕ Δ(U_{k-1}, a_k) is
//!   formed by the caller from the controller's increment ([`moonhaul_core::action`], through
//!   [`crate::pipeline`]), ⊕ being addition in joint space.
//! - Admissibility is judged in **task space**. Each unit's commanded base pose is its sensed
//!   base pose integrated for one control period under the interpolated wheel velocities
//!   (differential drive); its commanded end-effector pose is that base pose · arm mount ·
//!   FK(interpolated arm joints). Y_k is the same image of the sensed joints and base pose.
//!   T(t) ∈ V_k iff d(X(t), Y_k) ≤ 1 with core's stacked metric d.
//! - t_max = max{t : T(t) ∈ V_k}. t = 1 is tried first (the common case: one evaluation).
//!   Otherwise d need not be monotone in t (a wheel velocity reversing sign, or a large joint
//!   move whose end effector sweeps through V_k), so t = j/M (M = `search.scan_cells`) is
//!   scanned downward; the first admissible scan point's cell is bisected to
//!   `search.bisection_tolerance`. A cell whose two ends are inadmissible may still hide a
//!   narrow admissible stretch: a Lipschitz bound on d along the path (from the commands'
//!   joint and wheel increments, the arm's reach and the tolerances) discards every cell that
//!   provably holds none, and a branch and bound searches the others, within
//!   `search.max_evaluations` evaluations per tick. The result is always admissible; it can
//!   fall short of the maximum only when that budget runs out, or by an admissible stretch
//!   lying inside the bisected cell above its first crossing.
//! - **Hold** when no t is admissible, or when the caller asks (safety stop σ, Idle, a pending
//!   phase change): every wheel is commanded to zero velocity and every arm to its previous
//!   command U_{k-1}. A position servo holding U_{k-1} keeps the payload where it is; commanding
//!   the sensed joints instead would lower the servo's setpoint by its tracking error every
//!   held tick and let a loaded arm sink. A hold is therefore not always inside V_k (U_{k-1}
//!   may itself be out of tolerance); [`crate::pipeline`] owns the rule for that case.

use crate::config::{SearchConfig, SyncConfig};
use crate::message::{StopReason, Transition};
use crate::model::UnitModel;
use moonhaul_core::kinematics::KinematicsError;
use moonhaul_core::stacked::{
    StackedDistance, StackedError, StackedState, SyncTolerances, UnitPoses,
};
use moonhaul_core::state::{UnitCommand, UnitState, WHEEL_JOINTS};
use nalgebra::{Isometry3, Vector2};

/// t and d(X(t), Y_k) at one point of the interpolation path.
#[derive(Debug, Clone, Copy)]
struct Sample {
    t: f64,
    d: StackedDistance,
}

/// Why the clamp issued a hold instead of T(t_max).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HoldReason {
    /// σ = 1.
    SafetyStop(StopReason),
    /// No phase policy is active.
    Idle,
    /// The team waits for every unit to agree on this phase change.
    PhasePending(Transition),
    /// Not even the previous command lies within V_k anywhere along the path.
    NoAdmissibleStep,
}

/// What the clamp did this tick; plain data for the mission log and the operator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClampReport {
    /// Why a hold was issued; `None` when T(t_max) was.
    pub hold: Option<HoldReason>,
    /// t_max of the issued step; 0 on a hold.
    pub t_max: f64,
    /// d to Y_k and the binding subsystem: of the issued step; of the previous command (t = 0)
    /// when no step was admissible, naming the subsystem already out of tolerance; `None` when
    /// the hold was requested (nothing evaluated).
    pub distance: Option<StackedDistance>,
}

/// The inputs of one clamp step, one entry per unit.
#[derive(Debug, Clone, Copy)]
pub struct ClampInput<'a> {
    /// Sensed state at tick k (arm joint positions and base pose are used).
    pub sensed: &'a [UnitState],
    /// S_k = U_{k-1}: the commands issued last tick.
    pub previous: &'a [UnitCommand],
    /// F_k: this tick's policy outputs.
    pub target: &'a [UnitCommand],
}

#[derive(Debug, thiserror::Error)]
pub enum ClampError {
    #[error("{what} has {got} units; the team has {expected}")]
    UnitCount {
        what: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("unit {unit}: {field} is not finite")]
    NonFinite { unit: usize, field: &'static str },
    #[error("control period {0} s must be finite and positive")]
    Period(f64),
    #[error("a team needs at least one unit")]
    EmptyTeam,
    #[error(transparent)]
    Config(#[from] moonhaul_core::config::FieldError),
    #[error(transparent)]
    Kinematics(#[from] KinematicsError),
    #[error(transparent)]
    Stacked(#[from] StackedError),
}

/// The hold command of one unit: arm at its previous command, wheels stopped.
pub fn hold_command(previous: &UnitCommand) -> UnitCommand {
    UnitCommand {
        wheel_velocity_radps: [0.0; WHEEL_JOINTS],
        arm_position_rad: previous.arm_position_rad,
    }
}

/// A hold anchored on what the unit senses: arm at its sensed joints, wheels stopped. The first
/// command a unit issues (it has no previous one), and the re-anchored hold after its drives
/// could not reach their command.
pub fn anchor_command(sensed: &UnitState) -> UnitCommand {
    UnitCommand {
        wheel_velocity_radps: [0.0; WHEEL_JOINTS],
        arm_position_rad: sensed.arm.position_rad,
    }
}

/// T(t, S, F) for one unit: (1 − t)·S + t·F per joint, exact at both ends.
pub fn interpolate_command(s: &UnitCommand, f: &UnitCommand, t: f64) -> UnitCommand {
    let lerp = |a: f64, b: f64| (1.0 - t) * a + t * b;
    UnitCommand {
        wheel_velocity_radps: std::array::from_fn(|j| {
            lerp(s.wheel_velocity_radps[j], f.wheel_velocity_radps[j])
        }),
        arm_position_rad: std::array::from_fn(|j| {
            lerp(s.arm_position_rad[j], f.arm_position_rad[j])
        }),
    }
}

/// The clamp of a team of N units, with its scratch preallocated; create once, then
/// [`Clamp::step`] every tick without allocating.
#[derive(Debug, Clone)]
pub struct Clamp {
    model: UnitModel,
    tolerances: SyncTolerances,
    search: SearchConfig,
    control_period_s: f64,
    /// Y_k.
    sensed: StackedState,
    /// The task-space image of the candidate T(t).
    candidate: StackedState,
    /// The last step's search spent its whole `search.max_evaluations` (its result may then
    /// fall short of the maximum; see the module docs).
    search_exhausted: bool,
}

impl Clamp {
    pub fn new(
        model: UnitModel,
        config: &SyncConfig,
        control_period_s: f64,
        team_size: usize,
    ) -> Result<Self, ClampError> {
        moonhaul_core::config::Validate::validate(config)?;
        if !(control_period_s.is_finite() && control_period_s > 0.0) {
            return Err(ClampError::Period(control_period_s));
        }
        if team_size == 0 {
            return Err(ClampError::EmptyTeam);
        }
        let rest = UnitPoses {
            arm: Isometry3::identity(),
            base_xy_m: Vector2::zeros(),
        };
        let team = StackedState {
            units: vec![rest; team_size],
        };
        Ok(Clamp {
            model,
            tolerances: config.tolerances,
            search: config.search,
            control_period_s,
            sensed: team.clone(),
            candidate: team,
            search_exhausted: false,
        })
    }

    /// Whether the last step's search for narrow admissible stretches ran out of its
    /// evaluation budget (a hold or a step short of t_max may then hide an admissible one).
    pub fn search_exhausted(&self) -> bool {
        self.search_exhausted
    }

    /// One tick: writes U_k for every unit into `issued` and reports t_max, d and the binding
    /// subsystem. `hold` is the caller's reason to hold regardless (σ, Idle, pending change).
    pub fn step(
        &mut self,
        input: &ClampInput,
        hold: Option<HoldReason>,
        issued: &mut [UnitCommand],
    ) -> Result<ClampReport, ClampError> {
        self.search_exhausted = false;
        self.check(input, issued.len())?;
        if let Some(reason) = hold {
            return Ok(self.hold(input, reason, None, issued));
        }
        for (y, s) in self.sensed.units.iter_mut().zip(input.sensed) {
            *y = self.model.sensed_image(s)?;
        }
        let full = self.distance_at(input, 1.0)?;
        if full.value <= 1.0 {
            return Ok(self.issue(input, 1.0, full, issued));
        }
        let lipschitz = self.lipschitz(input);
        let mut budget = self.search.max_evaluations;
        let cells = self.search.scan_cells;
        let mut upper = Sample { t: 1.0, d: full };
        for j in (0..cells).rev() {
            let t = f64::from(j) / f64::from(cells);
            let lower = Sample {
                t,
                d: self.distance_at(input, t)?,
            };
            let best = if lower.d.value <= 1.0 {
                Some(self.bisect(input, lower, upper)?)
            } else {
                self.island_top(input, lower, upper, lipschitz, &mut budget)?
            };
            self.search_exhausted = budget == 0;
            if let Some(best) = best {
                return Ok(self.issue(input, best.t, best.d, issued));
            }
            upper = lower;
        }
        Ok(self.hold(input, HoldReason::NoAdmissibleStep, Some(upper.d), issued))
    }

    /// A Lipschitz constant of t ↦ d(X(t), Y_k) on [0, 1]: no subsystem's normalized distance
    /// can change faster than its image moves divided by its tolerance.
    fn lipschitz(&self, input: &ClampInput) -> f64 {
        let tol = &self.tolerances;
        let theta_max_rad = tol.arm_rotation_deg.to_radians();
        let base_tol_m = tol.base_xy_m[0].min(tol.base_xy_m[1]);
        input
            .previous
            .iter()
            .zip(input.target)
            .map(|(from, to)| {
                let rates = self
                    .model
                    .image_rate_bounds(from, to, self.control_period_s);
                (rates.arm_translation_m / tol.arm_translation_m)
                    .max(rates.arm_rotation_rad / theta_max_rad)
                    .max(rates.base_m / base_tol_m)
            })
            .fold(0.0, f64::max)
    }

    /// The top of the highest admissible stretch strictly inside a scan cell whose two ends
    /// are inadmissible, if the Lipschitz bound lets one exist: an interior t can be admissible
    /// only if t ≥ lo.t + (d(lo) − 1)/L and t ≤ hi.t − (d(hi) − 1)/L. Intervals whose window is
    /// empty are discarded without evaluating d; others are split at the window's middle, upper
    /// half first. Each split costs one evaluation from `budget`; an exhausted budget ends the
    /// search (the cell is then treated as inadmissible: safe, possibly not maximal).
    fn island_top(
        &mut self,
        input: &ClampInput,
        lo: Sample,
        hi: Sample,
        lipschitz: f64,
        budget: &mut u32,
    ) -> Result<Option<Sample>, ClampError> {
        let window_lo = lo.t + (lo.d.value - 1.0) / lipschitz;
        let window_hi = hi.t - (hi.d.value - 1.0) / lipschitz;
        // A path along which d is constant (L = 0) gives a NaN window: discarded too.
        let window_open = window_lo.partial_cmp(&window_hi) == Some(std::cmp::Ordering::Less);
        if !window_open || *budget == 0 {
            return Ok(None);
        }
        *budget -= 1;
        let t = 0.5 * (window_lo + window_hi);
        let mid = Sample {
            t,
            d: self.distance_at(input, t)?,
        };
        if mid.d.value <= 1.0 {
            return self.bisect(input, mid, hi).map(Some);
        }
        if let Some(found) = self.island_top(input, mid, hi, lipschitz, budget)? {
            return Ok(Some(found));
        }
        self.island_top(input, lo, mid, lipschitz, budget)
    }

    /// Narrows [lo admissible, hi inadmissible] to `search.bisection_tolerance`; returns the
    /// admissible end.
    fn bisect(
        &mut self,
        input: &ClampInput,
        mut lo: Sample,
        mut hi: Sample,
    ) -> Result<Sample, ClampError> {
        while hi.t - lo.t > self.search.bisection_tolerance {
            let t = 0.5 * (lo.t + hi.t);
            let mid = Sample {
                t,
                d: self.distance_at(input, t)?,
            };
            if mid.d.value <= 1.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        Ok(lo)
    }

    /// d(X(t), Y_k): the task-space image of T(t) against the sensed stacked state.
    fn distance_at(&mut self, input: &ClampInput, t: f64) -> Result<StackedDistance, ClampError> {
        let commands = input.previous.iter().zip(input.target);
        for ((x, s), (prev, target)) in self
            .candidate
            .units
            .iter_mut()
            .zip(input.sensed)
            .zip(commands)
        {
            let command = interpolate_command(prev, target, t);
            *x = self
                .model
                .command_image(s, &command, self.control_period_s)?;
        }
        Ok(self.candidate.distance(&self.sensed, &self.tolerances)?)
    }

    /// The tolerances d is normalized by.
    pub fn tolerances(&self) -> &SyncTolerances {
        &self.tolerances
    }

    /// The unit model the images are computed on.
    pub fn model(&self) -> &UnitModel {
        &self.model
    }

    /// The period a command's base motion is integrated over, s.
    pub fn control_period_s(&self) -> f64 {
        self.control_period_s
    }

    fn issue(
        &self,
        input: &ClampInput,
        t_max: f64,
        d: StackedDistance,
        issued: &mut [UnitCommand],
    ) -> ClampReport {
        for (u, (s, f)) in issued
            .iter_mut()
            .zip(input.previous.iter().zip(input.target))
        {
            *u = interpolate_command(s, f, t_max);
        }
        ClampReport {
            hold: None,
            t_max,
            distance: Some(d),
        }
    }

    fn hold(
        &self,
        input: &ClampInput,
        reason: HoldReason,
        distance: Option<StackedDistance>,
        issued: &mut [UnitCommand],
    ) -> ClampReport {
        for (u, s) in issued.iter_mut().zip(input.previous) {
            *u = hold_command(s);
        }
        ClampReport {
            hold: Some(reason),
            t_max: 0.0,
            distance,
        }
    }

    /// Team sizes agree and every number used is finite; errors name the unit and field.
    fn check(&self, input: &ClampInput, issued: usize) -> Result<(), ClampError> {
        let expected = self.sensed.units.len();
        for (what, got) in [
            ("sensed", input.sensed.len()),
            ("previous", input.previous.len()),
            ("target", input.target.len()),
            ("issued", issued),
        ] {
            if got != expected {
                return Err(ClampError::UnitCount {
                    what,
                    got,
                    expected,
                });
            }
        }
        for (unit, ((s, p), f)) in input
            .sensed
            .iter()
            .zip(input.previous)
            .zip(input.target)
            .enumerate()
        {
            let b = &s.base_pose;
            let fields: [(&'static str, &[f64]); 6] = [
                ("sensed.arm.position_rad", &s.arm.position_rad),
                ("sensed.base_pose", &[b.x_m, b.y_m, b.yaw_rad]),
                ("previous.wheel_velocity_radps", &p.wheel_velocity_radps),
                ("previous.arm_position_rad", &p.arm_position_rad),
                ("target.wheel_velocity_radps", &f.wheel_velocity_radps),
                ("target.arm_position_rad", &f.arm_position_rad),
            ];
            if let Some((field, _)) = fields
                .iter()
                .find(|(_, v)| v.iter().any(|x| !x.is_finite()))
            {
                return Err(ClampError::NonFinite { unit, field });
            }
        }
        Ok(())
    }
}

/// What the clamp issued over many ticks (a mission, a training rollout, a unit log): the
/// figures its soundness is judged by. Sums, so tallies of batches and units merge.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ClampTally {
    /// Ticks counted.
    pub ticks: u64,
    /// Sum of the issued t_max (0 on a hold).
    pub t_max_sum: f64,
    /// Ticks that issued less than the full step (t_max < 1, holds included).
    pub clamped: u64,
    /// Ticks that issued a hold, for any reason.
    pub holds: u64,
    /// Of the holds, those for want of an admissible step.
    pub no_step: u64,
}

impl ClampTally {
    /// Counts one tick that issued `t_max` with `hold` (a [`ClampReport`]'s, or a log's).
    pub fn record(&mut self, t_max: f64, hold: Option<HoldReason>) {
        self.ticks += 1;
        self.t_max_sum += t_max;
        self.clamped += u64::from(t_max < 1.0);
        self.holds += u64::from(hold.is_some());
        self.no_step += u64::from(hold == Some(HoldReason::NoAdmissibleStep));
    }

    pub fn merge(&mut self, other: &ClampTally) {
        self.ticks += other.ticks;
        self.t_max_sum += other.t_max_sum;
        self.clamped += other.clamped;
        self.holds += other.holds;
        self.no_step += other.no_step;
    }

    /// `count` per tick; `None` before any tick.
    fn per_tick(&self, count: f64) -> Option<f64> {
        (self.ticks > 0).then(|| count / self.ticks as f64)
    }

    pub fn mean_t_max(&self) -> Option<f64> {
        self.per_tick(self.t_max_sum)
    }

    pub fn clamped_fraction(&self) -> Option<f64> {
        self.per_tick(self.clamped as f64)
    }

    pub fn hold_fraction(&self) -> Option<f64> {
        self.per_tick(self.holds as f64)
    }

    pub fn no_step_fraction(&self) -> Option<f64> {
        self.per_tick(self.no_step as f64)
    }
}

#[cfg(test)]
mod tests;

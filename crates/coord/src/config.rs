//! The coordination layer's settings: `configs/sync.toml` (clamp) and `configs/gate.toml`
//! (phase gate and team agreement), read by core's one loader ([`moonhaul_core::config`]):
//! every key required, the shipped files hold the paper's values (or, where the paper gives
//! none, the values their comments justify).

use moonhaul_core::config::{self, count, in_range, positive, section, FieldError, Validate};
use moonhaul_core::stacked::SyncTolerances;
use serde::Deserialize;
use std::path::Path;

pub use moonhaul_core::config::ConfigError;

/// `configs/sync.toml`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncConfig {
    pub tolerances: SyncTolerances,
    pub search: SearchConfig,
    pub hold: HoldConfig,
}

/// The rule when no step is admissible (not in the paper; see `configs/sync.toml` and
/// [`crate::pipeline`]).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HoldConfig {
    /// Consecutive ticks a unit's own last command may stay beyond the clamp's tolerance of
    /// its sensed state (d > 1: its drives cannot reach it) before it raises a safety stop.
    pub tracking_stop_ticks: u32,
}

/// How the clamp searches t_max (see `configs/sync.toml`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SearchConfig {
    /// Cells of the downward scan over t ∈ [0, 1].
    pub scan_cells: u32,
    /// Most evaluations of d the search for narrow admissible stretches inside inadmissible
    /// scan cells may spend in one tick.
    pub max_evaluations: u32,
    /// Width at which bisection of the bracketing cell stops: t_max's resolution.
    pub bisection_tolerance: f64,
}

/// `configs/gate.toml`: the measured events of the phase gate and the agreement window.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GateConfig {
    pub lift: LiftConfig,
    pub transport: TransportConfig,
    pub place: PlaceConfig,
    pub agreement: AgreementConfig,
}

/// Lift → Transport when payload height ≥ h_min.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiftConfig {
    /// h_min, m above the ground.
    pub payload_height_min_m: f64,
    /// Once asserted, the event stays asserted down to h_min − hysteresis.
    pub hysteresis_m: f64,
    pub debounce_ticks: u32,
}

/// Transport → Place when the payload's distance to the goal ≤ τ_place.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransportConfig {
    /// τ_place, m (horizontal distance of the payload to its goal).
    pub goal_distance_max_m: f64,
    /// Once asserted, the event stays asserted up to τ_place + hysteresis.
    pub hysteresis_m: f64,
    /// ω_stop, rad/s: the team counts as stopped once every unit's last commanded wheel speed
    /// is at most this.
    pub wheel_speed_max_radps: f64,
    pub wheel_speed_hysteresis_radps: f64,
    /// Ticks both conditions must hold together.
    pub debounce_ticks: u32,
}

/// Place → Idle when released: payload resting on the ground and every grasp unloaded.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaceConfig {
    /// Payload height above the ground at or below which it rests (h0_tol of Table II), m.
    pub payload_height_max_m: f64,
    pub height_hysteresis_m: f64,
    /// Largest grasp force, over all units, at or below which the grasps count as let go, N.
    pub grasp_force_max_n: f64,
    pub force_hysteresis_n: f64,
    pub debounce_ticks: u32,
}

/// How long the team may wait for a phase change to be proposed by every unit.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgreementConfig {
    pub pending_window_ticks: u32,
}

/// Who this unit is and how its team runs; the daemon fills it from `configs/unit.toml`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TeamSettings {
    /// Messages naming another team are rejected.
    pub team: String,
    pub team_size: usize,
    /// This unit's index, 0-based.
    pub unit_index: usize,
    pub control_period_us: u64,
    /// A peer whose latest state is older than this many control periods stops every unit.
    pub peer_staleness_periods: u32,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TeamError {
    #[error("team_size must be at least 1")]
    EmptyTeam,
    #[error("unit_index {index} is outside a team of {team_size}")]
    UnitIndex { index: usize, team_size: usize },
    #[error("team name must not be empty")]
    EmptyName,
    #[error("control_period_us must be positive")]
    ZeroPeriod,
    #[error("peer_staleness_periods must be at least 1")]
    ZeroStaleness,
}

impl TeamSettings {
    /// How far a unit accepts a message's `seq` ahead of its stamp, µs: the staleness bound
    /// plus one control period, what clock offset within the stamp bound and one tick of
    /// messages can explain (see [`crate::message`#replay-protection](crate::message#replay-protection)).
    pub fn seq_lead_us(&self) -> u64 {
        self.staleness_us().saturating_add(self.control_period_us)
    }

    /// The staleness bound in µs.
    pub fn staleness_us(&self) -> u64 {
        self.control_period_us
            .saturating_mul(self.peer_staleness_periods.into())
    }

    pub fn validate(&self) -> Result<(), TeamError> {
        if self.team_size == 0 {
            return Err(TeamError::EmptyTeam);
        }
        if self.unit_index >= self.team_size {
            return Err(TeamError::UnitIndex {
                index: self.unit_index,
                team_size: self.team_size,
            });
        }
        if self.team.is_empty() {
            return Err(TeamError::EmptyName);
        }
        if self.control_period_us == 0 {
            return Err(TeamError::ZeroPeriod);
        }
        if self.peer_staleness_periods == 0 {
            return Err(TeamError::ZeroStaleness);
        }
        Ok(())
    }
}

impl SyncConfig {
    /// Reads and validates a sync config.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        config::load(path)
    }

    /// The shipped `configs/sync.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::from_file(&config::repo_file("configs/sync.toml"))
    }
}

impl GateConfig {
    /// Reads and validates a gate config.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        config::load(path)
    }

    /// The shipped `configs/gate.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::from_file(&config::repo_file("configs/gate.toml"))
    }
}

/// Most debounce or agreement ticks: 20 s at 50 Hz; longer would never fire in a mission.
const MAX_TICKS: u64 = 1000;

impl Validate for SyncConfig {
    fn validate(&self) -> Result<(), FieldError> {
        section("tolerances", || self.tolerances.validate())?;
        section("search", || {
            let s = &self.search;
            // The scan and the branch and bound run every tick: bounded so a tick stays short.
            count("scan_cells", s.scan_cells.into(), 1, 4096)?;
            count("max_evaluations", s.max_evaluations.into(), 1, 100_000)?;
            positive("bisection_tolerance", s.bisection_tolerance, 0.5)
        })?;
        section("hold", || {
            count(
                "tracking_stop_ticks",
                self.hold.tracking_stop_ticks.into(),
                1,
                MAX_TICKS,
            )
        })
    }
}

impl Validate for GateConfig {
    fn validate(&self) -> Result<(), FieldError> {
        let (l, t, p) = (&self.lift, &self.transport, &self.place);
        section("lift", || {
            positive("payload_height_min_m", l.payload_height_min_m, 2.0)?;
            in_range("hysteresis_m", l.hysteresis_m, 0.0, 0.5)?;
            count("debounce_ticks", l.debounce_ticks.into(), 1, MAX_TICKS)
        })?;
        section("transport", || {
            positive("goal_distance_max_m", t.goal_distance_max_m, 10.0)?;
            in_range("hysteresis_m", t.hysteresis_m, 0.0, 1.0)?;
            positive("wheel_speed_max_radps", t.wheel_speed_max_radps, 100.0)?;
            in_range(
                "wheel_speed_hysteresis_radps",
                t.wheel_speed_hysteresis_radps,
                0.0,
                100.0,
            )?;
            count("debounce_ticks", t.debounce_ticks.into(), 1, MAX_TICKS)
        })?;
        section("place", || {
            in_range("payload_height_max_m", p.payload_height_max_m, 0.0, 1.0)?;
            in_range("height_hysteresis_m", p.height_hysteresis_m, 0.0, 0.5)?;
            in_range("grasp_force_max_n", p.grasp_force_max_n, 0.0, 1000.0)?;
            in_range("force_hysteresis_n", p.force_hysteresis_n, 0.0, 100.0)?;
            count("debounce_ticks", p.debounce_ticks.into(), 1, MAX_TICKS)
        })?;
        section("agreement", || {
            count(
                "pending_window_ticks",
                self.agreement.pending_window_ticks.into(),
                1,
                MAX_TICKS,
            )
        })?;
        // A payload that counts as lifted must not count as resting, or Place could end at once.
        if l.payload_height_min_m - l.hysteresis_m <= p.payload_height_max_m + p.height_hysteresis_m
        {
            return Err(FieldError::new(
                "lift.payload_height_min_m",
                "less lift.hysteresis_m must exceed place.payload_height_max_m + place.height_hysteresis_m",
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use moonhaul_core::config::repo_file;
    use std::path::PathBuf;

    #[test]
    fn shipped_configs_hold_the_papers_values() {
        let sync = SyncConfig::from_file(&repo_file("configs/sync.toml")).unwrap();
        assert_eq!(
            (
                sync.tolerances.arm_translation_m,
                sync.tolerances.arm_rotation_deg
            ),
            (0.03, 5.0)
        );
        assert_eq!(sync.tolerances.base_xy_m, [0.02, 0.02]);
        GateConfig::from_file(&repo_file("configs/gate.toml")).unwrap();
    }

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn bad_configs_name_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let sync = std::fs::read_to_string(repo_file("configs/sync.toml")).unwrap();
        let sync_cases = [
            (
                sync.replace("arm_translation_m = ", "arm_translation_mm = "),
                "arm_translation_mm",
            ),
            (
                sync.replace("arm_translation_m = 0.03", "arm_translation_m = -0.03"),
                "tolerances.arm_translation_m",
            ),
            (
                sync.replace("base_xy_m = [0.02, 0.02]", "base_xy_m = [0.02]"),
                "tolerances.base_xy_m",
            ),
            (
                sync.replace("base_xy_m = [0.02, 0.02]", "base_xy_m = [0.02, 0.02, 0.02]"),
                "tolerances.base_xy_m",
            ),
            (
                sync.replace("scan_cells = 64", "scan_cells = 0"),
                "search.scan_cells",
            ),
            (
                sync.replace("scan_cells = 64", "scan_cells = 4000000000"),
                "search.scan_cells",
            ),
            (
                sync.replace("bisection_tolerance = 1e-7", "bisection_tolerance = 0.0"),
                "search.bisection_tolerance",
            ),
            (sync.replace("max_evaluations = 200\n", ""), "search"),
        ];
        for (i, (text, field)) in sync_cases.into_iter().enumerate() {
            let path = write(dir.path(), &format!("bad_sync{i}.toml"), &text);
            let message = SyncConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains("bad_sync"),
                "{field}: {message}"
            );
        }
        let gate = std::fs::read_to_string(repo_file("configs/gate.toml")).unwrap();
        let gate_cases = [
            (gate.replace("payload_height_min_m", "h_min"), "h_min"),
            (
                gate.replace("payload_height_min_m = 0.27", "payload_height_min_m = nan"),
                "lift.payload_height_min_m",
            ),
            (
                gate.replace("payload_height_min_m = 0.27", "payload_height_min_m = 0.02"),
                "lift.payload_height_min_m",
            ),
            (
                gate.replace("goal_distance_max_m = 0.05", "goal_distance_max_m = 0.0"),
                "transport.goal_distance_max_m",
            ),
            (
                gate.replace("force_hysteresis_n = 1.0", "force_hysteresis_n = -1.0"),
                "place.force_hysteresis_n",
            ),
            (
                gate.replace("debounce_ticks = 25", "debounce_ticks = 0"),
                "place.debounce_ticks",
            ),
            (
                gate.replace("debounce_ticks = 25", "debounce_ticks = 4000000"),
                "place.debounce_ticks",
            ),
            (
                gate.replace("pending_window_ticks = 10", "pending_window_ticks = 0"),
                "agreement.pending_window_ticks",
            ),
        ];
        for (i, (text, field)) in gate_cases.into_iter().enumerate() {
            let path = write(dir.path(), &format!("bad_gate{i}.toml"), &text);
            let message = GateConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains("bad_gate"),
                "{field}: {message}"
            );
        }
        let missing = SyncConfig::from_file(&dir.path().join("absent.toml"))
            .unwrap_err()
            .to_string();
        assert!(missing.contains("absent.toml"), "{missing}");
    }
}

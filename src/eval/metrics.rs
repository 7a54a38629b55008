//! The paper's state-based simulation metrics (Results and Discussion, "Policy Performance in
//! Simulation"), computed from one episode's rows ([`EpisodeRow`], the columns of its CSV).
//! Every definition is below, so anyone can recompute the figures from the CSVs.
//!
//! # Shared definitions
//!
//! - The rows are used as given, all of them (the caller passes one phase's episode); they
//!   must be non-empty, with finite numbers and strictly increasing `t_s` (the rules of
//!   [`episode`](super::episode)), or the metric is a [`MetricError`].
//! - **Steady window**: the rows with `t_s >= t_last - STEADY_WINDOW_S` ([`STEADY_WINDOW_S`]
//!   = 1 s), `t_last` the last row's time: the last second, both ends included. An episode
//!   shorter than that is all steady window.
//! - **Steady tilt**: the arithmetic mean of `payload_tilt_deg` over the steady window.
//!   **Peak tilt**: the largest `payload_tilt_deg` over all rows. Tilt is in degrees.
//! - **Held**: both grasp forces of the last row are above [`HELD_FORCE_N`] (1 N): the units
//!   still hold the payload at the end.
//! - Tolerances are the paper's Table II (h_tol, ḣ_tol, θ_tol, p_tol, h0_tol), except the lift's
//!   final-height tolerance [`LIFT_SUCCESS_TOL_M`]. A tolerance comparison is `<=` in metres
//!   (m/s, degrees); the mm fields are those metres × 1000.
//!
//! # Lift ([`lift`])
//!
//! - `final_height_error_mm` = |mean `payload_height_m` over the steady window −
//!   `goal_height_m` of the last row| × 1000 (the paper's "final height tracking error").
//! - `peak_tilt_deg`, `steady_tilt_deg` as above (the paper's "peak transient tilt" and
//!   "steady-state tilt").
//! - `success` = held AND final height error ≤ [`LIFT_SUCCESS_TOL_M`] (0.05 m) AND steady tilt ≤
//!   [`TILT_TOL_DEG`] (θ_tol = 10°). Peak tilt does not count: the paper calls θ_tol a
//!   reward-shaping reference, not a bound, for the mid-lift transient.
//!
//! # Transport ([`transport`])
//!
//! - `rms_velocity_error_mps` = √(mean over all rows of (vx − cmd_vx)² + (vy − cmd_vy)²), with
//!   v = `payload_v{x,y}_mps` and cmd = `command_v{x,y}_mps` (the paper's "RMS velocity
//!   tracking error").
//! - `max_height_deviation_mm` = max over all rows of |`payload_height_m` − the first row's
//!   `payload_height_m`| × 1000 (the payload is "maintained at" its starting height).
//! - `steady_tilt_deg` as above.
//! - `travel_error_m` = |travelled − commanded|, travelled = ∫ `payload_vx_mps` dt and
//!   commanded = ∫ `command_vx_mps` dt, both by the trapezoidal rule over consecutive rows
//!   (Σ (t_{i+1} − t_i)(v_i + v_{i+1})/2; 0 for one row).
//! - `success` = held AND max height deviation ≤ [`HEIGHT_TOL_M`] (h_tol = 0.03 m) AND travel
//!   error ≤ [`POSITION_TOL_M`] (p_tol = 0.20 m).
//!
//! # Place ([`place`])
//!
//! - `final_height_error_mm` = |mean `payload_height_m` over the steady window| × 1000: the
//!   reference is the ground, height 0 (the paper's error "relative to the ground reference").
//! - **Touchdown**: the first row with `ground_contact` = 1 that comes after at least one row
//!   with `ground_contact` = 0. `touched_down` says whether there is one.
//! - `touchdown_speed_mps` = |`payload_vz_mps`| at the touchdown row (the paper's "impact
//!   velocity at contact"); without a touchdown, |`payload_vz_mps`| of the last row.
//! - `peak_tilt_deg`, `steady_tilt_deg` as above (the steady window is after contact when the
//!   payload has settled for a second).
//! - `success` = touched down AND final height error ≤ [`FINAL_HEIGHT_TOL_M`] (h0_tol = 0.02 m)
//!   AND touchdown speed ≤ [`VERTICAL_SPEED_TOL_MPS`] (ḣ_tol = 0.10 m/s) AND steady tilt ≤
//!   [`TILT_TOL_DEG`] (10°).
//!
//! # Summaries over episodes
//!
//! [`summarize`] gives the mean and the sample standard deviation (n − 1 denominator; 0 for
//! one value). A success rate is the summary of the 0/1 `success` values, its mean the rate.
//! [`lift_summary`], [`transport_summary`] and [`place_summary`] give one JSON object with
//! one `{"mean": x, "sd": y}` per metric (`null` for no episodes).

use std::fmt;

use serde_json::{json, Value};

use super::episode::EpisodeRow;

/// Length of the steady window at the end of an episode, s.
pub const STEADY_WINDOW_S: f64 = 1.0;
/// A grasp force above this means the payload is still held, N.
pub const HELD_FORCE_N: f64 = 1.0;
/// Largest final height error of a successful lift, m. Looser than h_tol: the paper reports
/// 36 mm for its 0.75 m lift, which it counts as a working policy.
pub const LIFT_SUCCESS_TOL_M: f64 = 0.05;
/// θ_tol of Table II, degrees.
pub const TILT_TOL_DEG: f64 = 10.0;
/// h_tol of Table II, m.
pub const HEIGHT_TOL_M: f64 = 0.03;
/// p_tol of Table II, m.
pub const POSITION_TOL_M: f64 = 0.20;
/// h0_tol of Table II, m.
pub const FINAL_HEIGHT_TOL_M: f64 = 0.02;
/// ḣ_tol of Table II, m/s.
pub const VERTICAL_SPEED_TOL_MPS: f64 = 0.10;

/// Why an episode's rows have no metrics.
#[derive(Debug, Clone, PartialEq)]
pub enum MetricError {
    /// No rows at all.
    Empty,
    /// Row `row` (0-based; line `row + 2` of its CSV) breaks a rule of the episode format.
    InvalidRow {
        row: usize,
        column: &'static str,
        reason: String,
    },
}

impl fmt::Display for MetricError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MetricError::Empty => f.write_str("the episode has no rows"),
            MetricError::InvalidRow {
                row,
                column,
                reason,
            } => write!(f, "episode row {row}, column {column}: {reason}"),
        }
    }
}

impl std::error::Error for MetricError {}

/// Lift metrics of one episode (definitions in the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiftMetrics {
    pub final_height_error_mm: f64,
    pub peak_tilt_deg: f64,
    pub steady_tilt_deg: f64,
    pub success: bool,
}

/// Transport metrics of one episode (definitions in the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransportMetrics {
    pub rms_velocity_error_mps: f64,
    pub max_height_deviation_mm: f64,
    pub steady_tilt_deg: f64,
    /// |travelled − commanded| along x, m: what the success rule compares with p_tol.
    pub travel_error_m: f64,
    pub success: bool,
}

/// Place metrics of one episode (definitions in the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaceMetrics {
    pub final_height_error_mm: f64,
    pub touchdown_speed_mps: f64,
    pub peak_tilt_deg: f64,
    pub steady_tilt_deg: f64,
    /// Whether a touchdown happened (else `touchdown_speed_mps` is the last row's |vz|).
    pub touched_down: bool,
    pub success: bool,
}

/// Mean and sample standard deviation of a set of values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanSd {
    pub mean: f64,
    pub sd: f64,
}

/// The rows after the checks every metric needs.
fn checked(rows: &[EpisodeRow]) -> Result<&[EpisodeRow], MetricError> {
    if rows.is_empty() {
        return Err(MetricError::Empty);
    }
    let mut previous = None;
    for (row, r) in rows.iter().enumerate() {
        r.check(previous).map_err(|fault| MetricError::InvalidRow {
            row,
            column: fault.column,
            reason: fault.reason,
        })?;
        previous = Some(r.t_s);
    }
    Ok(rows)
}

/// The rows of the steady window (never empty for non-empty rows: the last row is in it).
fn steady(rows: &[EpisodeRow]) -> &[EpisodeRow] {
    let start = rows[rows.len() - 1].t_s - STEADY_WINDOW_S;
    // `t_s` increases, so the window is a suffix.
    let first = rows.partition_point(|r| r.t_s < start);
    &rows[first..]
}

fn mean(values: impl ExactSizeIterator<Item = f64>) -> f64 {
    let n = values.len() as f64;
    values.sum::<f64>() / n
}

fn steady_height_m(rows: &[EpisodeRow]) -> f64 {
    let window = steady(rows);
    mean(window.iter().map(|r| r.payload_height_m))
}

fn steady_tilt_deg(rows: &[EpisodeRow]) -> f64 {
    let window = steady(rows);
    mean(window.iter().map(|r| r.payload_tilt_deg))
}

fn peak_tilt_deg(rows: &[EpisodeRow]) -> f64 {
    rows.iter()
        .map(|r| r.payload_tilt_deg)
        .fold(f64::NEG_INFINITY, f64::max)
}

fn held_at_end(rows: &[EpisodeRow]) -> bool {
    let last = &rows[rows.len() - 1];
    last.grasp_force_1_n > HELD_FORCE_N && last.grasp_force_2_n > HELD_FORCE_N
}

/// Trapezoidal integral of `f` over the rows' times.
fn integral(rows: &[EpisodeRow], f: impl Fn(&EpisodeRow) -> f64) -> f64 {
    rows.windows(2)
        .map(|w| (w[1].t_s - w[0].t_s) * (f(&w[0]) + f(&w[1])) / 2.0)
        .sum()
}

/// Lift metrics of one episode.
pub fn lift(rows: &[EpisodeRow]) -> Result<LiftMetrics, MetricError> {
    let rows = checked(rows)?;
    let goal = rows[rows.len() - 1].goal_height_m;
    let error_m = (steady_height_m(rows) - goal).abs();
    let steady_tilt_deg = steady_tilt_deg(rows);
    Ok(LiftMetrics {
        final_height_error_mm: error_m * 1000.0,
        peak_tilt_deg: peak_tilt_deg(rows),
        steady_tilt_deg,
        success: held_at_end(rows)
            && error_m <= LIFT_SUCCESS_TOL_M
            && steady_tilt_deg <= TILT_TOL_DEG,
    })
}

/// Transport metrics of one episode.
pub fn transport(rows: &[EpisodeRow]) -> Result<TransportMetrics, MetricError> {
    let rows = checked(rows)?;
    let squared_error = rows.iter().map(|r| {
        (r.payload_vx_mps - r.command_vx_mps).powi(2)
            + (r.payload_vy_mps - r.command_vy_mps).powi(2)
    });
    let start_height = rows[0].payload_height_m;
    let deviation_m = rows
        .iter()
        .map(|r| (r.payload_height_m - start_height).abs())
        .fold(0.0, f64::max);
    let travel_error_m =
        (integral(rows, |r| r.payload_vx_mps) - integral(rows, |r| r.command_vx_mps)).abs();
    Ok(TransportMetrics {
        rms_velocity_error_mps: mean(squared_error).sqrt(),
        max_height_deviation_mm: deviation_m * 1000.0,
        steady_tilt_deg: steady_tilt_deg(rows),
        travel_error_m,
        success: held_at_end(rows)
            && deviation_m <= HEIGHT_TOL_M
            && travel_error_m <= POSITION_TOL_M,
    })
}

/// Place metrics of one episode.
pub fn place(rows: &[EpisodeRow]) -> Result<PlaceMetrics, MetricError> {
    let rows = checked(rows)?;
    let touchdown = rows
        .windows(2)
        .position(|w| !w[0].ground_contact && w[1].ground_contact)
        .map(|i| &rows[i + 1]);
    let speed_row = touchdown.unwrap_or(&rows[rows.len() - 1]);
    let touchdown_speed_mps = speed_row.payload_vz_mps.abs();
    let error_m = steady_height_m(rows).abs();
    let steady_tilt_deg = steady_tilt_deg(rows);
    Ok(PlaceMetrics {
        final_height_error_mm: error_m * 1000.0,
        touchdown_speed_mps,
        peak_tilt_deg: peak_tilt_deg(rows),
        steady_tilt_deg,
        touched_down: touchdown.is_some(),
        success: touchdown.is_some()
            && error_m <= FINAL_HEIGHT_TOL_M
            && touchdown_speed_mps <= VERTICAL_SPEED_TOL_MPS
            && steady_tilt_deg <= TILT_TOL_DEG,
    })
}

/// Mean and sample standard deviation (n − 1; 0 for one value); `None` for no values.
pub fn summarize(values: &[f64]) -> Option<MeanSd> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let mean = mean(values.iter().copied());
    let sd = if n == 1 {
        0.0
    } else {
        let squares: f64 = values.iter().map(|v| (v - mean).powi(2)).sum();
        (squares / (n - 1) as f64).sqrt()
    };
    Some(MeanSd { mean, sd })
}

/// `{"mean": x, "sd": y}` of `values`, or `null` for none.
fn summary_json(values: impl Iterator<Item = f64>) -> Value {
    let values: Vec<f64> = values.collect();
    summarize(&values).map_or(Value::Null, |s| json!({"mean": s.mean, "sd": s.sd}))
}

fn rate(success: bool) -> f64 {
    f64::from(u8::from(success))
}

/// Summary over lift episodes: `final_height_error_mm`, `peak_tilt_deg`, `steady_tilt_deg`,
/// `success_rate`.
pub fn lift_summary(episodes: &[LiftMetrics]) -> Value {
    let of = |f: fn(&LiftMetrics) -> f64| summary_json(episodes.iter().map(f));
    json!({
        "final_height_error_mm": of(|m| m.final_height_error_mm),
        "peak_tilt_deg": of(|m| m.peak_tilt_deg),
        "steady_tilt_deg": of(|m| m.steady_tilt_deg),
        "success_rate": of(|m| rate(m.success)),
    })
}

/// Summary over transport episodes: `rms_velocity_error_mps`, `max_height_deviation_mm`,
/// `steady_tilt_deg`, `success_rate`.
pub fn transport_summary(episodes: &[TransportMetrics]) -> Value {
    let of = |f: fn(&TransportMetrics) -> f64| summary_json(episodes.iter().map(f));
    json!({
        "rms_velocity_error_mps": of(|m| m.rms_velocity_error_mps),
        "max_height_deviation_mm": of(|m| m.max_height_deviation_mm),
        "steady_tilt_deg": of(|m| m.steady_tilt_deg),
        "success_rate": of(|m| rate(m.success)),
    })
}

/// Summary over place episodes: `final_height_error_mm`, `touchdown_speed_mps`,
/// `peak_tilt_deg`, `steady_tilt_deg`, `success_rate`.
pub fn place_summary(episodes: &[PlaceMetrics]) -> Value {
    let of = |f: fn(&PlaceMetrics) -> f64| summary_json(episodes.iter().map(f));
    json!({
        "final_height_error_mm": of(|m| m.final_height_error_mm),
        "touchdown_speed_mps": of(|m| m.touchdown_speed_mps),
        "peak_tilt_deg": of(|m| m.peak_tilt_deg),
        "steady_tilt_deg": of(|m| m.steady_tilt_deg),
        "success_rate": of(|m| rate(m.success)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::episode::tests::sample;
    use moonhaul_core::state::Phase;

    /// Sample spacing of the synthetic episodes, s: a power of two, so times are exact.
    const DT: f64 = 0.125;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * (1.0 + b.abs())
    }

    macro_rules! assert_close {
        ($a:expr, $b:expr) => {{
            let (a, b) = ($a, $b);
            assert!(close(a, b), "{} = {a}, expected {b}", stringify!($a));
        }};
    }

    /// `n + 1` rows at 0, DT, …, n·DT, each shaped by `f(t)`.
    fn episode(n: usize, f: impl Fn(f64, &mut EpisodeRow)) -> Vec<EpisodeRow> {
        (0..=n)
            .map(|i| {
                let t = i as f64 * DT;
                let mut row = sample(t);
                f(t, &mut row);
                row
            })
            .collect()
    }

    /// 4 s lift: a 2 s ramp to `top`, then a hold; a tilt spike of 15° at t = 1 s, 1° after.
    fn lift_episode(top: f64) -> Vec<EpisodeRow> {
        episode(32, |t, r| {
            r.phase = Phase::Lift;
            r.goal_height_m = 0.3;
            r.payload_height_m = top * (t / 2.0).min(1.0);
            r.payload_tilt_deg = match t {
                1.0 => 15.0,
                t if t < 2.0 => 5.0,
                _ => 1.0,
            };
        })
    }

    #[test]
    fn lift_ramp_spike_and_success() {
        let rows = lift_episode(0.31);
        let m = lift(&rows).unwrap();
        assert_close!(m.final_height_error_mm, 10.0);
        assert_eq!(m.peak_tilt_deg, 15.0);
        assert_close!(m.steady_tilt_deg, 1.0);
        // A peak above θ_tol does not fail the lift; the paper's own peaks are 18–25°.
        assert!(m.success);

        // Too far from the goal (60 mm), dropped at the end, tilted at rest: each fails it.
        assert!(!lift(&lift_episode(0.36)).unwrap().success);
        assert!(lift(&lift_episode(0.34)).unwrap().success);
        let mut dropped = lift_episode(0.31);
        dropped.last_mut().unwrap().grasp_force_2_n = HELD_FORCE_N;
        assert!(!lift(&dropped).unwrap().success);
        let mut tilted = lift_episode(0.31);
        tilted
            .iter_mut()
            .rev()
            .take(9)
            .for_each(|r| r.payload_tilt_deg = 11.0);
        let m = lift(&tilted).unwrap();
        assert_close!(m.steady_tilt_deg, 11.0);
        assert!(!m.success);
    }

    #[test]
    fn lift_goal_is_the_last_rows() {
        let mut rows = lift_episode(0.5);
        rows.last_mut().unwrap().goal_height_m = 0.5;
        assert_close!(lift(&rows).unwrap().final_height_error_mm, 0.0);
    }

    #[test]
    fn steady_window_is_the_last_second_both_ends_included() {
        // Rows at 0, 0.125, …, 3; the window is t ≥ 2: the row at 2 is in, 1.875 is out.
        let rows = episode(24, |t, r| {
            r.payload_height_m = if t == 1.875 { 9.0 } else { 0.3 };
            r.payload_tilt_deg = if t == 2.0 { 18.0 } else { 0.0 };
        });
        assert_eq!(steady(&rows).len(), 9);
        let m = lift(&rows).unwrap();
        assert_close!(m.final_height_error_mm, 0.0);
        assert_close!(m.steady_tilt_deg, 2.0);
        // An episode shorter than the window is all window; one row is its own window.
        let short = episode(4, |t, r| r.payload_tilt_deg = 8.0 * t);
        assert_eq!(steady(&short).len(), 5);
        assert_close!(lift(&short).unwrap().steady_tilt_deg, 2.0);
        assert_eq!(lift(&short[..1]).unwrap().steady_tilt_deg, 0.0);
    }

    /// 4 s of transport at a constant 0.19 m/s under a 0.2 m/s command, at 0.3 m.
    fn transport_episode(f: impl Fn(f64, &mut EpisodeRow)) -> Vec<EpisodeRow> {
        episode(32, |t, r| {
            r.phase = Phase::Transport;
            r.payload_height_m = 0.3;
            r.payload_vx_mps = 0.19;
            r.command_vx_mps = 0.2;
            f(t, r);
        })
    }

    #[test]
    fn transport_tracking_height_and_success() {
        let rows = transport_episode(|t, r| {
            if t == 1.5 {
                r.payload_height_m = 0.302;
            }
            if t >= 3.0 {
                r.payload_tilt_deg = 0.5;
            }
        });
        let m = transport(&rows).unwrap();
        assert_close!(m.rms_velocity_error_mps, 0.01);
        assert_close!(m.max_height_deviation_mm, 2.0);
        assert_close!(m.steady_tilt_deg, 0.5);
        assert_close!(m.travel_error_m, 0.04); // 4 s × 0.01 m/s
        assert!(m.success);

        // A lateral error counts in the planar RMS: √(0.01² + 0.02²).
        let sideways = transport_episode(|_, r| r.payload_vy_mps = 0.02);
        assert_close!(
            transport(&sideways).unwrap().rms_velocity_error_mps,
            0.0005_f64.sqrt()
        );
        // The deviation is from the first row's height, whichever it is, in either direction.
        let sag = transport_episode(|t, r| {
            r.payload_height_m = if t == 0.0 {
                0.31
            } else {
                0.3 - 0.03 * (t / 4.0)
            }
        });
        let m = transport(&sag).unwrap();
        assert_close!(m.max_height_deviation_mm, 40.0);
        assert!(!m.success);
    }

    #[test]
    fn transport_travel_is_trapezoidal_and_bounded_by_p_tol() {
        // Accelerating 0 → 0.2 m/s over the first second, commanded 0.2 throughout: the
        // payload falls 0.1 m behind (the triangle the trapezoids integrate exactly).
        let rows = transport_episode(|t, r| r.payload_vx_mps = 0.2 * t.min(1.0));
        let m = transport(&rows).unwrap();
        assert_close!(m.travel_error_m, 0.1);
        assert!(m.success);
        // 4 s at 0.16 m/s: 0.16 m behind, within p_tol; at 0.14 m/s, 0.24 m: past it.
        let slow = transport_episode(|_, r| r.payload_vx_mps = 0.16);
        assert!(transport(&slow).unwrap().success);
        let slower = transport_episode(|_, r| r.payload_vx_mps = 0.14);
        let m = transport(&slower).unwrap();
        assert_close!(m.travel_error_m, 0.24);
        assert!(!m.success);
        let mut dropped = transport_episode(|_, _| {});
        dropped.last_mut().unwrap().grasp_force_1_n = 0.0;
        assert!(!transport(&dropped).unwrap().success);
        assert_eq!(transport(&rows[..1]).unwrap().travel_error_m, 0.0);
    }

    /// Descends from 0.06 m at 0.03 m/s, touches down at t = 2 s and rests at 5 mm for 2 s;
    /// a tilt of 6° mid-descent, 0.6° after contact.
    fn place_episode(vz: f64) -> Vec<EpisodeRow> {
        episode(32, move |t, r| {
            r.phase = Phase::Place;
            r.goal_height_m = 0.0;
            let down = t >= 2.0;
            r.payload_height_m = if down { 0.005 } else { 0.06 - 0.03 * t };
            r.payload_vz_mps = if t <= 2.0 { -vz } else { 0.0 };
            r.ground_contact = down;
            r.payload_tilt_deg = match t {
                1.0 => 6.0,
                _ if down => 0.6,
                _ => 2.0,
            };
            if t > 3.0 {
                (r.grasp_force_1_n, r.grasp_force_2_n) = (0.0, 0.0); // released
            }
        })
    }

    #[test]
    fn place_touchdown_height_tilt_and_success() {
        let m = place(&place_episode(0.03)).unwrap();
        assert!(m.touched_down);
        assert_close!(m.touchdown_speed_mps, 0.03);
        assert_close!(m.final_height_error_mm, 5.0);
        assert_eq!(m.peak_tilt_deg, 6.0);
        assert_close!(m.steady_tilt_deg, 0.6);
        assert!(m.success, "{m:?}");

        let hard = place(&place_episode(0.2)).unwrap();
        assert_close!(hard.touchdown_speed_mps, 0.2);
        assert!(!hard.success);
        let mut high = place_episode(0.03);
        high.iter_mut()
            .filter(|r| r.t_s >= 2.0)
            .for_each(|r| r.payload_height_m = 0.025);
        assert!(!place(&high).unwrap().success);
        // The final height error is the magnitude: resting 5 mm into soft ground counts 5.
        let mut sunk = place_episode(0.03);
        sunk.iter_mut()
            .filter(|r| r.t_s >= 2.0)
            .for_each(|r| r.payload_height_m = -0.005);
        assert_close!(place(&sunk).unwrap().final_height_error_mm, 5.0);
    }

    #[test]
    fn touchdown_is_the_first_contact_after_a_row_without() {
        // On the ground at first (before the lift), off it, then down: the second contact.
        let mut rows = place_episode(0.03);
        rows[0].ground_contact = true;
        rows[0].payload_vz_mps = 0.5;
        let m = place(&rows).unwrap();
        assert!(m.touched_down);
        assert_close!(m.touchdown_speed_mps, 0.03);
        // A bounce: only the first touchdown counts.
        rows[20].ground_contact = false;
        rows[21].payload_vz_mps = -0.07;
        assert_close!(place(&rows).unwrap().touchdown_speed_mps, 0.03);
        // Never down: the last row's |vz|, and no success however good the rest looks.
        let mut hovering = place_episode(0.03);
        hovering.iter_mut().for_each(|r| r.ground_contact = false);
        hovering.last_mut().unwrap().payload_vz_mps = -0.01;
        let m = place(&hovering).unwrap();
        assert!(!m.touched_down && !m.success);
        assert_close!(m.touchdown_speed_mps, 0.01);
        // Never off the ground: no touchdown either.
        let mut grounded = place_episode(0.03);
        grounded.iter_mut().for_each(|r| r.ground_contact = true);
        assert!(!place(&grounded).unwrap().touched_down);
    }

    #[test]
    fn degenerate_episodes_are_errors() {
        assert_eq!(lift(&[]), Err(MetricError::Empty));
        assert_eq!(transport(&[]).unwrap_err(), MetricError::Empty);
        assert_eq!(place(&[]).unwrap_err(), MetricError::Empty);
        let mut rows = place_episode(0.03);
        rows[5].t_s = rows[4].t_s;
        let err = place(&rows).unwrap_err();
        assert!(
            matches!(
                err,
                MetricError::InvalidRow {
                    row: 5,
                    column: "t_s",
                    ..
                }
            ),
            "{err}"
        );
        assert!(
            err.to_string().starts_with("episode row 5, column t_s: "),
            "{err}"
        );
        let mut rows = transport_episode(|_, _| {});
        rows[3].payload_vy_mps = f64::NAN;
        assert!(matches!(
            transport(&rows),
            Err(MetricError::InvalidRow {
                row: 3,
                column: "payload_vy_mps",
                ..
            })
        ));
    }

    #[test]
    fn summarize_mean_and_sample_sd() {
        let s = summarize(&[2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0]).unwrap();
        assert_close!(s.mean, 5.0);
        assert_close!(s.sd, (32.0_f64 / 7.0).sqrt());
        assert_eq!(summarize(&[3.5]), Some(MeanSd { mean: 3.5, sd: 0.0 }));
        assert_eq!(summarize(&[]), None);
        let rate = summarize(&[1.0, 1.0, 0.0, 1.0]).unwrap();
        assert_close!(rate.mean, 0.75);
        assert_close!(rate.sd, 0.5);
    }

    #[test]
    fn summaries_have_the_documented_keys() {
        let keys = |v: &Value| -> Vec<String> {
            let mut keys: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
            keys.sort_unstable();
            keys
        };
        fn sorted(names: &[&str]) -> Vec<String> {
            let mut names: Vec<String> = names.iter().map(|n| n.to_string()).collect();
            names.sort_unstable();
            names
        }
        let a = lift(&lift_episode(0.31)).unwrap();
        let b = lift(&lift_episode(0.36)).unwrap();
        let v = lift_summary(&[a, b]);
        assert_eq!(
            keys(&v),
            sorted(&[
                "final_height_error_mm",
                "peak_tilt_deg",
                "steady_tilt_deg",
                "success_rate"
            ])
        );
        assert_close!(v["final_height_error_mm"]["mean"].as_f64().unwrap(), 35.0);
        assert_close!(
            v["final_height_error_mm"]["sd"].as_f64().unwrap(),
            50_f64.sqrt() * 5.0
        );
        assert_eq!(v["success_rate"]["mean"], 0.5);
        let line = serde_json::to_string(&lift_summary(&[a])).unwrap();
        assert!(
            line.contains(r#""peak_tilt_deg":{"mean":15.0,"sd":0.0}"#),
            "{line}"
        );

        let t = transport(&transport_episode(|_, _| {})).unwrap();
        assert_eq!(
            keys(&transport_summary(&[t])),
            sorted(&[
                "max_height_deviation_mm",
                "rms_velocity_error_mps",
                "steady_tilt_deg",
                "success_rate"
            ])
        );
        let p = place(&place_episode(0.03)).unwrap();
        let v = place_summary(&[p]);
        assert_eq!(
            keys(&v),
            sorted(&[
                "final_height_error_mm",
                "peak_tilt_deg",
                "steady_tilt_deg",
                "success_rate",
                "touchdown_speed_mps"
            ])
        );
        assert_eq!(v["success_rate"], json!({"mean": 1.0, "sd": 0.0}));
        assert_eq!(place_summary(&[])["touchdown_speed_mps"], Value::Null);
    }
}

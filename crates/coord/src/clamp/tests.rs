//! Clamp checks against an independent evaluation of the paper's definitions: the task-space
//! image of a command is recomputed here from the model and core's per-subsystem metrics.

use super::*;
use crate::model::tests::shipped_unit;
use moonhaul_core::se3::{planar_distance, pose_distance};
use moonhaul_core::stacked::Subsystem;
use moonhaul_core::state::{PlanarPose, ARM_JOINTS};
use proptest::prelude::*;
use std::sync::OnceLock;

const PERIOD_S: f64 = 0.02;

fn model() -> &'static UnitModel {
    static MODEL: OnceLock<UnitModel> = OnceLock::new();
    MODEL.get_or_init(shipped_unit)
}

fn clamp(n: usize) -> Clamp {
    Clamp::new(
        model().clone(),
        &SyncConfig::shipped().unwrap(),
        PERIOD_S,
        n,
    )
    .unwrap()
}

/// Every subsystem's distance between the task image of `commands` and the sensed state.
fn subsystem_distances(sensed: &[UnitState], commands: &[UnitCommand]) -> Vec<(Subsystem, f64)> {
    let m = model();
    let tol = SyncConfig::shipped().unwrap().tolerances;
    let delta_w = Vector2::from(tol.base_xy_m);
    let mut out = Vec::new();
    for (i, (s, u)) in sensed.iter().zip(commands).enumerate() {
        let y_arm = m.arm_world_pose(&s.base_pose, &s.arm.position_rad).unwrap();
        let base = m
            .spec()
            .integrate_base(&s.base_pose, &u.wheel_velocity_radps, PERIOD_S);
        let x_arm = m.arm_world_pose(&base, &u.arm_position_rad).unwrap();
        let (y_xy, x_xy) = (
            Vector2::new(s.base_pose.x_m, s.base_pose.y_m),
            Vector2::new(base.x_m, base.y_m),
        );
        out.push((
            Subsystem::Arm(i),
            pose_distance(
                &x_arm,
                &y_arm,
                tol.arm_translation_m,
                tol.arm_rotation_deg.to_radians(),
            ),
        ));
        out.push((Subsystem::Base(i), planar_distance(&x_xy, &y_xy, &delta_w)));
    }
    out
}

fn d_of(sensed: &[UnitState], commands: &[UnitCommand]) -> f64 {
    subsystem_distances(sensed, commands)
        .iter()
        .map(|p| p.1)
        .fold(f64::NEG_INFINITY, f64::max)
}

fn path(previous: &[UnitCommand], target: &[UnitCommand], t: f64) -> Vec<UnitCommand> {
    previous
        .iter()
        .zip(target)
        .map(|(s, f)| interpolate_command(s, f, t))
        .collect()
}

fn unit(q: [f64; ARM_JOINTS], pose: PlanarPose) -> UnitState {
    let mut s = UnitState::default();
    s.arm.position_rad = q;
    s.base_pose = pose;
    s
}

const HOME: [f64; ARM_JOINTS] = [0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8];

fn command(wheels: [f64; 2], arm: [f64; ARM_JOINTS]) -> UnitCommand {
    UnitCommand {
        wheel_velocity_radps: wheels,
        arm_position_rad: arm,
    }
}

#[test]
fn full_step_when_the_target_is_admissible() {
    let sensed = [
        unit(HOME, PlanarPose::default()),
        unit(
            HOME,
            PlanarPose {
                x_m: 1.0,
                y_m: 0.5,
                yaw_rad: 3.0,
            },
        ),
    ];
    let previous = [command([0.0; 2], HOME); 2];
    let mut nudged = HOME;
    nudged[3] += 0.01;
    let target = [command([2.0, 2.0], nudged), command([-1.0, 1.0], HOME)];
    let mut issued = [UnitCommand::default(); 2];
    let input = ClampInput {
        sensed: &sensed,
        previous: &previous,
        target: &target,
    };
    let report = clamp(2).step(&input, None, &mut issued).unwrap();
    assert_eq!((report.hold, report.t_max), (None, 1.0));
    assert_eq!(issued, target);
    assert!(report.distance.unwrap().value <= 1.0);
}

/// A wheel reversing from +15 to −15 rad/s moves its base by 0.03·|1 − 2t| m in one period:
/// d = 1.5·|1 − 2t| is V-shaped, admissible on [1/6, 5/6], so t_max = 5/6 although d(0) and
/// d(1) are both out of tolerance. A monotone-assuming search would hold here.
#[test]
fn non_monotone_path_finds_the_upper_edge() {
    let sensed = [
        unit(HOME, PlanarPose::default()),
        unit(
            HOME,
            PlanarPose {
                x_m: 0.0,
                y_m: 2.0,
                yaw_rad: 0.0,
            },
        ),
    ];
    let previous = [command([15.0, 15.0], HOME), command([0.0; 2], HOME)];
    let target = [command([-15.0, -15.0], HOME), command([0.0; 2], HOME)];
    let mut issued = [UnitCommand::default(); 2];
    let input = ClampInput {
        sensed: &sensed,
        previous: &previous,
        target: &target,
    };
    let report = clamp(2).step(&input, None, &mut issued).unwrap();
    assert_eq!(report.hold, None);
    assert!((report.t_max - 5.0 / 6.0).abs() < 1e-7, "{report:?}");
    let d = report.distance.unwrap();
    assert_eq!(d.binding, Subsystem::Base(0));
    assert!((d.value - 1.0).abs() < 1e-6);
    // Base 0 is the one at its limit; the arms did not move at all.
    assert!(
        (issued[0].wheel_velocity_radps[0] + 10.0).abs() < 1e-5,
        "{issued:?}"
    );
}

#[test]
fn hold_when_nothing_is_admissible_or_when_asked() {
    let sensed = [
        unit(HOME, PlanarPose::default()),
        unit(
            HOME,
            PlanarPose {
                x_m: 0.0,
                y_m: 2.0,
                yaw_rad: 0.0,
            },
        ),
    ];
    // Unit 1 keeps driving at 15 rad/s: 0.03 m per period, 1.5 tolerances, for every t.
    let previous = [command([0.0; 2], HOME), command([15.0, 15.0], HOME)];
    let target = previous;
    let mut issued = [UnitCommand::default(); 2];
    let input = ClampInput {
        sensed: &sensed,
        previous: &previous,
        target: &target,
    };
    let mut c = clamp(2);
    let report = c.step(&input, None, &mut issued).unwrap();
    assert_eq!(report.hold, Some(HoldReason::NoAdmissibleStep));
    let d = report.distance.unwrap();
    assert_eq!(d.binding, Subsystem::Base(1));
    assert!((d.value - 1.5).abs() < 1e-9);
    // The hold keeps every arm at its previous command and stops every wheel.
    let holds: Vec<_> = previous.iter().map(hold_command).collect();
    assert_eq!(issued.to_vec(), holds);
    assert!(issued.iter().all(|u| u.wheel_velocity_radps == [0.0; 2]));
    assert_eq!(d_of(&sensed, &issued), 0.0);
    // A requested hold (σ) wins even over an admissible target.
    let report = c
        .step(
            &ClampInput {
                target: &previous,
                previous: &[command([0.0; 2], HOME); 2],
                ..input
            },
            Some(HoldReason::Idle),
            &mut issued,
        )
        .unwrap();
    assert_eq!(
        report,
        ClampReport {
            hold: Some(HoldReason::Idle),
            t_max: 0.0,
            distance: None
        }
    );
    assert_eq!(issued.to_vec(), holds);
}

#[test]
fn bad_inputs_are_errors_naming_unit_and_field() {
    let sensed = [unit(HOME, PlanarPose::default()); 2];
    let previous = [command([0.0; 2], HOME); 2];
    let mut target = previous;
    target[1].arm_position_rad[2] = f64::NAN;
    let mut issued = [UnitCommand::default(); 2];
    let mut c = clamp(2);
    let err = c.step(
        &ClampInput {
            sensed: &sensed,
            previous: &previous,
            target: &target,
        },
        None,
        &mut issued,
    );
    assert_eq!(
        err.unwrap_err().to_string(),
        "unit 1: target.arm_position_rad is not finite"
    );
    let err = c.step(
        &ClampInput {
            sensed: &sensed[..1],
            previous: &previous,
            target: &previous,
        },
        None,
        &mut issued,
    );
    assert_eq!(
        err.unwrap_err().to_string(),
        "sensed has 1 units; the team has 2"
    );
    assert!(matches!(
        Clamp::new(model().clone(), &SyncConfig::shipped().unwrap(), 0.0, 2),
        Err(ClampError::Period(_))
    ));
}

/// A random team: sensed arms inside the Panda's limits, bases anywhere; previous commands lag
/// the sensed arms by `lag` rad per joint; targets step `step` rad per joint; wheel velocities
/// up to 25 rad/s (2.5 Δ_w per period) so arms and bases both bind.
fn scenario() -> impl Strategy<Value = (Vec<UnitState>, Vec<UnitCommand>, Vec<UnitCommand>)> {
    let limits: Vec<(f64, f64)> = model().arm_limits_rad().collect();
    (
        1usize..=3,
        prop::sample::select(vec![0.0, 0.002, 0.01, 0.05]),
        prop::sample::select(vec![0.003, 0.02, 0.1, 0.5]),
    )
        .prop_flat_map(move |(n, lag, step)| {
            let limits = limits.clone();
            let one = (
                prop::array::uniform7(0.0..1.0f64),
                (-3.0..3.0f64, -3.0..3.0f64, -3.2..3.2f64),
                prop::array::uniform7(-1.0..1.0f64),
                prop::array::uniform7(-1.0..1.0f64),
                prop::array::uniform2(-25.0..25.0f64),
                prop::array::uniform2(-25.0..25.0f64),
            )
                .prop_map(
                    move |(u, (x, y, yaw), lag_dir, step_dir, w_prev, w_target)| {
                        let q: [f64; ARM_JOINTS] = std::array::from_fn(|j| {
                            let (lo, hi) = limits[j];
                            lo + 0.1 + u[j] * (hi - lo - 0.2)
                        });
                        let s = unit(
                            q,
                            PlanarPose {
                                x_m: x,
                                y_m: y,
                                yaw_rad: yaw,
                            },
                        );
                        let prev_arm = std::array::from_fn(|j| q[j] + lag * lag_dir[j]);
                        let target_arm = std::array::from_fn(|j| prev_arm[j] + step * step_dir[j]);
                        (s, command(w_prev, prev_arm), command(w_target, target_arm))
                    },
                );
            prop::collection::vec(one, n)
        })
        .prop_map(|units| {
            let mut out = (Vec::new(), Vec::new(), Vec::new());
            for (s, p, f) in units {
                out.0.push(s);
                out.1.push(p);
                out.2.push(f);
            }
            out
        })
}

proptest! {

    #[test]
    fn clamp_issues_the_largest_admissible_step((sensed, previous, target) in scenario()) {
        let n = sensed.len();
        let mut issued = vec![UnitCommand::default(); n];
        let input = ClampInput { sensed: &sensed, previous: &previous, target: &target };
        let mut clamp = clamp(n);
        let report = clamp.step(&input, None, &mut issued).unwrap();
        let reported = report.distance.unwrap();

        // Dense reference scan: d at 2001 points of the path.
        let grid: Vec<(f64, f64)> = (0..=2000)
            .map(|j| f64::from(j) / 2000.0)
            .map(|t| (t, d_of(&sensed, &path(&previous, &target, t))))
            .collect();
        let dense = grid.iter().rev().find(|(_, d)| *d <= 1.0).map(|(t, _)| *t);
        // The search's pruning is sound only if its Lipschitz bound really bounds d's slope.
        let lipschitz = clamp.lipschitz(&input);
        for pair in grid.windows(2) {
            let slope = (pair[1].1 - pair[0].1).abs() / (pair[1].0 - pair[0].0);
            prop_assert!(slope <= lipschitz * (1.0 + 1e-9) + 1e-9, "slope {} > L {}", slope, lipschitz);
        }
        match report.hold {
            Some(reason) => {
                prop_assert_eq!(reason, HoldReason::NoAdmissibleStep);
                prop_assert_eq!(&issued, &previous.iter().map(hold_command).collect::<Vec<_>>());
                // The search is complete within its budget: only an exhausted one may miss
                // a narrow admissible stretch the dense scan finds (documented, and safe).
                if !clamp.search_exhausted() {
                    prop_assert_eq!(dense, None, "the dense scan found an admissible step");
                }
                // The reported d is the previous command's, and it is out of tolerance.
                let at_zero = subsystem_distances(&sensed, &previous);
                prop_assert!(reported.value > 1.0 && at_zero.contains(&(reported.binding, reported.value)));
            }
            None => {
                // The issued command is T(t_max) and it is admissible.
                prop_assert!((0.0..=1.0).contains(&report.t_max));
                prop_assert_eq!(&issued, &path(&previous, &target, report.t_max));
                let parts = subsystem_distances(&sensed, &issued);
                let d = parts.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
                prop_assert!(d <= 1.0, "issued d = {}", d);
                // t_max = 1 whenever F_k is admissible.
                if d_of(&sensed, &target) <= 1.0 {
                    prop_assert_eq!(report.t_max, 1.0);
                    prop_assert_eq!(&issued, &target);
                }
                // Maximal: no admissible dense-scan point above t_max − 1e-6, and (below) the
                // path leaves V_k within 1e-6 above t_max.
                let dense = dense.unwrap_or(f64::NEG_INFINITY);
                prop_assert!(report.t_max >= dense - 1e-6, "t_max {} < dense {}", report.t_max, dense);
                // The reported d and binding subsystem are those of the issued step …
                prop_assert_eq!(reported.value, d);
                prop_assert!(parts.contains(&(reported.binding, reported.value)));
                // … and when clamped, the binding subsystem is the one that reaches d = 1:
                // just past t_max it alone (or first) exceeds its tolerance.
                if report.t_max < 1.0 {
                    let beyond = subsystem_distances(&sensed, &path(&previous, &target, (report.t_max + 1e-6).min(1.0)));
                    let binding_beyond = beyond.iter().find(|p| p.0 == reported.binding).unwrap().1;
                    prop_assert!(binding_beyond > 1.0, "{:?} at t_max + 1e-6: {}", reported.binding, binding_beyond);
                    prop_assert!(reported.value > 1.0 - 1e-3, "d(t_max) = {}", reported.value);
                }
            }
        }
    }
}

#[test]
fn a_tally_counts_steps_cuts_and_holds_and_merges() {
    let mut a = ClampTally::default();
    assert_eq!(a.mean_t_max(), None);
    a.record(1.0, None);
    a.record(0.5, None);
    let mut b = ClampTally::default();
    b.record(0.0, Some(HoldReason::NoAdmissibleStep));
    b.record(0.0, Some(HoldReason::Idle));
    a.merge(&b);
    assert_eq!((a.ticks, a.clamped, a.holds, a.no_step), (4, 3, 2, 1));
    assert_eq!(a.mean_t_max(), Some(0.375));
    assert_eq!(a.hold_fraction(), Some(0.5));
    assert_eq!(a.no_step_fraction(), Some(0.25));
    assert_eq!(a.clamped_fraction(), Some(0.75));
}

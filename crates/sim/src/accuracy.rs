//! How much the configured (fast) solver settings change the physics: the nominal scripted
//! mission with the box, run with the configured settings and with a fine reference
//! (collisions at 200 Hz, integration at 1600 Hz, 4 Gauss–Seidel sweeps per substep, rapier's
//! default 2 cm contact prediction), compared step by step.

use std::fmt;

use moonhaul_core::state::Phase;

use crate::config::PhysicsConfig;
use crate::randomization::PayloadKind;
use crate::scene::{Env, EnvOptions, SceneModel};
use crate::scripted::{run_mission, MissionPlan, MissionSummary};
use crate::SimError;

/// Differences between the configured and the reference solver on one mission.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccuracyReport {
    pub physics: PhysicsConfig,
    /// RMS and largest difference of payload height over the mission, m.
    pub height_rms_m: f64,
    pub height_max_m: f64,
    /// Largest difference of payload tilt, rad.
    pub tilt_max_rad: f64,
    /// Mean |F₁| + |F₂| over the post-lift hold divided by the payload weight (≥ 1: the arms
    /// also squeeze).
    pub hold_force_ratio: f64,
    pub configured: MissionSummary,
    pub reference: MissionSummary,
}

impl fmt::Display for AccuracyReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (c, r) = (&self.configured, &self.reference);
        let p = &self.physics;
        writeln!(
            f,
            "accuracy of {} Hz integration / {} Hz collisions / {} PGS / {} mm prediction vs \
             reference 1600 Hz / 200 Hz / 4 PGS / 20 mm, nominal box mission:",
            p.physics_hz,
            p.collision_hz,
            p.num_internal_pgs_iterations,
            p.prediction_distance_m * 1e3
        )?;
        writeln!(
            f,
            "  payload height: RMS diff {:.2} mm, max diff {:.2} mm; tilt: max diff {:.3} deg",
            self.height_rms_m * 1e3,
            self.height_max_m * 1e3,
            self.tilt_max_rad.to_degrees()
        )?;
        writeln!(
            f,
            "  max tilt {:.3} / {:.3} deg, grasp drift {:.2} / {:.2} mm, touchdown {:.3} / {:.3} m/s (configured / reference)",
            c.max_tilt_rad.to_degrees(),
            r.max_tilt_rad.to_degrees(),
            c.max_grasp_drift_m * 1e3,
            r.max_grasp_drift_m * 1e3,
            c.touchdown_speed_mps,
            r.touchdown_speed_mps
        )?;
        write!(
            f,
            "  grasp force sum / payload weight while holding: {:.3}",
            self.hold_force_ratio
        )
    }
}

/// One nominal box mission as the comparison sees it.
struct Trace {
    /// (height m, tilt rad) per control step.
    samples: Vec<(f64, f64)>,
    hold_force_ratio: f64,
    summary: MissionSummary,
}

fn trace(scene: &SceneModel, plan: MissionPlan) -> Result<Trace, SimError> {
    let options = EnvOptions {
        randomize: false,
        payload: Some(PayloadKind::Box),
        start_lift_m: 0.0,
    };
    let mut env = Env::new(scene, 0, options)?;
    let weight_n =
        scene.payloads[&PayloadKind::Box].model.mass_kg() * scene.config.physics.gravity_mps2.abs();
    let mut samples = Vec::new();
    let (mut force_sum, mut n) = (0.0, 0usize);
    let summary = run_mission(scene, &mut env, plan, |phase, s| {
        samples.push((s.payload.height_m, s.payload.tilt_rad));
        let lifted = phase == Phase::Lift && s.payload.height_m > 0.9 * plan.lift_height_m;
        if lifted {
            force_sum += s.units.iter().map(|u| u.grasp.force_n).sum::<f64>();
            n += 1;
        }
    })?;
    Ok(Trace {
        samples,
        hold_force_ratio: force_sum / n.max(1) as f64 / weight_n,
        summary,
    })
}

/// Runs the comparison on the scripted mission `plan`.
pub fn compare(scene: &SceneModel, plan: MissionPlan) -> Result<AccuracyReport, SimError> {
    let mut config = scene.config.clone();
    config.physics = PhysicsConfig {
        physics_hz: 1600.0,
        collision_hz: 200.0,
        num_internal_pgs_iterations: 4,
        num_internal_stabilization_iterations: 1,
        prediction_distance_m: 0.02,
        ..config.physics
    };
    let fine = SceneModel::new(config)?;
    let (a, b) = (trace(scene, plan)?, trace(&fine, plan)?);
    let n = a.samples.len().min(b.samples.len()).max(1);
    let diffs = a
        .samples
        .iter()
        .zip(&b.samples)
        .map(|(x, y)| ((x.0 - y.0).abs(), (x.1 - y.1).abs()));
    let (mut sq, mut height_max_m, mut tilt_max_rad) = (0.0, 0.0f64, 0.0f64);
    for (dh, dt) in diffs {
        sq += dh * dh;
        height_max_m = height_max_m.max(dh);
        tilt_max_rad = tilt_max_rad.max(dt);
    }
    Ok(AccuracyReport {
        physics: scene.config.physics,
        height_rms_m: (sq / n as f64).sqrt(),
        height_max_m,
        tilt_max_rad,
        hold_force_ratio: a.hold_force_ratio,
        configured: a.summary,
        reference: b.summary,
    })
}

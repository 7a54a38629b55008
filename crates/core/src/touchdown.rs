//! Touchdown: when the ground carries the payload, judged from what the units know onboard.
//!
//! The lift estimate is measured from the ground under the rest grasp where the lift began
//! ([`crate::observation`]); after a transport over uneven terrain the ground under the payload
//! lies centimetres higher or lower. A fixed resting height would drive the arms into higher
//! ground until their drives give up (a tracking stop), or open the grippers above lower
//! ground. So touchdown is found the way a position-controlled arm finds contact: by its
//! following error. While the payload hangs, each end effector sits at or slightly below its
//! command (the drives' sag); once the ground carries the payload and the command goes lower,
//! the end effector stays above its command. That height of the sensed end effector over the
//! commanded one is the unit's *press*. The team's press is the largest: the ground carries
//! the payload once it pushes back at any grasp (the mean would wait for both, and an arm at
//! the end of its reach over lower ground never presses; measured: a tilted sledge resting on
//! one end, one arm pressing 10 mm, the other hanging 10 mm below its limit-bound command).
//! When the team's press, low-pass filtered over
//! `place.contact_filter_s` (encoder noise alone moves it by ±1.6 mm, 1σ, per tick), reaches
//! `place.contact_press_m` (`configs/tasks.toml`), the payload rests: the lift estimate at that
//! moment is the ground's height, and the gate's resting test measures from it. Contact for
//! `place.release_after_contact_s` in total opens the grippers.
//!
//! A controller that places has to press: the scripted one keeps its command
//! `place_press_m` (`configs/mission.toml`) below the sensed end effector once the chain stops
//! descending.

use crate::kinematics::KinematicsError;
use crate::observation::ee_in_base;
use crate::state::ARM_JOINTS;
use crate::task_config::PlaceTask;
use crate::unit::UnitSpec;

/// How far the end effector of `sensed` stands above the one of `commanded`, in the unit's
/// base frame, m.
pub fn press_m(
    spec: &UnitSpec,
    sensed: &[f64; ARM_JOINTS],
    commanded: &[f64; ARM_JOINTS],
) -> Result<f64, KinematicsError> {
    Ok(ee_in_base(spec, sensed)?.translation.z - ee_in_base(spec, commanded)?.translation.z)
}

/// The team's press: the largest [`press_m`] over the units' (sensed, commanded) arm joints;
/// NaN when FK fails for any.
pub fn team_press_m<'a>(
    spec: &UnitSpec,
    arms: impl IntoIterator<Item = (&'a [f64; ARM_JOINTS], &'a [f64; ARM_JOINTS])>,
) -> f64 {
    let mut largest = f64::NEG_INFINITY;
    for (sensed, commanded) in arms {
        match press_m(spec, sensed, commanded) {
            Ok(press) => largest = largest.max(press),
            Err(_) => return f64::NAN,
        }
    }
    largest
}

/// One placement's touchdown state; [`Touchdown::default`] at the start of each Place.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Touchdown {
    /// The filtered team press, m, from 0 (hanging) when the placement begins.
    press_m: f64,
    contact_s: f64,
    /// The lift estimate at the latest tick in contact, m.
    ground_lift_m: Option<f64>,
}

impl Touchdown {
    /// Takes one tick's team press ([`team_press_m`]) and lift estimate; true once the contact has lasted
    /// long enough to open the grippers. A non-finite press or estimate is skipped.
    pub fn update(
        &mut self,
        place: &PlaceTask,
        press_m: f64,
        lift_estimate_m: f64,
        period_s: f64,
    ) -> bool {
        if press_m.is_finite() && lift_estimate_m.is_finite() {
            let alpha = 1.0 - (-period_s / place.contact_filter_s).exp();
            self.press_m += alpha * (press_m - self.press_m);
        }
        if self.press_m >= place.contact_press_m && lift_estimate_m.is_finite() {
            self.contact_s += period_s;
            self.ground_lift_m = Some(lift_estimate_m);
        }
        // A zero duration still needs one tick in contact.
        self.ground_lift_m.is_some() && self.contact_s >= place.release_after_contact_s
    }

    /// The payload's height above the ground: above the ground found at touchdown, or, before
    /// any, above the ground where the lift began, m.
    pub fn height_above_ground_m(&self, lift_estimate_m: f64) -> f64 {
        lift_estimate_m - self.ground_lift_m.unwrap_or(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task_config::TaskConfig;

    #[test]
    fn contact_on_higher_ground_releases_and_resets_the_resting_height() {
        let place = TaskConfig::shipped().unwrap().place;
        let period_s = 0.02;
        let mut t = Touchdown::default();
        // Hanging: the drives sag, the press is negative; nothing rests.
        for _ in 0..100 {
            assert!(!t.update(&place, -0.002, 0.10, period_s));
        }
        assert_eq!(t.height_above_ground_m(0.10), 0.10);
        // The ground is 35 mm above the start's: the chain stops there and the arms press by
        // twice the threshold. The release follows after the contact time and the filter's lag.
        let ticks = (place.release_after_contact_s / period_s).ceil() as usize;
        let lag = (3.0 * place.contact_filter_s / period_s).ceil() as usize;
        let mut released_at = None;
        for k in 0..ticks + lag {
            if t.update(&place, 2.0 * place.contact_press_m, 0.035, period_s) {
                released_at.get_or_insert(k + 1);
            }
        }
        assert!(released_at.is_some_and(|k| k >= ticks), "{released_at:?}");
        assert!(t.height_above_ground_m(0.035).abs() < 1e-12);
        // A NaN is no contact, and changes nothing.
        let mut fresh = Touchdown::default();
        assert!(!fresh.update(&place, f64::NAN, 0.0, period_s));
        assert_eq!(fresh, Touchdown::default());
    }

    #[test]
    fn encoder_noise_alone_never_counts_as_contact() {
        let place = TaskConfig::shipped().unwrap().place;
        // Hanging for a minute with the measured press noise (1.6 mm, 1σ; Box–Muller on a
        // xorshift) around a 1 mm lag, and single spikes of 6 mm.
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut t = Touchdown::default();
        for k in 0..3000 {
            let (u, v) = (uniform().max(1e-300), uniform());
            let gauss = (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos();
            let spike = if k % 100 == 0 { 0.006 } else { 0.0 };
            let press = 0.001 + 0.0016 * gauss + spike;
            assert!(!t.update(&place, press, 0.2, 0.02), "tick {k}");
        }
        assert_eq!(t.height_above_ground_m(0.2), 0.2);
    }

    #[test]
    fn press_is_the_height_of_the_sensed_end_effector_over_the_commanded_one() {
        let spec = UnitSpec::from_file(&crate::config::repo_file("assets/unit.urdf")).unwrap();
        let q = [0.0, -0.5, 0.0, 1.2, 0.0, 0.8, 0.0];
        assert!(press_m(&spec, &q, &q).unwrap().abs() < 1e-12);
        // Raising the shoulder raises the end effector above the unchanged command.
        let mut up = q;
        up[1] -= 0.02;
        let lower = ee_in_base(&spec, &q).unwrap().translation.z;
        let higher = ee_in_base(&spec, &up).unwrap().translation.z;
        let expected = higher - lower;
        assert!(expected.abs() > 1e-3);
        assert!((press_m(&spec, &up, &q).unwrap() - expected).abs() < 1e-12);
        assert!((press_m(&spec, &q, &up).unwrap() + expected).abs() < 1e-12);
    }
}

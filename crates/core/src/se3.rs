//! SE(3) and planar metrics of the synchronization clamp, and SE(3) interpolation.
//!
//! The paper's arm metric is
//! d_SE(g₁, g₂) = max(‖t₁ − t₂‖₂ / d_max, ∠(R₁ᵀR₂) / θ_max), which reaches 1 when either the
//! translation error hits d_max or the rotation error hits θ_max; the wheel metric is
//! ‖(p₁ − p₂) ⊘ Δ_w‖₂ on base planar positions.
//!
//! Rotation angles are computed from the relative unit quaternion q = q₁⁻¹q₂ as
//! 2·atan2(‖q_v‖, |q_w|), which keeps full precision near 0 (where acos of the trace or of q_w
//! loses half the digits) and near π (where the sign of q_w flips).

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector2};

/// Rotation angle in [0, π] of R₁ᵀR₂, i.e. the geodesic distance between two orientations.
///
/// The relative quaternion q₁*q₂ is expanded by hand so that its vector part is exactly zero
/// for equal inputs (the metric is then exactly 0, not a rounding residue).
pub fn rotation_angle(r1: &UnitQuaternion<f64>, r2: &UnitQuaternion<f64>) -> f64 {
    let (w1, v1, w2, v2) = (r1.w, r1.imag(), r2.w, r2.imag());
    let w = w1 * w2 + v1.dot(&v2);
    let v = v2 * w1 - v1 * w2 - v1.cross(&v2);
    2.0 * v.norm().atan2(w.abs())
}

/// The paper's arm pose metric d_SE with tolerances `d_max_m` (m) and `theta_max_rad` (rad).
pub fn pose_distance(
    g1: &Isometry3<f64>,
    g2: &Isometry3<f64>,
    d_max_m: f64,
    theta_max_rad: f64,
) -> f64 {
    let translation = (g1.translation.vector - g2.translation.vector).norm() / d_max_m;
    let rotation = rotation_angle(&g1.rotation, &g2.rotation) / theta_max_rad;
    translation.max(rotation)
}

/// The paper's wheel metric ‖(p₁ − p₂) ⊘ Δ_w‖₂ with per-axis tolerances `delta_w_m` (m).
pub fn planar_distance(p1: &Vector2<f64>, p2: &Vector2<f64>, delta_w_m: &Vector2<f64>) -> f64 {
    (p1 - p2).component_div(delta_w_m).norm()
}

/// Interpolates between two poses: translation by linear interpolation, rotation by slerp
/// along the shorter arc. `t = 0` returns `a` and `t = 1` returns `b` exactly.
///
/// When the two orientations are exactly π apart both arcs are equally short; the one whose
/// axis follows the sign of the relative quaternion's vector part is taken.
pub fn interpolate_pose(a: &Isometry3<f64>, b: &Isometry3<f64>, t: f64) -> Isometry3<f64> {
    if t <= 0.0 {
        return *a;
    }
    if t >= 1.0 {
        return *b;
    }
    let translation = a.translation.vector.lerp(&b.translation.vector, t);
    let rotation = a.rotation * relative_rotation_fraction(&(a.rotation.inverse() * b.rotation), t);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// exp(t · log(delta)) on the shorter arc, robust for angles near 0 and π.
fn relative_rotation_fraction(delta: &UnitQuaternion<f64>, t: f64) -> UnitQuaternion<f64> {
    // q and −q are the same rotation; the one with w ≥ 0 gives the shorter arc.
    let (w, v) = if delta.w < 0.0 {
        (-delta.w, -delta.imag())
    } else {
        (delta.w, delta.imag())
    };
    let sin_half = v.norm();
    let half_angle = sin_half.atan2(w);
    // sin(t·φ)/sin(φ) → t·φ/sin(φ) → t/w as φ → 0; the second form avoids 0/0.
    let scale = if sin_half > 1e-12 {
        (t * half_angle).sin() / sin_half
    } else {
        t / w
    };
    UnitQuaternion::new_normalize(Quaternion::from_parts((t * half_angle).cos(), v * scale))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Unit, Vector3};
    use proptest::prelude::*;
    use std::f64::consts::PI;

    const D_MAX: f64 = 0.03;
    const THETA_MAX: f64 = 5.0 * PI / 180.0;

    fn axis_angle(axis: [f64; 3], angle: f64) -> UnitQuaternion<f64> {
        UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), angle)
    }

    fn pose() -> impl Strategy<Value = Isometry3<f64>> {
        (
            prop::array::uniform3(-2.0..2.0f64),
            prop::array::uniform3(-1.0..1.0f64),
            0.0..PI,
        )
            .prop_filter_map("non-degenerate axis", |(t, axis, angle)| {
                let axis = Vector3::from(axis);
                (axis.norm() > 1e-3).then(|| {
                    Isometry3::from_parts(
                        Translation3::from(Vector3::from(t)),
                        UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), angle),
                    )
                })
            })
    }

    #[test]
    fn angle_is_precise_near_zero_and_pi() {
        let id = UnitQuaternion::identity();
        for angle in [1e-12, 1e-9, 1e-6, 0.3, PI - 1e-6, PI - 1e-9, PI] {
            let r = axis_angle([0.3, -0.2, 0.9], angle);
            let got = rotation_angle(&id, &r);
            assert!(
                (got - angle).abs() <= 1e-15 + 1e-12 * angle,
                "{angle}: {got}"
            );
        }
    }

    #[test]
    fn metric_hits_one_at_each_tolerance() {
        let a = Isometry3::identity();
        let shifted = Isometry3::translation(0.0, D_MAX, 0.0);
        assert!((pose_distance(&a, &shifted, D_MAX, THETA_MAX) - 1.0).abs() < 1e-12);
        let turned = Isometry3::from_parts(
            Translation3::identity(),
            axis_angle([0.0, 0.0, 1.0], THETA_MAX),
        );
        assert!((pose_distance(&a, &turned, D_MAX, THETA_MAX) - 1.0).abs() < 1e-12);
        let delta = Vector2::new(0.02, 0.02);
        let p = Vector2::new(0.012, -0.016);
        assert!((planar_distance(&Vector2::zeros(), &p, &delta) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn slerp_through_pi_stays_on_the_great_circle() {
        let a = Isometry3::identity();
        let b = Isometry3::from_parts(Translation3::identity(), axis_angle([1.0, 0.0, 0.0], PI));
        let mid = interpolate_pose(&a, &b, 0.5);
        assert!((rotation_angle(&a.rotation, &mid.rotation) - PI / 2.0).abs() < 1e-12);
        assert!((rotation_angle(&mid.rotation, &b.rotation) - PI / 2.0).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn pose_metric_symmetric_and_zero_on_self(a in pose(), b in pose()) {
            prop_assert_eq!(pose_distance(&a, &a, D_MAX, THETA_MAX), 0.0);
            let ab = pose_distance(&a, &b, D_MAX, THETA_MAX);
            let ba = pose_distance(&b, &a, D_MAX, THETA_MAX);
            prop_assert!((ab - ba).abs() <= 1e-9 * ab.max(1.0));
        }

        #[test]
        fn pose_metric_scales_inversely_with_tolerances(a in pose(), b in pose(), k in 0.1..10.0f64) {
            let d = pose_distance(&a, &b, D_MAX, THETA_MAX);
            let scaled = pose_distance(&a, &b, k * D_MAX, k * THETA_MAX);
            prop_assert!((scaled * k - d).abs() <= 1e-9 * d.max(1.0));
        }

        #[test]
        fn planar_metric_symmetric_zero_and_scaling(
            p in prop::array::uniform2(-5.0..5.0f64),
            q in prop::array::uniform2(-5.0..5.0f64),
            k in 0.1..10.0f64,
        ) {
            let (p, q) = (Vector2::from(p), Vector2::from(q));
            let delta = Vector2::new(0.02, 0.02);
            prop_assert_eq!(planar_distance(&p, &p, &delta), 0.0);
            prop_assert_eq!(planar_distance(&p, &q, &delta), planar_distance(&q, &p, &delta));
            let d = planar_distance(&p, &q, &delta);
            prop_assert!((planar_distance(&p, &q, &(delta * k)) * k - d).abs() <= 1e-9 * d.max(1.0));
        }

        #[test]
        fn interpolation_endpoints_exact_and_path_geodesic(a in pose(), b in pose(), t in 0.0..1.0f64) {
            prop_assert_eq!(interpolate_pose(&a, &b, 0.0), a);
            prop_assert_eq!(interpolate_pose(&a, &b, 1.0), b);
            let total = rotation_angle(&a.rotation, &b.rotation);
            let x = interpolate_pose(&a, &b, t);
            // On the shorter great arc the angles to both ends add up to the whole, split t : 1−t.
            prop_assert!((rotation_angle(&a.rotation, &x.rotation) - t * total).abs() < 1e-9);
            prop_assert!((rotation_angle(&x.rotation, &b.rotation) - (1.0 - t) * total).abs() < 1e-9);
            let expected_t = a.translation.vector + t * (b.translation.vector - a.translation.vector);
            prop_assert!((x.translation.vector - expected_t).norm() < 1e-12);
        }
    }
}

//! The one boundary between core's nalgebra f64 math and rapier's glam f32 types.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rapier3d::math::{Pose, Rotation, Vector};

/// nalgebra isometry → rapier pose.
pub fn to_pose(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    Pose::from_parts(
        to_vector(&t),
        Rotation::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32).normalize(),
    )
}

/// rapier pose → nalgebra isometry.
pub fn to_isometry(pose: &Pose) -> Isometry3<f64> {
    let r = pose.rotation;
    Isometry3::from_parts(
        Translation3::from(from_vector(pose.translation)),
        UnitQuaternion::from_quaternion(Quaternion::new(
            r.w as f64, r.x as f64, r.y as f64, r.z as f64,
        )),
    )
}

/// nalgebra vector → rapier vector.
pub fn to_vector(v: &Vector3<f64>) -> Vector {
    Vector::new(v.x as f32, v.y as f32, v.z as f32)
}

/// rapier vector → nalgebra vector.
pub fn from_vector(v: Vector) -> Vector3<f64> {
    Vector3::new(v.x as f64, v.y as f64, v.z as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_round_trip_within_f32_precision() {
        let iso = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.3, -0.2, 1.1));
        let back = to_isometry(&to_pose(&iso));
        assert!((back.translation.vector - iso.translation.vector).norm() < 1e-6);
        assert!(back.rotation.angle_to(&iso.rotation) < 1e-6);
        let p = Vector3::new(0.1, 0.2, 0.3);
        let a = iso * nalgebra::Point3::from(p);
        let b = to_pose(&iso).transform_point(to_vector(&p));
        assert!((from_vector(b) - a.coords).norm() < 1e-6);
    }
}

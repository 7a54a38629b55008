//! Foxglove's 3-D types from the records' plain arrays.

use foxglove::schemas::{
    Color, CubePrimitive, Pose, Quaternion, SceneEntity, SceneUpdate, Timestamp, Vector3,
};

use super::topics::PAYLOAD_FRAME_ID;

/// The payload as a cube in its own frame, locked to it so it follows `/tf`.
pub(super) fn payload_scene(size_m: [f64; 3], stamp: Timestamp) -> SceneUpdate {
    SceneUpdate {
        deletions: Vec::new(),
        entities: vec![SceneEntity {
            timestamp: Some(stamp),
            frame_id: PAYLOAD_FRAME_ID.to_owned(),
            id: "payload".to_owned(),
            // No lifetime: the entity stays until replaced by the next update.
            lifetime: None,
            frame_locked: true,
            cubes: vec![CubePrimitive {
                pose: Some(Pose {
                    position: Some(Vector3::default()),
                    orientation: Some(Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: 0.0,
                        w: 1.0,
                    }),
                }),
                size: Some(vector(&size_m)),
                color: Some(Color {
                    r: 0.85,
                    g: 0.55,
                    b: 0.2,
                    a: 0.9,
                }),
            }],
            ..Default::default()
        }],
    }
}

pub(super) fn vector(v: &[f64; 3]) -> Vector3 {
    Vector3 {
        x: v[0],
        y: v[1],
        z: v[2],
    }
}

pub(super) fn quaternion(q: &[f64; 4]) -> Quaternion {
    Quaternion {
        x: q[0],
        y: q[1],
        z: q[2],
        w: q[3],
    }
}

/// A foxglove timestamp from µs (saturating beyond the year 2106).
pub(super) fn timestamp(stamp_us: u64) -> Timestamp {
    let sec = u32::try_from(stamp_us / 1_000_000).unwrap_or(u32::MAX);
    // < 10⁹, fits u32.
    let nsec = ((stamp_us % 1_000_000) * 1000) as u32;
    Timestamp::new_checked(sec, nsec).unwrap_or(Timestamp::MAX)
}

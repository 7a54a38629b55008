//! The ROS 2 messages a unit publishes, as plain serde structs laid out field for field like
//! their `.msg` files (CDR encodes fields in declaration order, nothing else), and each type's
//! identity: its ROS name, its DDS name (rmw_zenoh's key expressions carry it), its Jazzy type
//! hash (RIHS01, REP-2016) and its `ros2msg` definition (rosbag2's MCAP schemas).
//!
//! The hashes are Jazzy's, copied from rosidl's generated type descriptions; the tests check
//! them against a published copy (`tests/data/ros2_type_hashes.txt`) and against `rosbags`'
//! own hashing of its Jazzy type store. A message whose definition changed in a later ROS
//! release would change its hash, and rmw_zenoh would then keep ours and theirs apart.

use byteorder::LittleEndian;
use serde::Serialize;

/// builtin_interfaces/msg/Time.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// The time `stamp_us` µs after the epoch of the team's clock; `None` past the year 2038,
    /// which `sec` (int32) cannot hold.
    pub fn from_us(stamp_us: u64) -> Option<Time> {
        let sec = i32::try_from(stamp_us / 1_000_000).ok()?;
        // < 1e9, so it fits.
        let nanosec = (stamp_us % 1_000_000) as u32 * 1000;
        Some(Time { sec, nanosec })
    }
}

/// std_msgs/msg/Header.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// std_msgs/msg/String.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StringMsg {
    pub data: String,
}

/// sensor_msgs/msg/JointState.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// geometry_msgs/msg/Vector3 and geometry_msgs/msg/Point (the same layout).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// geometry_msgs/msg/Quaternion.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

/// geometry_msgs/msg/Transform.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// geometry_msgs/msg/TransformStamped.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// tf2_msgs/msg/TFMessage.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// diagnostic_msgs/msg/KeyValue.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// diagnostic_msgs/msg/DiagnosticStatus.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DiagnosticStatus {
    /// [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE`.
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
}

/// diagnostic_msgs/msg/DiagnosticArray.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// geometry_msgs/msg/Pose.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Pose {
    pub position: Vector3,
    pub orientation: Quaternion,
}

/// geometry_msgs/msg/PoseStamped.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// The CDR encapsulation header of little-endian plain CDR (`CDR_LE`), first in every payload
/// rmw_zenoh and rosbag2 carry.
const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// `message` as rmw_zenoh sends it and rosbag2 stores it: the encapsulation header, then the
/// little-endian CDR body (aligned from the body's start), written into `out` (cleared first,
/// so a caller reuses its buffer).
pub fn encode_cdr<T: Serialize>(message: &T, out: &mut Vec<u8>) -> Result<(), cdr_encoding::Error> {
    out.clear();
    out.extend_from_slice(&CDR_LE_HEADER);
    cdr_encoding::to_writer::<T, LittleEndian, _>(&mut *out, message)
}

/// One message type's identity on the ROS 2 graph and in a bag.
#[derive(Debug, PartialEq, Eq)]
pub struct RosType {
    /// `pkg/msg/Name`: rosbag2's topic type.
    pub name: &'static str,
    /// Jazzy's RIHS01 type hash, `RIHS01_<64 hex>`.
    pub hash: &'static str,
    /// The `.msg` fields (without comments).
    fields: &'static str,
    /// Every type it refers to, transitively, each once: the `ros2msg` schema lists them after
    /// its own fields.
    refers_to: &'static [&'static Nested],
}

/// A type only ever sent inside another.
#[derive(Debug, PartialEq, Eq)]
struct Nested {
    /// `pkg/Name`, as a `ros2msg` schema names it.
    name: &'static str,
    fields: &'static str,
}

impl RosType {
    /// The DDS type name rmw_zenoh puts in key expressions: `pkg::msg::dds_::Name_`.
    pub fn dds_name(&self) -> String {
        format!("{}_", self.name.replacen("/msg/", "::msg::dds_::", 1))
    }

    /// The `ros2msg` definition rosbag2 stores as a channel's schema: the type's fields, then
    /// each referred type after a separator line and `MSG: pkg/Name`.
    pub fn definition(&self) -> String {
        let mut text = self.fields.to_owned();
        for t in self.refers_to {
            text.push('\n');
            text.push_str(&"=".repeat(80));
            text.push_str("\nMSG: ");
            text.push_str(t.name);
            text.push('\n');
            text.push_str(t.fields);
        }
        text
    }
}

const TIME: Nested = Nested {
    name: "builtin_interfaces/Time",
    fields: "int32 sec\nuint32 nanosec",
};
const HEADER: Nested = Nested {
    name: "std_msgs/Header",
    fields: "builtin_interfaces/Time stamp\nstring frame_id",
};
const VECTOR3: Nested = Nested {
    name: "geometry_msgs/Vector3",
    fields: "float64 x\nfloat64 y\nfloat64 z",
};
const POINT: Nested = Nested {
    name: "geometry_msgs/Point",
    fields: "float64 x\nfloat64 y\nfloat64 z",
};
const QUATERNION: Nested = Nested {
    name: "geometry_msgs/Quaternion",
    fields: "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
};
const TRANSFORM: Nested = Nested {
    name: "geometry_msgs/Transform",
    fields: "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation",
};
const TRANSFORM_STAMPED: Nested = Nested {
    name: "geometry_msgs/TransformStamped",
    fields: "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform",
};
const KEY_VALUE: Nested = Nested {
    name: "diagnostic_msgs/KeyValue",
    fields: "string key\nstring value",
};
const DIAGNOSTIC_STATUS: Nested = Nested {
    name: "diagnostic_msgs/DiagnosticStatus",
    fields: "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\n\
             string message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values",
};
const POSE: Nested = Nested {
    name: "geometry_msgs/Pose",
    fields: "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
};

/// std_msgs/msg/String: `/<ns>/robot_description`.
pub const STRING: RosType = RosType {
    name: "std_msgs/msg/String",
    hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    fields: "string data",
    refers_to: &[],
};
/// sensor_msgs/msg/JointState: `/<ns>/joint_states`.
pub const JOINT_STATE: RosType = RosType {
    name: "sensor_msgs/msg/JointState",
    hash: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    fields: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n\
             float64[] effort",
    refers_to: &[&HEADER, &TIME],
};
/// tf2_msgs/msg/TFMessage: `/tf`, `/tf_static`.
pub const TF_MESSAGE: RosType = RosType {
    name: "tf2_msgs/msg/TFMessage",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    fields: "geometry_msgs/TransformStamped[] transforms",
    refers_to: &[
        &TRANSFORM_STAMPED,
        &HEADER,
        &TIME,
        &TRANSFORM,
        &VECTOR3,
        &QUATERNION,
    ],
};
/// diagnostic_msgs/msg/DiagnosticArray: `/diagnostics`.
pub const DIAGNOSTIC_ARRAY: RosType = RosType {
    name: "diagnostic_msgs/msg/DiagnosticArray",
    hash: "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
    fields: "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status",
    refers_to: &[&HEADER, &TIME, &DIAGNOSTIC_STATUS, &KEY_VALUE],
};
/// geometry_msgs/msg/PoseStamped: `/ground_truth/payload`.
pub const POSE_STAMPED: RosType = RosType {
    name: "geometry_msgs/msg/PoseStamped",
    hash: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    fields: "std_msgs/Header header\ngeometry_msgs/Pose pose",
    refers_to: &[&HEADER, &TIME, &POSE, &POINT, &QUATERNION],
};

/// The types a unit or a bag publishes, for tests and listings.
pub const PUBLISHED_TYPES: [&RosType; 5] = [
    &JOINT_STATE,
    &TF_MESSAGE,
    &STRING,
    &DIAGNOSTIC_ARRAY,
    &POSE_STAMPED,
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_hashes_are_the_published_jazzy_ones() {
        let published = include_str!("../../tests/data/ros2_jazzy_type_hashes.txt");
        let mut seen = 0;
        for line in published
            .lines()
            .filter(|l| !l.starts_with('#') && !l.is_empty())
        {
            let (name, hash) = line.split_once(' ').unwrap();
            let ours = PUBLISHED_TYPES.iter().find(|t| t.name == name).unwrap();
            assert_eq!(ours.hash, hash, "{name}");
            seen += 1;
        }
        assert_eq!(seen, PUBLISHED_TYPES.len());
    }

    #[test]
    fn dds_names_are_rmw_zenohs() {
        // docs/design.md of rmw_zenoh: `std_msgs::msg::dds_::String_`.
        assert_eq!(STRING.dds_name(), "std_msgs::msg::dds_::String_");
        assert_eq!(
            JOINT_STATE.dds_name(),
            "sensor_msgs::msg::dds_::JointState_"
        );
    }

    #[test]
    fn cdr_has_the_encapsulation_header_and_aligns_from_the_body() {
        let mut out = Vec::new();
        encode_cdr(
            &StringMsg {
                data: "hi".to_owned(),
            },
            &mut out,
        )
        .unwrap();
        // CDR_LE, then the string's length with its NUL, the bytes, the NUL.
        assert_eq!(out, [0, 1, 0, 0, 3, 0, 0, 0, b'h', b'i', 0]);
        let mut out = Vec::new();
        let header = Header {
            stamp: Time { sec: 1, nanosec: 2 },
            frame_id: "a".to_owned(),
        };
        encode_cdr(
            &PoseStamped {
                header,
                pose: Pose::default(),
            },
            &mut out,
        )
        .unwrap();
        // Body: sec, nanosec, len 2, "a\0", 2 bytes of padding to the first float64 at 16.
        assert_eq!(
            &out[4..20],
            &[1, 0, 0, 0, 2, 0, 0, 0, 2, 0, 0, 0, b'a', 0, 0, 0]
        );
        assert_eq!(out.len(), 4 + 16 + 7 * 8);
    }

    #[test]
    fn times_past_int32_seconds_are_refused() {
        assert_eq!(
            Time::from_us(1_500_000),
            Some(Time {
                sec: 1,
                nanosec: 500_000_000
            })
        );
        assert_eq!(Time::from_us((i32::MAX as u64 + 1) * 1_000_000), None);
    }
}

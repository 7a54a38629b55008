//! What a unit shows the ROS 2 graph, built from its tick records: the same messages whether
//! they go out live ([`super::live`]) or into a bag ([`super::bag`]).
//!
//! Per unit, under its namespace `ns` (default `unit_<index>`):
//!
//! - `/<ns>/joint_states` — the nine joints by their URDF names (wheels, then arm base to tip),
//!   sensed positions and velocities; `effort` is empty: the drives report no torque.
//! - `/tf` — `<ns>/odom` → `<ns>/<base link>` by the unit's wheel odometry, then every movable
//!   URDF joint's child link at its sensed position, every frame prefixed `<ns>/`, as
//!   robot_state_publisher with `frame_prefix` would draw them.
//! - `/tf_static` — `world` → `<ns>/odom` (the identity: a unit's odometry starts at its
//!   start pose in the team's shared world frame, so its odom frame is the world frame) and
//!   the fixed URDF joints.
//! - `/<ns>/robot_description` — the URDF the unit runs with (transient local, depth 1).
//! - `/diagnostics` — one status per unit: phase, the clamp's t_max and hold, the age of each
//!   peer's newest state, the latched fault with its reason.
//!
//! And from a simulated world's ground truth, `/ground_truth/payload` (the payload's pose in
//! `world`).

use moonhaul_core::kinematics::{parse_urdf, KinematicTree};
use moonhaul_core::unit::UnitSpec;
use nalgebra::{Isometry3, Vector3 as NVector3};

use super::msgs::{
    DiagnosticArray, DiagnosticStatus, Header, JointState, KeyValue, Pose, PoseStamped, Quaternion,
    RosType, StringMsg, TfMessage, Time, Transform, TransformStamped, Vector3, DIAGNOSTIC_ARRAY,
    JOINT_STATE, POSE_STAMPED, STRING, TF_MESSAGE,
};
// The world frame (`/tf_static`'s root) and `/tf` are the mission logs' own.
use crate::mission_log::{UnitLinks, TF_TOPIC, WORLD_FRAME_ID as WORLD_FRAME};
use crate::record::{TickRecord, WorldFrame};

/// `/tf_static`.
pub const TF_STATIC_TOPIC: &str = "/tf_static";
/// `/diagnostics`.
pub const DIAGNOSTICS_TOPIC: &str = "/diagnostics";
/// The payload's pose by the world's ground truth.
pub const PAYLOAD_TOPIC: &str = "/ground_truth/payload";

/// The default namespace of unit `index`.
pub fn default_namespace(index: usize) -> String {
    format!("unit_{index}")
}

/// A topic's durability: whether a late subscriber gets the last samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    Volatile,
    TransientLocal,
}

/// The QoS a topic is offered with: always reliable, keep-last `depth`, automatic liveliness,
/// no deadline or lifespan (rmw_zenoh's defaults but for depth and durability).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub durability: Durability,
    pub depth: u32,
}

impl Qos {
    /// A stream of samples (rclcpp's default depth).
    pub const STREAM: Qos = Qos {
        durability: Durability::Volatile,
        depth: 10,
    };
    /// `/tf`: tf2's broadcaster depth.
    pub const TF: Qos = Qos {
        durability: Durability::Volatile,
        depth: 100,
    };
    /// `/tf_static`, `robot_description`: the last sample stays for late subscribers.
    pub const LATCHED: Qos = Qos {
        durability: Durability::TransientLocal,
        depth: 1,
    };
}

/// One topic: its name, message type and offered QoS.
#[derive(Debug, Clone, PartialEq)]
pub struct Topic {
    pub name: String,
    pub ros_type: &'static RosType,
    pub qos: Qos,
}

impl Topic {
    fn new(name: impl Into<String>, ros_type: &'static RosType, qos: Qos) -> Self {
        Topic {
            name: name.into(),
            ros_type,
            qos,
        }
    }
}

/// The ground truth's topic.
pub fn payload_topic() -> Topic {
    Topic::new(PAYLOAD_TOPIC, &POSE_STAMPED, Qos::STREAM)
}

/// One unit's topics and the model its messages are built with.
pub struct UnitTopics {
    namespace: String,
    urdf: String,
    joint_names: Vec<String>,
    links: UnitLinks,
    /// `<ns>/<link>` of the root, then of each joint's child, in [`UnitLinks::joints`] order.
    frames: Vec<String>,
    /// Per joint in the same order: whether it moves (`/tf`) or is fixed (`/tf_static`).
    movable: Vec<bool>,
    odom_frame: String,
    pub joint_states: Topic,
    pub tf: Topic,
    pub tf_static: Topic,
    pub robot_description: Topic,
    pub diagnostics: Topic,
}

impl UnitTopics {
    /// The topics of a unit running with the URDF `urdf`, under `namespace` (a ROS name
    /// without slashes, e.g. `unit_0`).
    pub fn new(urdf: &str, namespace: &str) -> Result<Self, String> {
        if !valid_namespace(namespace) {
            return Err(format!(
                "ROS 2 namespace {namespace:?} is not a name: letters, digits and '_', not \
                 starting with a digit"
            ));
        }
        let robot = parse_urdf(urdf).map_err(|e| e.to_string())?;
        let tree = KinematicTree::from_robot(&robot).map_err(|e| e.to_string())?;
        let spec = UnitSpec::from_robot(&robot).map_err(|e| e.to_string())?;
        let links = UnitLinks::new(&tree, &spec);
        let frame = |link: &str| format!("{namespace}/{link}");
        let mut frames = vec![frame(links.base_link())];
        let mut movable = Vec::with_capacity(links.joints().len());
        for joint in links.joints() {
            frames.push(frame(&joint.child));
            movable.push(joint.motion.is_some());
        }
        let joint_names = spec.joint_names().map(str::to_owned).collect();
        Ok(UnitTopics {
            odom_frame: frame("odom"),
            joint_states: Topic::new(
                format!("/{namespace}/joint_states"),
                &JOINT_STATE,
                Qos::STREAM,
            ),
            tf: Topic::new(TF_TOPIC, &TF_MESSAGE, Qos::TF),
            tf_static: Topic::new(TF_STATIC_TOPIC, &TF_MESSAGE, Qos::LATCHED),
            robot_description: Topic::new(
                format!("/{namespace}/robot_description"),
                &STRING,
                Qos::LATCHED,
            ),
            diagnostics: Topic::new(DIAGNOSTICS_TOPIC, &DIAGNOSTIC_ARRAY, Qos::STREAM),
            namespace: namespace.to_owned(),
            urdf: urdf.to_owned(),
            joint_names,
            links,
            frames,
            movable,
        })
    }

    /// The unit's namespace.
    pub fn namespace(&self) -> &str {
        &self.namespace
    }

    /// Every topic of the unit, in the order above.
    pub fn all(&self) -> [&Topic; 5] {
        [
            &self.joint_states,
            &self.tf,
            &self.tf_static,
            &self.robot_description,
            &self.diagnostics,
        ]
    }

    /// The unit's joints at tick `r`.
    pub fn joint_state(&self, r: &TickRecord, stamp: Time) -> JointState {
        let s = &r.sensed;
        JointState {
            header: header(stamp, ""),
            name: self.joint_names.clone(),
            position: s
                .wheels
                .position_rad
                .iter()
                .chain(&s.arm.position_rad)
                .copied()
                .collect(),
            velocity: s
                .wheels
                .velocity_radps
                .iter()
                .chain(&s.arm.velocity_radps)
                .copied()
                .collect(),
            effort: Vec::new(),
        }
    }

    /// `/tf` at tick `r`: odom → base link by odometry, then the movable joints.
    pub fn tf(&self, r: &TickRecord, stamp: Time) -> TfMessage {
        let pose = &r.sensed.base_pose;
        let footprint = Isometry3::new(
            NVector3::new(pose.x_m, pose.y_m, 0.0),
            NVector3::z() * pose.yaw_rad,
        );
        let mut transforms = Vec::with_capacity(self.frames.len());
        transforms.push(stamped(
            stamp,
            &self.odom_frame,
            &self.frames[0],
            &self.links.root(&footprint),
        ));
        let poses = self
            .links
            .poses(&r.sensed.wheels.position_rad, &r.sensed.arm.position_rad);
        for (k, (joint, pose)) in self.links.joints().zip(poses).enumerate() {
            if self.movable[k] {
                transforms.push(stamped(
                    stamp,
                    &self.frames_of_parent(&joint.parent),
                    &self.frames[k + 1],
                    &pose,
                ));
            }
        }
        TfMessage { transforms }
    }

    /// `/tf_static`: world → odom, then the fixed joints.
    pub fn tf_static(&self, stamp: Time) -> Vec<TransformStamped> {
        let mut transforms = vec![stamped(
            stamp,
            WORLD_FRAME,
            &self.odom_frame,
            &Isometry3::identity(),
        )];
        let zero = [0.0; moonhaul_core::state::WHEEL_JOINTS];
        let zero_arm = [0.0; moonhaul_core::state::ARM_JOINTS];
        let poses = self.links.poses(&zero, &zero_arm);
        for (k, (joint, pose)) in self.links.joints().zip(poses).enumerate() {
            if !self.movable[k] {
                transforms.push(stamped(
                    stamp,
                    &self.frames_of_parent(&joint.parent),
                    &self.frames[k + 1],
                    &pose,
                ));
            }
        }
        transforms
    }

    /// `robot_description`: the URDF.
    pub fn robot_description(&self) -> StringMsg {
        StringMsg {
            data: self.urdf.clone(),
        }
    }

    /// `/diagnostics` at tick `r`: ERROR with a latched fault or a safety stop, WARN on any
    /// other hold outside Idle, OK otherwise.
    pub fn diagnostics(&self, r: &TickRecord, stamp: Time) -> DiagnosticArray {
        use moonhaul_coord::HoldReason;
        let hold = r.hold.map(|h| format!("{h:?}"));
        let (level, message) = match (&r.fault, r.hold) {
            (Some(fault), _) => (DiagnosticStatus::ERROR, format!("fault: {fault}")),
            (None, Some(HoldReason::SafetyStop(why))) => {
                (DiagnosticStatus::ERROR, format!("safety stop: {why:?}"))
            }
            (None, Some(HoldReason::Idle) | None) => {
                (DiagnosticStatus::OK, format!("phase {}", r.phase))
            }
            (None, Some(other)) => (
                DiagnosticStatus::WARN,
                format!("phase {}, holding: {other:?}", r.phase),
            ),
        };
        let kv = |key: &str, value: String| KeyValue {
            key: key.to_owned(),
            value,
        };
        let mut values = vec![
            kv("phase", r.phase.to_string()),
            kv("t_max", r.t_max.to_string()),
            kv("hold", hold.unwrap_or_else(|| "none".to_owned())),
            kv("fault", r.fault.as_deref().unwrap_or("none").to_owned()),
            kv("tick", r.tick.to_string()),
            kv("deadline_misses", r.deadline_misses.to_string()),
        ];
        for (peer, age) in r.peer_age_us.iter().enumerate() {
            if peer == r.unit {
                continue;
            }
            values.push(kv(
                &format!("peer_age_s.{}", default_namespace(peer)),
                age.map_or_else(
                    || "never heard".to_owned(),
                    |us| (us as f64 / 1e6).to_string(),
                ),
            ));
        }
        DiagnosticArray {
            header: header(stamp, ""),
            status: vec![DiagnosticStatus {
                level,
                name: format!("{}: moonhaul unit", self.namespace),
                message,
                hardware_id: self.namespace.clone(),
                values,
            }],
        }
    }

    fn frames_of_parent(&self, link: &str) -> String {
        format!("{}/{link}", self.namespace)
    }
}

/// `/ground_truth/payload` of world frame `f`.
pub fn payload_pose(f: &WorldFrame, stamp: Time) -> PoseStamped {
    let [x, y, z] = f.payload_position_m;
    let [qx, qy, qz, qw] = f.payload_orientation_xyzw;
    PoseStamped {
        header: header(stamp, WORLD_FRAME),
        pose: Pose {
            position: Vector3 { x, y, z },
            orientation: Quaternion {
                x: qx,
                y: qy,
                z: qz,
                w: qw,
            },
        },
    }
}

fn header(stamp: Time, frame_id: &str) -> Header {
    Header {
        stamp,
        frame_id: frame_id.to_owned(),
    }
}

fn stamped(stamp: Time, parent: &str, child: &str, pose: &Isometry3<f64>) -> TransformStamped {
    let t = pose.translation.vector;
    let q = pose.rotation.coords;
    TransformStamped {
        header: header(stamp, parent),
        child_frame_id: child.to_owned(),
        transform: Transform {
            translation: Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            rotation: Quaternion {
                x: q.x,
                y: q.y,
                z: q.z,
                w: q.w,
            },
        },
    }
}

/// A ROS name token: letters, digits and underscores, not starting with a digit.
fn valid_namespace(ns: &str) -> bool {
    ns.chars()
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && ns.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

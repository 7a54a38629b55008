//! A unit in the ROS 2 graph, read-only: its joint states, transforms, URDF and diagnostics as
//! ROS 2 Jazzy messages ([`msgs`], built by [`topics`]), published live in rmw_zenoh's wire
//! format on a zenoh session of their own ([`live`]), and every mission log converted to a
//! rosbag2 bag ([`bag`]).
//!
//! Nothing here subscribes to anything: no ROS 2 message can reach a unit's tick.

pub mod bag;
pub mod live;
pub mod msgs;
pub mod topics;

pub use bag::{BagError, BagWriter, TopicId};
pub use topics::{default_namespace, payload_pose, payload_topic, Qos, Topic, UnitTopics};

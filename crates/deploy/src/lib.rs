//! # moonhaul-deploy
//!
//! What runs on each robot: the onboard tick ([`tick`]), the `moonhaul-unit` daemon
//! ([`daemon`]) over a unit-level hardware backend, peers and operator over zenoh
//! ([`network`]), the sim-backed hardware link ([`sim_link`]) and the mission log
//! ([`record`], [`mission_log`]); read-only ROS 2 topics and rosbag2 export ([`ros2`]); what
//! the daemon shares with the CLI ([`cli_support`]).

pub mod cli_support;
pub mod daemon;
pub mod mission_log;
pub mod network;
pub mod record;
pub mod ros2;
pub mod sim_link;
pub mod tick;
pub mod unit_config;

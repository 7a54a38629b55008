//! A unit's daemon settings, read from `configs/unit.toml` (one file per robot, flashed with
//! the daemon) by core's one loader; the control rate comes from the `configs/control.toml`
//! the file names.

use crate::network::NetworkSettings;
use moonhaul_coord::message::ARENA_HALF_WIDTH_M;
use moonhaul_coord::{TeamError, TeamSettings};
use moonhaul_core::config::{self, count, ConfigError, ControlConfig, FieldError, Validate};
use moonhaul_core::overwrite::RunInputs;
use moonhaul_core::state::{Phase, PlanarPose, ARM_JOINTS};
use moonhaul_core::unit::UnitSpec;
use serde::Deserialize;
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `configs/unit.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitConfig {
    /// This unit's index in the team, 0-based; peers and the stacked state use it.
    pub unit_index: usize,
    /// Number of units in the team (the paper's N = 2).
    pub team_size: usize,
    /// Team name: messages from another team are rejected.
    pub team: String,
    /// The control-rate file (`configs/control.toml`), relative to this file's folder.
    pub control: PathBuf,
    /// Control loop rate, Hz: from `control` when the file is loaded.
    #[serde(skip)]
    pub control_rate_hz: f64,
    /// A peer whose newest state is older than this many control periods stops every unit.
    pub peer_staleness_periods: u32,
    /// The unit model (URDF), relative to this file's folder.
    pub urdf: PathBuf,
    /// The phase gate and agreement settings (`configs/gate.toml`).
    pub gate: PathBuf,
    /// The synchronization clamp settings (`configs/sync.toml`).
    pub sync: PathBuf,
    /// The mission goals the policies were trained on (`configs/tasks.toml`).
    pub tasks: PathBuf,
    /// The folder of the phase policies `lift.safetensors`, `transport.safetensors`,
    /// `place.safetensors`.
    pub policies: PathBuf,
    /// The scripted controller's plan (`configs/mission.toml`), for `--controller scripted`.
    pub mission: PathBuf,
    /// Where this unit's base starts in the team's world frame (all units start from known
    /// poses); a launcher may override it.
    pub start_pose: PlanarPose,
    /// The team's network.
    pub network: NetworkSettings,
    /// The mock hardware backend (`--hal mock`).
    pub mock: MockSettings,
    /// The CAN backend's drive settings (`--hal can`), e.g. `unit_can.toml`.
    pub can: PathBuf,
    /// Read-only ROS 2 topics (`[ros2]`); off when the section is absent.
    #[serde(default)]
    pub ros2: Ros2Config,
}

/// `[ros2]` of the unit config: the unit's read-only topics in rmw_zenoh's wire format, on a
/// zenoh session of their own (`moonhaul_deploy::ros2::live`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// Publish (default false; `--ros2-connect` turns it on).
    pub enabled: bool,
    /// `ROS_DOMAIN_ID` (default 0; 0 to 232, as ROS 2 allows).
    pub domain_id: u32,
    /// The unit's namespace (default `unit_<unit_index>`).
    pub namespace: Option<String>,
    /// Zenoh endpoints to connect to (default rmw_zenoh's router, `tcp/localhost:7447`).
    pub endpoints: Vec<String>,
}

impl Default for Ros2Config {
    fn default() -> Self {
        Ros2Config {
            enabled: false,
            domain_id: 0,
            namespace: None,
            endpoints: vec!["tcp/localhost:7447".to_owned()],
        }
    }
}

/// The largest `ROS_DOMAIN_ID` ROS 2 allows.
pub const MAX_ROS_DOMAIN_ID: u32 = 232;

/// The largest grasp load the mock reports, N: an arm's share of a 100 kg payload, ten times
/// the heaviest the units carry.
const MAX_GRASP_LOAD_N: f64 = 500.0;

/// `[mock]` of the unit config.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MockSettings {
    /// The share of the payload's weight the mock gripper reports while closed, N.
    pub grasp_load_n: f64,
    /// Arm joint positions the mock starts at (the rest grasp), rad.
    #[serde(deserialize_with = "config::exact_array")]
    pub arm_start_rad: [f64; ARM_JOINTS],
}

/// Longest zenoh endpoint accepted, bytes (a DNS name has at most 253).
const MAX_ENDPOINT_BYTES: usize = 255;

/// Checks a zenoh endpoint of this build: `tcp/<host>:<port>`, the host an IPv4 address, a
/// bracketed IPv6 address or a DNS name, the port 1 to 65535 (0, "any free port", only where
/// the process `listen`s). Zenoh itself accepts a malformed `connect` endpoint and keeps
/// retrying it, leaving the process cut off from every peer; so the unit config, the daemon's
/// `--connect`/`--listen` and [`crate::network::open`] all refuse it here, with the reason.
pub fn check_endpoint(endpoint: &str, listen: bool) -> Result<(), String> {
    if endpoint.len() > MAX_ENDPOINT_BYTES {
        return Err(format!("longer than {MAX_ENDPOINT_BYTES} bytes"));
    }
    let Some(address) = endpoint.strip_prefix("tcp/") else {
        return Err(
            "expected tcp/<host>:<port> (this build links zenoh's TCP transport only)".into(),
        );
    };
    let Some((host, port)) = address.rsplit_once(':') else {
        return Err("no port: expected tcp/<host>:<port>".into());
    };
    let host_ok = match host.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
        Some(v6) => v6.parse::<std::net::Ipv6Addr>().is_ok(),
        None => {
            host.parse::<std::net::Ipv4Addr>().is_ok()
                || (!host.is_empty()
                    && host.split('.').all(|label| {
                        (1..=63).contains(&label.len())
                            && !label.starts_with('-')
                            && !label.ends_with('-')
                            && label
                                .bytes()
                                .all(|b| b.is_ascii_alphanumeric() || b == b'-')
                    }))
        }
    };
    if !host_ok {
        return Err(format!(
            "host {host:?} is neither an IP address ([..] for IPv6) nor a DNS name"
        ));
    }
    match port.parse::<u16>() {
        Ok(0) if !listen => Err("port 0 can only be listened on, not connected to".into()),
        Ok(_) if port.bytes().all(|b| b.is_ascii_digit()) => Ok(()),
        _ => Err(format!("port {port:?} is not a number from 1 to 65535")),
    }
}

impl Validate for UnitConfig {
    fn resolve(&mut self, path: &Path) -> Result<(), ConfigError> {
        self.control_rate_hz = ControlConfig::load_referenced(path, &self.control)?.control_rate_hz;
        for file in [
            &mut self.control,
            &mut self.urdf,
            &mut self.gate,
            &mut self.sync,
            &mut self.tasks,
            &mut self.policies,
            &mut self.mission,
            &mut self.can,
        ] {
            *file = config::resolve(path, file);
        }
        Ok(())
    }

    /// Ranges here; team membership and staleness by [`TeamSettings::validate`], the one check
    /// the coordination layer also relies on.
    fn validate(&self) -> Result<(), FieldError> {
        count(
            "team_size",
            self.team_size as u64,
            1,
            moonhaul_core::state::MAX_TEAM_SIZE as u64,
        )?;
        let pose = &self.start_pose;
        // Within the arena every peer holds unit messages to: a unit starting outside it would
        // have its every message refused.
        for (field, v) in [("start_pose.x_m", pose.x_m), ("start_pose.y_m", pose.y_m)] {
            config::in_range(field, v, -ARENA_HALF_WIDTH_M, ARENA_HALF_WIDTH_M)?;
        }
        config::in_range("start_pose.yaw_rad", pose.yaw_rad, -TAU, TAU)?;
        let mock = &self.mock;
        config::in_range(
            "mock.grasp_load_n",
            mock.grasp_load_n,
            0.0,
            MAX_GRASP_LOAD_N,
        )?;
        if !mock.arm_start_rad.iter().all(|v| v.is_finite()) {
            return Err(FieldError::new("mock.arm_start_rad", "must be finite"));
        }
        count(
            "ros2.domain_id",
            self.ros2.domain_id.into(),
            0,
            MAX_ROS_DOMAIN_ID.into(),
        )?;
        for (list, listen, name) in [
            (&self.network.connect, false, "network.connect"),
            (&self.network.listen, true, "network.listen"),
            (&self.ros2.endpoints, false, "ros2.endpoints"),
        ] {
            for (i, endpoint) in list.iter().enumerate() {
                check_endpoint(endpoint, listen).map_err(|reason| {
                    FieldError::new(format!("{name}[{i}]"), format!("{endpoint:?}: {reason}"))
                })?;
            }
        }
        count(
            "peer_staleness_periods",
            self.peer_staleness_periods.into(),
            1,
            1000,
        )?;
        moonhaul_coord::auth::check_team_name(&self.team)
            .map_err(|reason| FieldError::new("team", reason))?;
        self.team_settings().validate().map_err(|e| {
            let field = match e {
                TeamError::EmptyTeam => "team_size",
                TeamError::UnitIndex { .. } => "unit_index",
                TeamError::EmptyName => "team",
                TeamError::ZeroPeriod => "control",
                TeamError::ZeroStaleness => "peer_staleness_periods",
            };
            FieldError::new(field, e.to_string())
        })
    }
}

impl UnitConfig {
    /// The checks that need the unit model (`urdf`, loaded by the caller): the mock's start
    /// joints within the URDF's limits. `path` names this config in the error.
    pub fn check_against_model(&self, path: &Path, spec: &UnitSpec) -> Result<(), ConfigError> {
        for (i, (q, limit)) in self
            .mock
            .arm_start_rad
            .iter()
            .zip(&spec.arm_limits)
            .enumerate()
        {
            if !(limit.lower..=limit.upper).contains(q) {
                return Err(ConfigError::Invalid {
                    path: path.to_owned(),
                    error: FieldError::new(
                        format!("mock.arm_start_rad[{i}]"),
                        format!(
                            "{q} rad is outside joint {i}'s limits [{}, {}] in {}",
                            limit.lower,
                            limit.upper,
                            self.urdf.display()
                        ),
                    ),
                });
            }
        }
        Ok(())
    }

    /// Reads and validates a unit config; errors name the file and the field.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        config::load(path)
    }

    /// The files a daemon running this config (at `path`) reads, with their roles: what no
    /// output of the run may overwrite.
    pub fn inputs(&self, path: &Path) -> RunInputs {
        let mut inputs = RunInputs::new();
        inputs
            .add("unit config", path)
            .add("control config", &self.control)
            .add("unit model", &self.urdf)
            .add("gate config", &self.gate)
            .add("sync config", &self.sync)
            .add("task config", &self.tasks)
            .add("mission plan", &self.mission)
            .add("CAN config", &self.can);
        for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
            inputs.add(
                format!("{phase} policy"),
                crate::cli_support::policy_file(&self.policies, phase),
            );
        }
        inputs
    }

    /// What the coordination layer needs of this config.
    pub fn team_settings(&self) -> TeamSettings {
        TeamSettings {
            team: self.team.clone(),
            team_size: self.team_size,
            unit_index: self.unit_index,
            control_period_us: (1e6 / self.control_rate_hz).round() as u64,
            peer_staleness_periods: self.peer_staleness_periods,
        }
    }

    /// One control period.
    pub fn control_period(&self) -> Duration {
        Duration::from_micros(self.team_settings().control_period_us)
    }

    /// Age beyond which a peer's state is stale.
    pub fn peer_staleness(&self) -> Duration {
        Duration::from_micros(self.team_settings().staleness_us())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use moonhaul_core::config::repo_file;

    #[test]
    fn shipped_config_is_valid_with_papers_rate() {
        let config = UnitConfig::from_file(&repo_file("configs/unit.toml")).unwrap();
        assert_eq!(config.control_period(), Duration::from_millis(20));
        assert_eq!(config.peer_staleness(), Duration::from_millis(60));
        assert_eq!(config.team_size, 2);
    }

    /// The mock's start joints are held to the unit model's limits, each joint by index.
    #[test]
    fn mock_start_joints_outside_the_urdf_limits_are_named() {
        let path = repo_file("configs/unit.toml");
        let mut config = UnitConfig::from_file(&path).unwrap();
        let spec = UnitSpec::from_file(&config.urdf).unwrap();
        config.check_against_model(&path, &spec).unwrap();
        for joint in 0..ARM_JOINTS {
            let mut bad = config.clone();
            bad.mock.arm_start_rad[joint] = spec.arm_limits[joint].upper + 0.01;
            let message = bad
                .check_against_model(&path, &spec)
                .unwrap_err()
                .to_string();
            assert!(
                message.contains(&format!("mock.arm_start_rad[{joint}]"))
                    && message.contains("unit.toml"),
                "{message}"
            );
        }
        config.mock.arm_start_rad[0] = spec.arm_limits[0].lower - 1.0;
        assert!(config.check_against_model(&path, &spec).is_err());
    }

    #[test]
    fn bad_configs_name_file_and_field() {
        let good = std::fs::read_to_string(repo_file("configs/unit.toml")).unwrap();
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("control.toml"), "control_rate_hz = 50.0\n").unwrap();
        let cases = [
            (
                good.replace("unit_index = 0", "unit_index = 2"),
                "unit_index",
            ),
            (
                good.replace("team_size = 2", "team_size = 100000"),
                "team_size",
            ),
            (
                good.replace("peer_staleness_periods = 3", "peer_staleness_periods = 0"),
                "peer_staleness_periods",
            ),
            (
                good.replace("team = \"moonhaul\"", "team = \"a/b\""),
                "team",
            ),
            (format!("{good}\nspeed = 3\n"), "speed"),
            // An unknown key in a nested table, not only at the top.
            (
                good.replace("yaw_rad = 0.0", "yaw_rad = 0.0\nyaw_deg = 90.0"),
                "yaw_deg",
            ),
            // Fixed-size arrays: an extra (or missing) joint is an error, never dropped.
            (
                good.replace("-2.6671]", "-2.6671, 0.5]"),
                "mock.arm_start_rad",
            ),
            (good.replace(", -2.6671]", "]"), "mock.arm_start_rad"),
            (good.replace("team = \"moonhaul\"", ""), "team"),
            (
                good.replace("control = \"control.toml\"", "control = \"rate.toml\""),
                "rate.toml",
            ),
            // Finite but impossible: outside the arena peers hold messages to, a heading of
            // many turns, a load no arm carries.
            (good.replace("x_m = 0.0", "x_m = 5000.0"), "start_pose.x_m"),
            (
                good.replace("y_m = -0.72", "y_m = -1e300"),
                "start_pose.y_m",
            ),
            (
                good.replace("yaw_rad = 0.0", "yaw_rad = 100.0"),
                "start_pose.yaw_rad",
            ),
            (
                good.replace("grasp_load_n = 36.8", "grasp_load_n = 1e6"),
                "mock.grasp_load_n",
            ),
            (
                good.replace("grasp_load_n = 36.8", "grasp_load_n = -1.0"),
                "mock.grasp_load_n",
            ),
        ];
        for (i, (text, field)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("unit{i}.toml"));
            std::fs::write(&path, text).unwrap();
            let message = UnitConfig::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(field) && message.contains(".toml"),
                "{field}: {message}"
            );
        }
        // Endpoints: every malformed one names its list entry and the reason.
        for (list, endpoint, reason) in [
            ("connect", "tcp/127.0.0.1", "no port"),
            ("connect", "tcp/127.0.0.1:99999", "port"),
            ("connect", "tcp/127.0.0.1:abc", "port"),
            ("connect", "tcp/127.0.0.1:", "port"),
            ("connect", "tcp/127.0.0.1:+80", "port"),
            ("connect", "tcp/127.0.0.1:0", "port 0"),
            ("connect", "udp/127.0.0.1:7447", "tcp"),
            ("connect", "tcp/:7447", "host"),
            ("connect", "tcp/bad host:7447", "host"),
            ("connect", "tcp/[::1:7447", "host"),
            ("listen", "tcp/127.0.0.1", "no port"),
            ("listen", "tcp/127.0.0.1:65536", "port"),
        ] {
            let text = good.replace(
                "connect = [\"tcp/127.0.0.1:7447\"]\nlisten = []",
                &if list == "connect" {
                    format!("connect = [\"tcp/127.0.0.1:7447\", {endpoint:?}]\nlisten = []")
                } else {
                    format!("connect = []\nlisten = [{endpoint:?}]")
                },
            );
            assert_ne!(text, good);
            let path = dir.path().join("endpoint.toml");
            std::fs::write(&path, text).unwrap();
            let message = UnitConfig::from_file(&path).unwrap_err().to_string();
            let index = if list == "connect" { 1 } else { 0 };
            assert!(
                message.contains(&format!("network.{list}[{index}]"))
                    && message.contains(endpoint)
                    && message.contains(reason),
                "{endpoint}: {message}"
            );
        }
        for (endpoint, listen) in [
            ("tcp/127.0.0.1:7447", false),
            ("tcp/[::1]:7447", false),
            ("tcp/robot-1.local:7447", false),
            ("tcp/0.0.0.0:0", true),
        ] {
            check_endpoint(endpoint, listen).unwrap();
        }
        // The shared control rate is checked where it lives.
        std::fs::write(dir.path().join("control.toml"), "control_rate_hz = 0.0\n").unwrap();
        let path = dir.path().join("unit.toml");
        std::fs::write(&path, &good).unwrap();
        let message = UnitConfig::from_file(&path).unwrap_err().to_string();
        assert!(
            message.contains("control.toml") && message.contains("control_rate_hz"),
            "{message}"
        );
    }
}

//! The team's network over zenoh 1.x: key expressions and session settings.
//!
//! Every process (unit daemons, the simulated world, the operator console) opens a zenoh
//! *peer* session with multicast scouting off — a team's processes find each other only
//! through the endpoints they are given (and zenoh's gossip among them), so two missions on one
//! machine never hear each other. Messages are [`moonhaul_coord::auth`] frames on these keys:
//!
//! | key | who publishes | what |
//! |---|---|---|
//! | `moonhaul/<team>/unit/<i>/state` | unit i, every tick | its state and announcements |
//! | `moonhaul/<team>/operator` | the operator console | start / stop |
//! | `moonhaul/<team>/sim/<i>/sensed` | the simulated world | unit i's encoder readings |
//! | `moonhaul/<team>/sim/<i>/command` | unit i on the sim-backed HAL | its drive commands |
//!
//! Zenoh's own session lease (seconds) is not a safety bound: a peer is stale when its newest
//! state is older than coord's staleness rule (3 control periods), judged on message stamps.

use serde::{Deserialize, Serialize};
use zenoh::qos::{CongestionControl, Priority};

/// Where a process listens and whom it connects to, as zenoh TCP endpoints
/// (`tcp/127.0.0.1:7447`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkSettings {
    #[serde(default)]
    pub connect: Vec<String>,
    #[serde(default)]
    pub listen: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum NetworkError {
    #[error("zenoh endpoint {endpoint:?}: {reason}")]
    Endpoint { endpoint: String, reason: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> NetworkError {
    NetworkError::Zenoh(e.to_string())
}

/// Opens a peer session on `settings`.
pub async fn open(settings: &NetworkSettings) -> Result<zenoh::Session, NetworkError> {
    let connect = settings.connect.iter().map(|e| (e, false));
    for (endpoint, listen) in connect.chain(settings.listen.iter().map(|e| (e, true))) {
        crate::unit_config::check_endpoint(endpoint, listen).map_err(|reason| {
            NetworkError::Endpoint {
                endpoint: endpoint.clone(),
                reason,
            }
        })?;
    }
    let list = |v: &[String]| serde_json::to_string(v).map_err(zerr);
    let mut config = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, key: &str, value: &str| {
        c.insert_json5(key, value)
            .map_err(|e| NetworkError::Zenoh(format!("config {key} = {value}: {e}")))
    };
    set(&mut config, "mode", "\"peer\"")?;
    set(&mut config, "scouting/multicast/enabled", "false")?;
    set(&mut config, "connect/endpoints", &list(&settings.connect)?)?;
    set(&mut config, "listen/endpoints", &list(&settings.listen)?)?;
    // Keep retrying a peer that is not up yet (a unit started before the world).
    set(&mut config, "connect/timeout_ms", "-1")?;
    set(&mut config, "connect/exit_on_failure", "false")?;
    zenoh::open(config).await.map_err(zerr)
}

/// Key expressions of a team's traffic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    team: String,
}

impl Keys {
    /// `team` must already be validated (unit_config allows `[A-Za-z0-9_-]`, which never forms
    /// a wildcard or a separator).
    pub fn new(team: &str) -> Self {
        Keys {
            team: team.to_owned(),
        }
    }

    pub fn unit_state(&self, unit: usize) -> String {
        format!("moonhaul/{}/unit/{unit}/state", self.team)
    }

    /// Every unit's state.
    pub fn all_unit_states(&self) -> String {
        format!("moonhaul/{}/unit/*/state", self.team)
    }

    pub fn operator(&self) -> String {
        format!("moonhaul/{}/operator", self.team)
    }

    pub fn sim_sensed(&self, unit: usize) -> String {
        format!("moonhaul/{}/sim/{unit}/sensed", self.team)
    }

    pub fn sim_command(&self, unit: usize) -> String {
        format!("moonhaul/{}/sim/{unit}/command", self.team)
    }

    /// Every unit's drive commands (the world subscribes once).
    pub fn all_sim_commands(&self) -> String {
        format!("moonhaul/{}/sim/*/command", self.team)
    }
}

/// A publisher for control traffic: real-time priority, express (not batched), dropped rather
/// than blocking the control loop when the network is congested (the next tick's message
/// supersedes it).
pub async fn control_publisher(
    session: &zenoh::Session,
    key: String,
) -> Result<zenoh::pubsub::Publisher<'static>, NetworkError> {
    session
        .declare_publisher(key)
        .priority(Priority::RealTime)
        .express(true)
        .congestion_control(CongestionControl::Drop)
        .await
        .map_err(zerr)
}

/// Publishes `bytes` on `publisher`; a failure is reported, never fatal to the control loop.
pub async fn put(
    publisher: &zenoh::pubsub::Publisher<'static>,
    bytes: &[u8],
) -> Result<(), NetworkError> {
    publisher.put(bytes.to_vec()).await.map_err(zerr)
}

/// A free TCP port on the loopback interface (for a launcher choosing the world's endpoint).
pub fn free_loopback_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

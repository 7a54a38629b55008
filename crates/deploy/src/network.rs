//! The team's network over zenoh 1.x: key expressions, who may publish on them, session
//! settings, and the bounded queues that keep the control loop from ever waiting on it.
//!
//! Every process (unit daemons, the simulated world, the operator console) opens a zenoh
//! *peer* session through [`open`] with multicast scouting off — a team's processes find each
//! other only through the endpoints they are given (and zenoh's gossip among them), so two
//! missions on one machine never hear each other. Messages are [`moonhaul_coord::auth`] frames
//! (or, between the simulated world and a unit, [`crate::sim_link`] frames) on these keys:
//!
//! | key | who publishes ([`Role`]) | what |
//! |---|---|---|
//! | `moonhaul/<team>/unit/<i>/state` | unit i, every tick | its state and announcements |
//! | `moonhaul/<team>/operator` | the operator console | start / stop |
//! | `moonhaul/<team>/sim/<i>/sensed` | the simulated world | unit i's encoder readings |
//! | `moonhaul/<team>/sim/<i>/command` | unit i on the sim-backed HAL | its drive commands |
//!
//! Zenoh's own session lease (seconds) is not a safety bound: a peer is stale when its newest
//! state is older than coord's staleness rule (3 control periods), judged on message stamps.
//!
//! # Who may talk: transport authentication and access control
//!
//! Every session authenticates with zenoh's user/password extension (`auth_usrpwd`): a process
//! that connects proves, by a challenge–response HMAC (the password never travels), that it
//! holds its role's password, and a session that cannot is refused before any of its messages
//! is read. The credentials come from the team's key file, so a team provisions nothing new:
//! `moonhaul keys generate` is all there is. For role `r` of team `t` under key epoch `e`, the
//! user is `r@t` (`unit-0@moonhaul`, `operator@moonhaul`, `world@moonhaul`) and the password is
//! the hex of `HMAC-SHA256(key, "moonhaul zenoh password v1 team=t epoch=e role=r")` keyed with
//! unit i's key for unit i and with the operator's key for the operator and the world
//! ([`moonhaul_coord::auth::KeyFile::derive_secret`]). Rotating the key file rotates them.
//! Every process holds the key file, so each builds the whole team's user/password dictionary
//! for the sessions it accepts; zenoh reads it from a file, which [`open`] writes private
//! (0600 in a 0700 folder) and removes once the session is open.
//!
//! We chose user/password over TLS with client certificates because it needs no new
//! dependency (TLS would bring rustls and a certificate authority to run) and no new secret to
//! provision. Its limit: zenoh's user/password authenticates the side that *connects*, not the
//! side that accepts. A session a process dialled itself (an endpoint of its own configuration,
//! or one its authenticated peers gossiped) is known by the zenoh id the other side answers
//! with; units and the world therefore run under a zenoh id derived from their key like the
//! password, and the access-control list names every role both by user and by that id. An
//! outsider without the key file can neither connect nor be gossiped to the team; only one that
//! occupies an endpoint the team dials before the real peer is up is heard, and its frames
//! then meet the queues, the size cap and the envelope's HMAC below.
//!
//! Zenoh's access control (default deny) then lets each role publish only its own keys
//! ([`Keys::published_by`]): unit i `unit/<i>/state` and `sim/<i>/command`, the operator
//! `operator`, the world `sim/*/sensed`; subscriptions to the team's keys are open to the whole
//! team. As the key file's own threat model says, every team member holds every key, so this
//! is least privilege for team members (a misconfigured unit cannot speak as another), not a
//! barrier against a compromised one; the HMAC envelope stays as the end-to-end check.
//!
//! # The control loop never waits on the network
//!
//! Frames are received by zenoh callbacks into bounded [`FrameQueue`]s that drop the oldest
//! frame when full and refuse an oversized one before it is copied, counting both; the tick
//! drains them without blocking. Publishing goes through an [`Outbox`]: the tick leaves its
//! newest frame in a one-frame slot (superseding an unsent one) and a task of its own puts it
//! on the wire. No session delivers its own publications to itself. The transport itself
//! refuses frames larger than [`MAX_FRAME_BYTES`] (plus zenoh's headroom): the negotiated batch
//! is that small, and a fragmented message larger than it is dropped on reassembly.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use moonhaul_coord::auth::{self, KeyFile, KeyMismatch};
use moonhaul_coord::message::{RejectCounts, Rejection, Sender};
use moonhaul_coord::validator::Admission;
use serde::{Deserialize, Serialize};
use serde_json::json;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::{Locality, Sample};

use crate::sim_link;

/// Largest frame of the team's traffic: an authenticated envelope or a sim link frame. The
/// transport cap and every receiving queue derive from it.
pub const MAX_FRAME_BYTES: usize = if auth::MAX_FRAME_BYTES > sim_link::MAX_FRAME_BYTES {
    auth::MAX_FRAME_BYTES
} else {
    sim_link::MAX_FRAME_BYTES
};

/// Room for zenoh's own framing around one frame in a batch (message headers, a key
/// expression with a team name of up to [`auth::MAX_TEAM_NAME_BYTES`], extensions).
const TRANSPORT_HEADROOM_BYTES: usize = 1024;

/// Zenoh's batch size and reassembly limit: a legitimate frame always fits one batch; a larger
/// message is fragmented, and reassembly drops it at this size.
const TRANSPORT_MESSAGE_BYTES: usize = MAX_FRAME_BYTES + TRANSPORT_HEADROOM_BYTES;
// Zenoh's batch size is a u16.
const _: () = assert!(TRANSPORT_MESSAGE_BYTES <= u16::MAX as usize);

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
    #[error("the key file has no credentials for {role}: {source}")]
    Credentials { role: Role, source: KeyMismatch },
    #[error("{role} is not a role of a team of {team_size} units")]
    NoSuchRole { role: Role, team_size: usize },
    #[error("the private zenoh dictionary {}: {source}", path.display())]
    Dictionary {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> NetworkError {
    NetworkError::Zenoh(e.to_string())
}

/// Who a process is on the team's network: what it may publish, how it authenticates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Unit(usize),
    Operator,
    /// The simulated world serving the units' sim-backed drives.
    World,
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Role::Unit(i) => write!(f, "unit-{i}"),
            Role::Operator => f.write_str("operator"),
            Role::World => f.write_str("world"),
        }
    }
}

impl Role {
    /// The key file's key its credentials derive from.
    fn key(self) -> Sender {
        match self {
            Role::Unit(i) => Sender::Unit(i),
            Role::Operator | Role::World => Sender::Operator,
        }
    }

    /// Whether the role runs under a zenoh id derived from its key: the roles that accept
    /// sessions (units, the world), one process each per team. Operator consoles only dial
    /// out, and several may run at once.
    fn fixed_id(self) -> bool {
        !matches!(self, Role::Operator)
    }
}

/// One role's transport credentials.
#[derive(Clone, PartialEq, Eq)]
struct Credential {
    role: Role,
    user: String,
    password: String,
    zid: Option<String>,
}

impl std::fmt::Debug for Credential {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Credential")
            .field("user", &self.user)
            .field("zid", &self.zid)
            .finish_non_exhaustive()
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A process's place on its team's network: its own credentials and every role's, to check
/// the sessions it accepts and to build the access-control list. `Debug` shows no password.
#[derive(Debug, Clone)]
pub struct Access {
    team: String,
    own: Credential,
    roles: Vec<Credential>,
}

impl Access {
    /// The access of `role` in the team of `keys` (the key file's team and size).
    pub fn new(keys: &KeyFile, role: Role) -> Result<Access, NetworkError> {
        let team = keys.team().to_owned();
        let team_size = keys.team_size();
        if matches!(role, Role::Unit(i) if i >= team_size) {
            return Err(NetworkError::NoSuchRole { role, team_size });
        }
        let credential = |role: Role| -> Result<Credential, NetworkError> {
            let derive = |what: &str| {
                let purpose = format!(
                    "moonhaul zenoh {what} v1 team={team} epoch={} role={role}",
                    keys.epoch()
                );
                keys.derive_secret(role.key(), &purpose)
                    .map_err(|source| NetworkError::Credentials { role, source })
            };
            let zid = if role.fixed_id() {
                // A zenoh id is at most 16 bytes, written without a leading 0.
                let mut id = derive("id")?;
                id[0] |= 0x10;
                Some(hex(&id[..16]))
            } else {
                None
            };
            Ok(Credential {
                role,
                user: format!("{role}@{team}"),
                password: hex(&derive("password")?),
                zid,
            })
        };
        let roles = (0..team_size)
            .map(Role::Unit)
            .chain([Role::Operator, Role::World])
            .map(credential)
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Access {
            own: credential(role)?,
            team,
            roles,
        })
    }

    pub fn role(&self) -> Role {
        self.own.role
    }

    /// The same access under a zenoh id of zenoh's choosing instead of the role's fixed one:
    /// a second session of a role beside its running process (whose id zenoh will not admit
    /// twice), e.g. a credentialed adversary in the fault campaign. Access control knows it
    /// by its user alone.
    pub fn with_random_id(mut self) -> Access {
        self.own.zid = None;
        self
    }

    /// Zenoh's access-control configuration: default deny; the team's keys open to every
    /// role's subscriptions and to this process's own publications; each role's publications
    /// accepted on [`Keys::published_by`] only, from a session authenticated as that role's
    /// user or, for a session this process dialled, answering with that role's zenoh id.
    fn access_control(&self) -> serde_json::Value {
        let keys = Keys::new(&self.team);
        let mut rules = vec![
            json!({"id": "subscribe", "messages": ["declare_subscriber"],
                   "flows": ["ingress", "egress"], "permission": "allow",
                   "key_exprs": [keys.team_all()]}),
            json!({"id": "send", "messages": ["put"], "flows": ["egress"],
                   "permission": "allow", "key_exprs": [keys.team_all()]}),
        ];
        let mut subjects = Vec::new();
        let mut policies = Vec::new();
        let mut everyone = Vec::new();
        for c in &self.roles {
            let role = c.role;
            rules.push(json!({"id": format!("publish-{role}"), "messages": ["put"],
                              "flows": ["ingress"], "permission": "allow",
                              "key_exprs": keys.published_by(role)}));
            let mut ids = vec![format!("user-{role}")];
            subjects.push(json!({"id": ids[0], "usernames": [c.user]}));
            if let Some(zid) = &c.zid {
                ids.push(format!("zid-{role}"));
                subjects.push(json!({"id": ids[1], "zids": [zid]}));
            }
            policies.push(json!({"rules": [format!("publish-{role}")], "subjects": ids}));
            everyone.extend(ids);
        }
        policies.push(json!({"rules": ["subscribe", "send"], "subjects": everyone}));
        json!({
            "enabled": true,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        })
    }
}

/// The team's user/password dictionary in a private file zenoh reads at start-up; removed when
/// dropped.
struct Dictionary {
    dir: PathBuf,
    file: PathBuf,
}

impl Dictionary {
    fn write(access: &Access) -> Result<Dictionary, NetworkError> {
        use std::io::Write as _;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let dir =
            std::env::temp_dir().join(format!("moonhaul-zenoh-{}-{nanos:09}", std::process::id()));
        let fail = |path: &Path| {
            let path = path.to_owned();
            move |source| NetworkError::Dictionary { path, source }
        };
        let mut builder = std::fs::DirBuilder::new();
        #[cfg(unix)]
        {
            use std::os::unix::fs::DirBuilderExt as _;
            builder.mode(0o700);
        }
        builder.create(&dir).map_err(fail(&dir))?;
        let dictionary = Dictionary {
            file: dir.join("usrpwd.txt"),
            dir,
        };
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt as _;
            options.mode(0o600);
        }
        let mut out = options
            .open(&dictionary.file)
            .map_err(fail(&dictionary.file))?;
        for c in &access.roles {
            writeln!(out, "{}:{}", c.user, c.password).map_err(fail(&dictionary.file))?;
        }
        out.sync_all().map_err(fail(&dictionary.file))?;
        Ok(dictionary)
    }
}

impl Drop for Dictionary {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.file);
        let _ = std::fs::remove_dir(&self.dir);
    }
}

/// The zenoh configuration every moonhaul session starts from (the team's, the ROS 2
/// publisher's, a test's bare peer): peer mode, no multicast scouting (endpoints are explicit),
/// `connect` dialled and retried in the background until it answers (a peer started before the
/// other), `listen` opened. An error names the key.
pub fn peer_config(connect: &[String], listen: &[String]) -> Result<zenoh::Config, String> {
    let mut config = zenoh::Config::default();
    let list = |v: &[String]| serde_json::to_string(v).map_err(|e| e.to_string());
    for (key, value) in [
        ("mode", "\"peer\"".to_owned()),
        ("scouting/multicast/enabled", "false".to_owned()),
        ("connect/endpoints", list(connect)?),
        ("listen/endpoints", list(listen)?),
        ("connect/timeout_ms", "-1".to_owned()),
        ("connect/exit_on_failure", "false".to_owned()),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| format!("config {key}: {e}"))?;
    }
    Ok(config)
}

/// Opens a peer session on `settings` as `access`'s role: authenticated, under the team's
/// access-control list, with the transport's frame cap.
pub async fn open(
    settings: &NetworkSettings,
    access: &Access,
) -> Result<zenoh::Session, NetworkError> {
    let connect = settings.connect.iter().map(|e| (e, false));
    for (endpoint, listen) in connect.chain(settings.listen.iter().map(|e| (e, true))) {
        crate::unit_config::check_endpoint(endpoint, listen).map_err(|reason| {
            NetworkError::Endpoint {
                endpoint: endpoint.clone(),
                reason,
            }
        })?;
    }
    let dictionary = Dictionary::write(access)?;
    let mut config =
        peer_config(&settings.connect, &settings.listen).map_err(NetworkError::Zenoh)?;
    let set = |c: &mut zenoh::Config, key: &str, value: &str| {
        c.insert_json5(key, value)
            .map_err(|e| NetworkError::Zenoh(format!("config {key}: {e}")))
    };
    let string = |s: &str| serde_json::to_string(s).map_err(zerr);
    if let Some(zid) = &access.own.zid {
        set(&mut config, "id", &string(zid)?)?;
        // Of two units (or a unit and the world) that learn of each other by gossip, only the
        // one of greater id dials: with both dialling, zenoh closes the redundant link and at
        // times both, and the pair is then left to a third peer's brokering, whose frames
        // the receiver's access control refuses (they come from the broker's session, not the
        // publisher's). Operator consoles keep dialling everyone; nobody dials them.
        set(
            &mut config,
            "scouting/gossip/autoconnect_strategy",
            "\"greater-zid\"",
        )?;
    }
    set(
        &mut config,
        "transport/link/tx/batch_size",
        &TRANSPORT_MESSAGE_BYTES.to_string(),
    )?;
    set(
        &mut config,
        "transport/link/rx/max_message_size",
        &TRANSPORT_MESSAGE_BYTES.to_string(),
    )?;
    set(
        &mut config,
        "transport/auth/usrpwd/user",
        &string(&access.own.user)?,
    )?;
    set(
        &mut config,
        "transport/auth/usrpwd/password",
        &string(&access.own.password)?,
    )?;
    let path = dictionary
        .file
        .to_str()
        .ok_or_else(|| NetworkError::Dictionary {
            path: dictionary.file.clone(),
            source: std::io::Error::other("the temporary folder's path is not UTF-8"),
        })?;
    set(
        &mut config,
        "transport/auth/usrpwd/dictionary_file",
        &string(path)?,
    )?;
    set(
        &mut config,
        "access_control",
        &access.access_control().to_string(),
    )?;
    let session = zenoh::open(config).await.map_err(zerr);
    // Zenoh has read the dictionary by now; it leaves the disk with `dictionary`.
    drop(dictionary);
    session
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

    /// Everything of the team.
    pub fn team_all(&self) -> String {
        format!("moonhaul/{}/**", self.team)
    }

    /// The keys `role` alone may publish on.
    pub fn published_by(&self, role: Role) -> Vec<String> {
        match role {
            Role::Unit(i) => vec![self.unit_state(i), self.sim_command(i)],
            Role::Operator => vec![self.operator()],
            Role::World => vec![format!("moonhaul/{}/sim/*/sensed", self.team)],
        }
    }
}

/// A publisher for control traffic: real-time priority, express (not batched), dropped rather
/// than blocking when the network is congested (the next tick's message supersedes it), and
/// never delivered to this session's own subscribers.
pub async fn control_publisher(
    session: &zenoh::Session,
    key: String,
) -> Result<zenoh::pubsub::Publisher<'static>, NetworkError> {
    session
        .declare_publisher(key)
        .priority(Priority::RealTime)
        .express(true)
        .congestion_control(CongestionControl::Drop)
        .allowed_destination(Locality::Remote)
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

/// What a [`FrameQueue`] took in and threw away.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueCounts {
    /// Frames queued.
    pub received: u64,
    /// Frames pushed out, unread, by newer ones (the queue was full).
    pub dropped: u64,
    /// Frames over [`MAX_FRAME_BYTES`], refused before they were copied.
    pub oversize: u64,
}

impl QueueCounts {
    pub fn refused(&self) -> u64 {
        self.dropped + self.oversize
    }
}

impl std::ops::AddAssign for QueueCounts {
    fn add_assign(&mut self, other: QueueCounts) {
        self.received += other.received;
        self.dropped += other.dropped;
        self.oversize += other.oversize;
    }
}

/// A bounded queue of received frames that drops the oldest when full: what a zenoh callback
/// fills on the network's threads and the control loop drains without blocking. A frame over
/// [`MAX_FRAME_BYTES`] is counted and refused before any copy of it is made. (`T` is a zenoh
/// [`Sample`] on the network, whose payload is still the receive buffer.)
pub struct FrameQueue<T = Sample> {
    frames: Mutex<VecDeque<T>>,
    capacity: usize,
    received: AtomicU64,
    dropped: AtomicU64,
    oversize: AtomicU64,
    /// Frames refused on arrival by the subscription's admission check, by reason.
    refused: Mutex<RejectCounts>,
    ready: Arc<tokio::sync::Notify>,
}

impl<T> FrameQueue<T> {
    /// A queue of `capacity` frames (at least 1) that signals `ready` on every arrival.
    pub fn new(capacity: usize, ready: Arc<tokio::sync::Notify>) -> Arc<Self> {
        let capacity = capacity.max(1);
        Arc::new(FrameQueue {
            frames: Mutex::new(VecDeque::with_capacity(capacity)),
            capacity,
            received: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            oversize: AtomicU64::new(0),
            refused: Mutex::new(RejectCounts::default()),
            ready,
        })
    }

    /// Counts a frame refused on arrival (it never takes a slot).
    pub fn refuse(&self, rejection: &Rejection) {
        self.refused
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .record(rejection);
    }

    /// The frames refused on arrival so far, by reason.
    pub fn refused(&self) -> RejectCounts {
        *self.refused.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Takes in one frame of `len` bytes (the zenoh callback): never blocks beyond the queue's
    /// lock.
    pub fn push(&self, frame: T, len: usize) {
        if len > MAX_FRAME_BYTES {
            self.oversize.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.received.fetch_add(1, Ordering::Relaxed);
        let mut frames = self.frames.lock().unwrap_or_else(|p| p.into_inner());
        if frames.len() == self.capacity {
            frames.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        frames.push_back(frame);
        drop(frames);
        self.ready.notify_one();
    }

    /// Hands every waiting frame to `take`, oldest first (at most the capacity: the work is
    /// bounded whatever the network does). The lock is held only to take each frame out, never
    /// while `take` runs, and nothing is allocated: this runs every control tick.
    pub fn drain(&self, mut take: impl FnMut(&T)) {
        for _ in 0..self.capacity {
            let frame = self
                .frames
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .pop_front();
            match frame {
                Some(frame) => take(&frame),
                None => return,
            }
        }
    }

    pub fn counts(&self) -> QueueCounts {
        QueueCounts {
            received: self.received.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
            oversize: self.oversize.load(Ordering::Relaxed),
        }
    }
}

/// A subscription on `key` (remote publications only) feeding `queue`; undeclared when the
/// returned subscriber is dropped. With `admission` (the key's sender), a frame that cannot be
/// genuine is refused and counted on arrival, on zenoh's thread, before it takes a queue slot
/// ([`Admission`]): a flood of forged frames cannot push genuine ones out.
pub async fn subscribe(
    session: &zenoh::Session,
    key: String,
    queue: &Arc<FrameQueue>,
    admission: Option<Admission>,
) -> Result<zenoh::pubsub::Subscriber<()>, NetworkError> {
    let queue = Arc::clone(queue);
    session
        .declare_subscriber(key)
        .allowed_origin(Locality::Remote)
        .callback(move |sample| {
            let len = sample.payload().len();
            if let (Some(admission), true) = (&admission, len <= MAX_FRAME_BYTES) {
                // Contiguous payloads are borrowed; a fragmented one is copied, bounded by
                // the frame cap.
                if let Err(rejection) = admission.check(&sample.payload().to_bytes()) {
                    queue.refuse(&rejection);
                    return;
                }
            }
            queue.push(sample, len)
        })
        .await
        .map_err(zerr)
}

/// What an [`Outbox`] sent and gave up.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OutboxCounts {
    pub sent: u64,
    /// Frames replaced by a newer one before the publishing task got to them.
    pub superseded: u64,
    /// Puts zenoh refused.
    pub failed: u64,
}

struct OutboxSlot {
    frame: Mutex<Option<Vec<u8>>>,
    wake: tokio::sync::Notify,
    queued: AtomicU64,
    sent: AtomicU64,
    superseded: AtomicU64,
    failed: AtomicU64,
}

/// Publishing off the control loop: [`Outbox::send`] leaves the newest frame in a one-frame
/// slot (replacing an unsent one, counted) and returns at once; a task of its own puts it on
/// the wire. Control traffic is "newest wins": a late state or command is worth nothing once
/// the next tick's exists.
pub struct Outbox {
    slot: Arc<OutboxSlot>,
    task: tokio::task::JoinHandle<()>,
}

impl Outbox {
    /// Runs `publisher`'s task on the current tokio runtime.
    pub fn spawn(publisher: zenoh::pubsub::Publisher<'static>) -> Outbox {
        let slot = Arc::new(OutboxSlot {
            frame: Mutex::new(None),
            wake: tokio::sync::Notify::new(),
            queued: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            superseded: AtomicU64::new(0),
            failed: AtomicU64::new(0),
        });
        let task_slot = Arc::clone(&slot);
        let task = tokio::spawn(async move {
            loop {
                task_slot.wake.notified().await;
                let frame = task_slot
                    .frame
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .take();
                let Some(frame) = frame else { continue };
                let counter = match publisher.put(frame).await {
                    Ok(()) => &task_slot.sent,
                    Err(e) => {
                        tracing::debug!(key = %publisher.key_expr(), error = %e, "put failed");
                        &task_slot.failed
                    }
                };
                counter.fetch_add(1, Ordering::Relaxed);
            }
        });
        Outbox { slot, task }
    }

    /// Queues `bytes` as the next frame to publish; never waits.
    pub fn send(&self, bytes: &[u8]) {
        let previous = self
            .slot
            .frame
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .replace(bytes.to_vec());
        self.slot.queued.fetch_add(1, Ordering::Relaxed);
        if previous.is_some() {
            self.slot.superseded.fetch_add(1, Ordering::Relaxed);
        }
        self.slot.wake.notify_one();
    }

    pub fn counts(&self) -> OutboxCounts {
        OutboxCounts {
            sent: self.slot.sent.load(Ordering::Relaxed),
            superseded: self.slot.superseded.load(Ordering::Relaxed),
            failed: self.slot.failed.load(Ordering::Relaxed),
        }
    }

    /// Waits up to `timeout` for the waiting frame to go out (the hold command at shutdown),
    /// then stops the task.
    pub async fn close(self, timeout: std::time::Duration) {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            let c = self.counts();
            let done = c.sent + c.superseded + c.failed;
            if done >= self.slot.queued.load(Ordering::Relaxed)
                || tokio::time::Instant::now() >= deadline
            {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(1)).await;
        }
        self.task.abort();
    }
}

impl Drop for Outbox {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A free TCP port on the loopback interface (for a launcher choosing the world's endpoint).
pub fn free_loopback_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn queue<T>(capacity: usize) -> Arc<FrameQueue<T>> {
        FrameQueue::new(capacity, Arc::new(tokio::sync::Notify::new()))
    }

    #[test]
    fn a_full_queue_drops_the_oldest_and_counts_it() {
        for capacity in [1, 2, 8, 256] {
            for pushed in [0, 1, capacity - 1, capacity, capacity + 1, 3 * capacity + 5] {
                let q = queue(capacity);
                for i in 0..pushed {
                    q.push(i, 10);
                }
                let mut seen = Vec::new();
                q.drain(|&i| seen.push(i));
                let kept = pushed.min(capacity);
                // The newest `kept`, oldest first.
                assert_eq!(seen, (pushed - kept..pushed).collect::<Vec<_>>());
                let c = q.counts();
                assert_eq!(c.received, pushed as u64);
                assert_eq!(c.dropped, (pushed - kept) as u64);
                assert_eq!(c.oversize, 0);
                // Drained means empty.
                q.drain(|_| panic!("drained twice"));
            }
        }
    }

    #[test]
    fn an_oversize_frame_is_refused_and_counted_whatever_its_size() {
        let q = queue(4);
        for len in [MAX_FRAME_BYTES + 1, 1 << 20, 64 << 20, usize::MAX] {
            q.push(len, len);
        }
        q.push(MAX_FRAME_BYTES, MAX_FRAME_BYTES);
        let mut seen = Vec::new();
        q.drain(|&len| seen.push(len));
        assert_eq!(seen, [MAX_FRAME_BYTES]);
        let c = q.counts();
        assert_eq!((c.received, c.dropped, c.oversize), (1, 0, 4));
        assert_eq!(c.refused(), 4);
    }

    #[test]
    fn credentials_are_per_role_deterministic_and_follow_the_keys() {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let other = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let roles = [Role::Unit(0), Role::Unit(1), Role::Operator, Role::World];
        let mut passwords = std::collections::HashSet::new();
        for role in roles {
            let a = Access::new(&keys, role).unwrap();
            let again = Access::new(&keys, role).unwrap();
            assert_eq!(a.own, again.own);
            assert_eq!(a.own.user, format!("{role}@moonhaul"));
            assert_eq!(a.own.password.len(), 64);
            assert!(passwords.insert(a.own.password.clone()), "{role}");
            assert_ne!(
                Access::new(&other, role).unwrap().own.password,
                a.own.password
            );
            assert_eq!(a.own.zid.is_some(), role != Role::Operator);
            // Every role sees the whole team.
            assert_eq!(a.roles.len(), 4);
            assert!(!format!("{a:?}").contains(&a.own.password));
        }
        assert!(matches!(
            Access::new(&keys, Role::Unit(2)),
            Err(NetworkError::NoSuchRole { .. })
        ));
    }

    fn endpoint(port: u16) -> String {
        format!("tcp/127.0.0.1:{port}")
    }

    async fn session(
        keys: &KeyFile,
        role: Role,
        connect: &[String],
        listen: &[String],
    ) -> zenoh::Session {
        let access = Access::new(keys, role).unwrap();
        open(
            &NetworkSettings {
                connect: connect.to_vec(),
                listen: listen.to_vec(),
            },
            &access,
        )
        .await
        .unwrap()
    }

    /// Waits (bounded) until `session` has a peer.
    async fn connected(session: &zenoh::Session, within: Duration) -> bool {
        let deadline = Instant::now() + within;
        while Instant::now() < deadline {
            if session.info().peers_zid().await.next().is_some() {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        false
    }

    /// What a listening world-role session hears on the team's keys from `speaker`, which
    /// publishes each of `keys` (and a mark on `mark_key`, a key it may publish) once a
    /// subscription is in place.
    async fn heard(
        listener: &zenoh::Session,
        speaker: &zenoh::Session,
        keys: &[String],
    ) -> Vec<String> {
        let team = Keys::new("moonhaul");
        let q: Arc<FrameQueue> = queue(64);
        let _sub = subscribe(listener, team.team_all(), &q, None)
            .await
            .unwrap();
        // Let the subscription's declaration reach the speaker.
        tokio::time::sleep(Duration::from_millis(300)).await;
        for key in keys {
            speaker.put(key.as_str(), b"frame".to_vec()).await.unwrap();
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        let mut got = Vec::new();
        q.drain(|s| got.push(s.key_expr().as_str().to_owned()));
        got.sort();
        got
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn each_role_publishes_only_its_own_keys() {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let team = Keys::new("moonhaul");
        let port = free_loopback_port().unwrap();
        let listener = session(&keys, Role::World, &[], &[endpoint(port)]).await;
        let every_key = [
            team.unit_state(0),
            team.unit_state(1),
            team.operator(),
            team.sim_sensed(0),
            team.sim_command(0),
            team.sim_command(1),
            "moonhaul/moonhaul/elsewhere".to_owned(),
        ];
        for role in [Role::Unit(0), Role::Unit(1), Role::Operator] {
            let speaker = session(&keys, role, &[endpoint(port)], &[]).await;
            assert!(connected(&speaker, Duration::from_secs(10)).await, "{role}");
            let got = heard(&listener, &speaker, &every_key).await;
            let mut allowed = team.published_by(role);
            allowed.sort();
            assert_eq!(got, allowed, "{role}");
            speaker.close().await.unwrap();
        }
        listener.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_session_without_the_teams_credentials_is_refused() {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let team = Keys::new("moonhaul");
        let port = free_loopback_port().unwrap();
        let listener = session(&keys, Role::Unit(0), &[], &[endpoint(port)]).await;
        let q: Arc<FrameQueue> = queue(64);
        let _sub = subscribe(&listener, team.team_all(), &q, None)
            .await
            .unwrap();
        // Another team's key file (the same team name, other secrets), and no credentials at
        // all (zenoh's defaults).
        let stranger = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let forged = session(&stranger, Role::Operator, &[endpoint(port)], &[]).await;
        let plain = peer_config(&[endpoint(port)], &[]).unwrap();
        let anonymous = zenoh::open(plain).await.unwrap();
        for outsider in [&forged, &anonymous] {
            assert!(!connected(outsider, Duration::from_secs(2)).await);
            for key in [team.operator(), team.unit_state(1)] {
                outsider.put(key.as_str(), b"frame".to_vec()).await.unwrap();
            }
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(!connected(&listener, Duration::from_millis(100)).await);
        assert_eq!(q.counts().received, 0);
        for s in [forged, anonymous, listener] {
            s.close().await.unwrap();
        }
    }

    /// A session holding unit 1's transport credentials floods unit 1's key with frames that
    /// cannot be genuine (sealed with another team's keys, claiming the operator, garbage), a
    /// hundred for each genuine frame of unit 1: the forged ones are refused on arrival, by
    /// reason, and never take a slot of the 8-frame queue, so every genuine frame is there
    /// when the tick drains it. Without the admission check the flood evicts them.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_flood_of_forged_frames_never_pushes_out_a_genuine_one() {
        use moonhaul_coord::message::{Body, Envelope, OperatorCommand, PROTOCOL_VERSION};
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let rogue = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let team = Keys::new("moonhaul");
        let port = free_loopback_port().unwrap();
        let listener = session(&keys, Role::Unit(0), &[], &[endpoint(port)]).await;
        let q: Arc<FrameQueue> = queue(8);
        let admission = moonhaul_coord::Validator::monitor(&keys).admission(Sender::Unit(1));
        let key = team.unit_state(1);
        let _sub = subscribe(&listener, key.clone(), &q, Some(admission))
            .await
            .unwrap();
        let flooder = session(&keys, Role::Unit(1), &[endpoint(port)], &[]).await;
        assert!(connected(&flooder, Duration::from_secs(10)).await);
        tokio::time::sleep(Duration::from_millis(300)).await;
        let envelope = |sender, seq| Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender,
            seq,
            stamp_us: seq,
            body: Body::Operator(OperatorCommand::Start { mission: 1 }),
        };
        let genuine = keys.sealer(Sender::Unit(1)).unwrap();
        let forged = rogue.sealer(Sender::Unit(1)).unwrap();
        let impostor = keys.sealer(Sender::Operator).unwrap();
        let put = |bytes: Vec<u8>| {
            flooder
                .put(key.as_str(), bytes)
                .congestion_control(CongestionControl::Block)
        };
        let (rounds, per_round) = (20u64, 100u64);
        let mut heard = Vec::new();
        for round in 0..rounds {
            // The genuine frame first: a drop-oldest queue flooded after it would lose it.
            let seq = round * 1000 + 999;
            put(genuine.seal(&envelope(Sender::Unit(1), seq)).unwrap())
                .await
                .unwrap();
            for k in 0..per_round {
                let seq = round * 1000 + k;
                let bytes = match k % 3 {
                    0 => forged.seal(&envelope(Sender::Unit(1), seq)).unwrap(),
                    1 => impostor.seal(&envelope(Sender::Operator, seq)).unwrap(),
                    _ => vec![0xa5; 200],
                };
                put(bytes).await.unwrap();
            }
            // The tick drains its queue every 20 ms.
            let deadline = Instant::now() + Duration::from_secs(5);
            while heard.len() as u64 <= round && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
                q.drain(|s| heard.push(s.payload().to_bytes().into_owned()));
            }
        }
        let refused = q.refused();
        assert_eq!(heard.len() as u64, rounds, "{:?} {refused:?}", q.counts());
        assert_eq!(q.counts().dropped, 0);
        assert_eq!(
            refused.bad_mac + refused.unknown_sender + refused.malformed,
            rounds * per_round,
            "{refused:?}"
        );
        assert!(refused.bad_mac > 0 && refused.unknown_sender > 0 && refused.malformed > 0);
        for s in [flooder, listener] {
            s.close().await.unwrap();
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_transport_drops_frames_over_the_cap_and_keeps_the_link() {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let team = Keys::new("moonhaul");
        let port = free_loopback_port().unwrap();
        let listener = session(&keys, Role::Unit(0), &[], &[endpoint(port)]).await;
        let q: Arc<FrameQueue> = queue(64);
        let _sub = subscribe(&listener, team.operator(), &q, None)
            .await
            .unwrap();
        let operator = session(&keys, Role::Operator, &[endpoint(port)], &[]).await;
        assert!(connected(&operator, Duration::from_secs(10)).await);
        tokio::time::sleep(Duration::from_millis(300)).await;
        let key = team.operator();
        // Just over the cap but in one batch: the queue refuses it uncopied; far over: the
        // transport's reassembly drops it. Then a legitimate frame still arrives (sent until
        // it does: the link is the one that carried the large ones).
        for len in [MAX_FRAME_BYTES + 1, 1 << 20, 64 << 20] {
            operator
                .put(key.as_str(), vec![0u8; len])
                .congestion_control(CongestionControl::Block)
                .await
                .unwrap();
        }
        let deadline = Instant::now() + Duration::from_secs(20);
        while q.counts().received == 0 && Instant::now() < deadline {
            operator
                .put(key.as_str(), vec![0u8; MAX_FRAME_BYTES])
                .congestion_control(CongestionControl::Block)
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let mut lens = Vec::new();
        q.drain(|s| lens.push(s.payload().len()));
        assert!(!lens.is_empty(), "{:?}", q.counts());
        assert!(lens.iter().all(|&l| l == MAX_FRAME_BYTES), "{lens:?}");
        assert_eq!(q.counts().oversize, 1);
        operator.close().await.unwrap();
        listener.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_outbox_never_waits_and_keeps_the_newest() {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let team = Keys::new("moonhaul");
        let port = free_loopback_port().unwrap();
        let listener = session(&keys, Role::Unit(1), &[], &[endpoint(port)]).await;
        let q: Arc<FrameQueue> = queue(1 << 14);
        let _sub = subscribe(&listener, team.unit_state(0), &q, None)
            .await
            .unwrap();
        let unit = session(&keys, Role::Unit(0), &[endpoint(port)], &[]).await;
        assert!(connected(&unit, Duration::from_secs(10)).await);
        // Its own state never comes back to it.
        let own: Arc<FrameQueue> = queue(16);
        let _own_sub = subscribe(&unit, team.unit_state(0), &own, None)
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let outbox = Outbox::spawn(control_publisher(&unit, team.unit_state(0)).await.unwrap());
        let n = 10_000u32;
        for i in 0..n {
            outbox.send(&i.to_le_bytes());
        }
        let c = outbox.counts();
        assert!(c.sent + c.superseded + c.failed <= u64::from(n));
        // The burst overruns zenoh's own queue, and a congested `Drop` publisher loses frames
        // on the wire whatever the outbox does (CI saw the burst's frame 2571 arrive last).
        // What the daemon relies on is the next tick's frame getting through once the burst
        // is over, and no older frame arriving after it: the newest is sent once per tick,
        // as the daemon does, until it arrives.
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut last = Vec::new();
        while Instant::now() < deadline && last != b"last" {
            outbox.send(b"last");
            tokio::time::sleep(Duration::from_millis(20)).await;
            q.drain(|s| last = s.payload().to_bytes().into_owned());
        }
        assert_eq!(last, b"last", "the newest frame went out");
        outbox.close(Duration::from_secs(5)).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
        q.drain(|s| {
            assert_eq!(
                &*s.payload().to_bytes(),
                b"last",
                "an older frame came after the newest"
            )
        });
        own.drain(|s| panic!("own frame delivered to itself: {}", s.key_expr()));
        unit.close().await.unwrap();
        listener.close().await.unwrap();
    }
}

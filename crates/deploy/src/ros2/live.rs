//! A unit's ROS 2 topics, live, in rmw_zenoh's wire format (its `docs/design.md`), on a zenoh
//! session of their own: the team's authenticated session and its access control never see
//! ROS 2 traffic, and this session declares no subscriber and no queryable, so nothing from
//! the ROS 2 graph reaches the unit.
//!
//! - **Key expressions**: `<domain>/<topic without its leading slash>/<DDS type>/<RIHS01 hash>`,
//!   e.g. `0/unit_0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13ee3…`.
//! - **Payloads**: CDR with its 4-byte encapsulation header.
//! - **Attachment** of every sample: the publisher's sequence number (int64 LE, from 1), the
//!   source timestamp (int64 LE, ns since the Unix epoch), the GID's length (one byte, 16) and
//!   the 16-byte publisher GID.
//! - **Liveliness tokens** for the graph (`ros2 topic list`, `ros2 node list`): node
//!   `@ros2_lv/<domain>/<zid>/0/0/NN/%/%<ns>/moonhaul_unit`, and one per publisher,
//!   `@ros2_lv/<domain>/<zid>/0/<id>/MP/%/%<ns>/moonhaul_unit/<mangled topic>/<DDS type>/<hash>/<qos>`
//!   (mangled: `/` → `%`; QoS in rmw_zenoh's compact form, defaults left empty).
//!
//! The GID is the first 16 bytes of the SHA-256 of the publisher's liveliness key expression:
//! unique per publisher and stable across restarts (rmw_zenoh hashes the same key expression
//! with XXH3; a subscriber only compares GIDs it received).
//!
//! # Never in the tick's way
//!
//! The tick hands its record over with [`Ros2Publisher::offer`]: a copy into a one-record slot
//! (reusing the slot's buffers), taken with `try_lock` — a slot still held by the publishing
//! task, or a record not yet taken when the next arrives, is dropped and counted, never waited
//! for. The task builds, encodes and puts the messages (zenoh's congestion control drops rather
//! than blocks). `/tf_static` and `robot_description` are transient local in ROS 2; this session
//! keeps no publication cache for late subscribers, so it sends both again every
//! [`LATCHED_REPEAT`] instead.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::Serialize;
use sha2::{Digest, Sha256};
use tokio::sync::Notify;
use tracing::warn;
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::msgs::{encode_cdr, Time};
use super::topics::{Durability, Qos, Topic, UnitTopics};
use crate::record::TickRecord;

/// The node every unit's topics belong to.
pub const NODE_NAME: &str = "moonhaul_unit";
/// How often the transient-local topics are sent again for subscribers that joined late.
pub const LATCHED_REPEAT: Duration = Duration::from_secs(1);

/// Where and how a unit publishes (`[ros2]` of the unit config, `--ros2-connect`).
#[derive(Debug, Clone, PartialEq)]
pub struct LiveSettings {
    /// `ROS_DOMAIN_ID`.
    pub domain_id: u32,
    /// The unit's namespace (e.g. `unit_0`).
    pub namespace: String,
    /// Zenoh endpoints to connect to: rmw_zenoh's router (`tcp/localhost:7447`) or a peer.
    pub connect: Vec<String>,
}

/// Why the ROS 2 session could not start.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error("ROS 2: {0}")]
    Model(String),
    #[error("ROS 2 zenoh session: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> LiveError {
    LiveError::Zenoh(e.to_string())
}

/// The slot between the tick and the publishing task.
struct Shared {
    slot: Mutex<Slot>,
    ready: Notify,
    /// Records the task never published: replaced before it took them, or offered while it
    /// held the slot.
    dropped: AtomicU64,
    /// Samples zenoh refused to send.
    failed: AtomicU64,
}

struct Slot {
    record: TickRecord,
    fresh: bool,
    closed: bool,
}

/// A unit's live ROS 2 publishing: the session, its tokens and the task that publishes.
pub struct Ros2Publisher {
    shared: Arc<Shared>,
    task: tokio::task::JoinHandle<()>,
    session: zenoh::Session,
}

impl Ros2Publisher {
    /// Opens the ROS 2 session on `settings`, declares the node, the publishers and their
    /// liveliness tokens for the unit of `urdf`, and starts the publishing task.
    pub async fn start(
        settings: &LiveSettings,
        urdf: &str,
        team_size: usize,
    ) -> Result<Self, LiveError> {
        let topics = UnitTopics::new(urdf, &settings.namespace).map_err(LiveError::Model)?;
        let mut config = zenoh::Config::default();
        let set = |c: &mut zenoh::Config, key: &str, value: String| {
            c.insert_json5(key, &value)
                .map_err(|e| LiveError::Zenoh(format!("config {key}: {e}")))
        };
        // rmw_zenoh's session defaults: a peer dialling the router, no multicast scouting.
        set(&mut config, "mode", "\"peer\"".into())?;
        set(&mut config, "scouting/multicast/enabled", "false".into())?;
        set(
            &mut config,
            "connect/endpoints",
            serde_json::to_string(&settings.connect).map_err(zerr)?,
        )?;
        set(&mut config, "listen/endpoints", "[]".into())?;
        // A router that is not up yet is retried in the background; the unit does not wait.
        set(&mut config, "connect/timeout_ms", "-1".into())?;
        set(&mut config, "connect/exit_on_failure", "false".into())?;
        let session = zenoh::open(config).await.map_err(zerr)?;
        let zid = session.zid().to_string();
        let domain = settings.domain_id;
        let ns = &settings.namespace;
        let mut tokens = vec![session
            .liveliness()
            .declare_token(format!(
                "@ros2_lv/{domain}/{zid}/0/0/NN/%/%{ns}/{NODE_NAME}"
            ))
            .await
            .map_err(zerr)?];
        let mut declare = Declare {
            session: &session,
            domain,
            zid: &zid,
            namespace: ns,
            tokens: &mut tokens,
            next_id: 10,
        };
        let outlets = Outlets {
            joint_states: declare.outlet(&topics.joint_states).await?,
            tf: declare.outlet(&topics.tf).await?,
            tf_static: declare.outlet(&topics.tf_static).await?,
            robot_description: declare.outlet(&topics.robot_description).await?,
            diagnostics: declare.outlet(&topics.diagnostics).await?,
        };
        let shared = Arc::new(Shared {
            slot: Mutex::new(Slot {
                record: TickRecord::for_team(team_size),
                fresh: false,
                closed: false,
            }),
            ready: Notify::new(),
            dropped: AtomicU64::new(0),
            failed: AtomicU64::new(0),
        });
        let task = tokio::spawn(publish(topics, outlets, tokens, shared.clone(), team_size));
        Ok(Ros2Publisher {
            shared,
            task,
            session,
        })
    }

    /// Hands tick record `r` to the publishing task without waiting (see the module docs).
    pub fn offer(&self, r: &TickRecord) {
        match self.shared.slot.try_lock() {
            Ok(mut slot) => {
                if slot.fresh {
                    self.shared.dropped.fetch_add(1, Ordering::Relaxed);
                }
                slot.record.copy_from(r);
                slot.fresh = true;
                drop(slot);
                self.shared.ready.notify_one();
            }
            Err(_) => {
                self.shared.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Records offered but never published, and samples zenoh refused.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.shared.dropped.load(Ordering::Relaxed),
            self.shared.failed.load(Ordering::Relaxed),
        )
    }

    /// Stops the task (its tokens go with it) and closes the session.
    pub async fn close(self) {
        if let Ok(mut slot) = self.shared.slot.lock() {
            slot.closed = true;
        }
        self.shared.ready.notify_one();
        let _ = self.task.await;
        let _ = self.session.close().await;
    }
}

/// rmw_zenoh's compact QoS in a liveliness token (`qos_to_keyexpr`): reliability, durability,
/// `history,depth`, `deadline s,ns`, `lifespan s,ns`, `liveliness,lease s,lease ns`, each left
/// empty where it is rmw_zenoh's default (reliable, volatile, keep-last, depth 42, infinite
/// times, automatic). Transient local is 1 (rmw's enum).
pub fn qos_keyexpr(qos: &Qos) -> String {
    let durability = match qos.durability {
        Durability::Volatile => "",
        Durability::TransientLocal => "1",
    };
    let depth = if qos.depth == 42 {
        String::new()
    } else {
        qos.depth.to_string()
    };
    format!(":{durability}:,{depth}:,:,:,,")
}

/// rmw_zenoh's attachment of one sample.
pub fn attachment(sequence: i64, source_ns: i64, gid: &[u8; 16]) -> [u8; 33] {
    let mut out = [0u8; 33];
    out[..8].copy_from_slice(&sequence.to_le_bytes());
    out[8..16].copy_from_slice(&source_ns.to_le_bytes());
    out[16] = 16;
    out[17..].copy_from_slice(gid);
    out
}

/// One publisher: its zenoh publisher, GID and sequence.
struct Outlet {
    publisher: Publisher<'static>,
    gid: [u8; 16],
    sequence: i64,
}

/// Declares a unit's publishers one by one, each with its liveliness token.
struct Declare<'a> {
    session: &'a zenoh::Session,
    domain: u32,
    zid: &'a str,
    namespace: &'a str,
    tokens: &'a mut Vec<LivelinessToken>,
    /// The next entity id within the node (rmw_zenoh numbers them within a context).
    next_id: u32,
}

impl Declare<'_> {
    async fn outlet(&mut self, topic: &Topic) -> Result<Outlet, LiveError> {
        let (domain, zid, ns) = (self.domain, self.zid, self.namespace);
        let (dds, hash) = (topic.ros_type.dds_name(), topic.ros_type.hash);
        let token = format!(
            "@ros2_lv/{domain}/{zid}/0/{}/MP/%/%{ns}/{NODE_NAME}/{}/{dds}/{hash}/{}",
            self.next_id,
            topic.name.replace('/', "%"),
            qos_keyexpr(&topic.qos),
        );
        self.next_id += 1;
        let mut gid = [0u8; 16];
        gid.copy_from_slice(&Sha256::digest(token.as_bytes())[..16]);
        self.tokens.push(
            self.session
                .liveliness()
                .declare_token(token)
                .await
                .map_err(zerr)?,
        );
        let key = format!(
            "{domain}/{}/{dds}/{hash}",
            topic.name.trim_start_matches('/')
        );
        let publisher = self
            .session
            .declare_publisher(key)
            .congestion_control(CongestionControl::Drop)
            .await
            .map_err(zerr)?;
        Ok(Outlet {
            publisher,
            gid,
            sequence: 0,
        })
    }
}

impl Outlet {
    fn put<T: Serialize>(&mut self, message: &T, buf: &mut Vec<u8>, failed: &AtomicU64) {
        if let Err(e) = encode_cdr(message, buf) {
            warn!(error = %e, "ROS 2 message not encoded");
            failed.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.sequence += 1;
        let now_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        let attachment = attachment(self.sequence, now_ns, &self.gid);
        let put = self
            .publisher
            .put(ZBytes::from(buf.clone()))
            .attachment(ZBytes::from(attachment.to_vec()))
            .wait();
        if put.is_err() {
            failed.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// One outlet per topic of [`UnitTopics`].
struct Outlets {
    joint_states: Outlet,
    tf: Outlet,
    tf_static: Outlet,
    robot_description: Outlet,
    diagnostics: Outlet,
}

/// The publishing task: one record at a time, as the tick offers them; the latched topics at
/// start and every [`LATCHED_REPEAT`].
async fn publish(
    topics: UnitTopics,
    mut out: Outlets,
    _tokens: Vec<LivelinessToken>,
    shared: Arc<Shared>,
    team_size: usize,
) {
    let mut record = TickRecord::for_team(team_size);
    let mut buf = Vec::with_capacity(4096);
    let failed = &shared.failed;
    let mut latched_due = tokio::time::Instant::now();
    let mut stamp = Time::default();
    loop {
        if tokio::time::Instant::now() >= latched_due {
            let tf_static = super::msgs::TfMessage {
                transforms: topics.tf_static(stamp),
            };
            out.tf_static.put(&tf_static, &mut buf, failed);
            out.robot_description
                .put(&topics.robot_description(), &mut buf, failed);
            latched_due += LATCHED_REPEAT;
        }
        tokio::select! {
            () = shared.ready.notified() => {}
            () = tokio::time::sleep_until(latched_due) => continue,
        }
        {
            let Ok(mut slot) = shared.slot.lock() else {
                return;
            };
            if slot.closed {
                return;
            }
            if !slot.fresh {
                continue;
            }
            std::mem::swap(&mut slot.record, &mut record);
            slot.fresh = false;
        }
        let Some(now) = Time::from_us(record.stamp_us) else {
            failed.fetch_add(1, Ordering::Relaxed);
            continue;
        };
        stamp = now;
        out.joint_states
            .put(&topics.joint_state(&record, stamp), &mut buf, failed);
        out.tf.put(&topics.tf(&record, stamp), &mut buf, failed);
        out.diagnostics
            .put(&topics.diagnostics(&record, stamp), &mut buf, failed);
    }
}

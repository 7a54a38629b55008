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
//! The GID is rmw_zenoh's: the XXH3-128 of the publisher's liveliness key expression ([`gid`]),
//! unique per publisher and stable across restarts of a session with the same id.
//!
//! # Never in the tick's way
//!
//! The pattern is ros2_control's `realtime_tools::RealtimePublisher`: the control thread only
//! `try_lock`s and copies; a thread of its own, which the control thread never wakes, does the
//! publishing.
//!
//! - **The hand-over** ([`Ros2Publisher::offer`]) is a `try_lock` and a copy of the tick record
//!   into a queue of [`QUEUE_RECORDS`] records allocated at start (reusing their buffers): no
//!   allocation, no system call, no wake-up. A queue that is full, or held at that instant by
//!   the publishing thread, drops the record and counts it ([`Ros2Publisher::counts`]); the
//!   tick never waits.
//! - **The publishing thread** (`ros2-publish`, a plain OS thread, not a task on the daemon's
//!   tokio workers, which also drive the tick's timer and the team's transport) wakes on its
//!   own every [`PUBLISH_PERIOD`], swaps the queue for a spare one and builds, CDR-encodes and
//!   puts every record taken: one `joint_states`, `/tf` and `/diagnostics` sample per tick,
//!   none skipped, at most one period late. It runs at Linux's lowest priority,
//!   `SCHED_IDLE` (nice 19 where that is refused), so on a busy core the tick, the team's
//!   transport and anything else preempt it, never the other way round.
//! - **zenoh** sends with congestion control `Drop` (never blocks the thread). Its runtimes are
//!   process-wide (shared with the team's session, sized by `ZENOH_RUNTIME`, not per session),
//!   so the transmission that follows a put runs at normal priority; it is woken by the
//!   publishing thread on its own period, never by the tick.
//!
//! Measured (`cargo bench -p moonhaul-deploy --bench onboard -- --ros2-ticks 3000`, 2 loaded
//! cores, `docs/measurements/2026-12-04-ros2-tick.md`): a hand-over that woke the publishing
//! task at every tick (a tokio `Notify`) cost 57–125 µs at p50 and 0.24–3.2 ms at p99, the
//! woken worker preempting the tick; waking even a `SCHED_IDLE` thread at every tick (a futex
//! wake in a VM) still cost 120 µs at p99; the queue the thread polls costs 2–3 µs at p50 and
//! 4–6 µs at p99, and the tick's p99 with publishing on was 0.94–0.95 of that with it off.
//!
//! `/tf_static` and `robot_description` are transient local in ROS 2; this session keeps no
//! publication cache for late subscribers, so the thread sends both again every
//! [`LATCHED_REPEAT`] instead.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;
use tracing::{info, warn};
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
/// How often the publishing thread takes the records queued since its last turn and sends
/// them: the most a live sample waits (plus the thread's wait for a core).
pub const PUBLISH_PERIOD: Duration = Duration::from_millis(10);
/// Records the queue holds between two turns of the publishing thread: 0.64 s of ticks at
/// 50 Hz, so a publishing thread kept off the cores that long by other work loses none.
pub const QUEUE_RECORDS: usize = 32;

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

/// What the tick and the publishing thread share.
struct Shared {
    queue: Mutex<Queue>,
    /// Records the thread never published: offered while the queue was full, or while the
    /// thread held it for the instant it takes to swap it out.
    dropped: AtomicU64,
    /// Samples zenoh refused to send, or records without a valid stamp.
    failed: AtomicU64,
}

/// The records offered since the thread's last turn: `records[..len]`, the rest spare
/// buffers, all allocated at start so that an offer only copies.
struct Queue {
    records: Vec<TickRecord>,
    len: usize,
    closed: bool,
}

impl Shared {
    fn new(team_size: usize) -> Self {
        Shared {
            queue: Mutex::new(Queue::new(team_size)),
            dropped: AtomicU64::new(0),
            failed: AtomicU64::new(0),
        }
    }

    /// The tick's side: a copy into the next free record, or a drop, counted.
    fn offer(&self, r: &TickRecord) {
        let Ok(mut queue) = self.queue.try_lock() else {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        };
        let Queue { records, len, .. } = &mut *queue;
        match records.get_mut(*len) {
            Some(slot) => {
                copy_published(slot, r);
                *len += 1;
            }
            None => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// The thread's side: swaps the queue's records for `spare`'s (whose own are all free)
    /// and empties it; `spare` then holds the records offered, `spare.len` of them. Whether
    /// the publisher was closed; `None` on a poisoned lock.
    fn take(&self, spare: &mut Queue) -> Option<bool> {
        let mut queue = self.queue.lock().ok()?;
        std::mem::swap(&mut queue.records, &mut spare.records);
        spare.len = std::mem::take(&mut queue.len);
        Some(queue.closed)
    }
}

/// Copies into `dst` the fields of `src` the live topics are built from (see
/// [`UnitTopics::joint_state`], [`UnitTopics::tf`], [`UnitTopics::diagnostics`]), and no
/// more: the whole record is over 1 KB, cold in the cache at every tick, and copying all
/// of it made the hand-over several times dearer. Every field is named, so a new one is not
/// forgotten; the ones left out are marked `_`.
fn copy_published(dst: &mut TickRecord, src: &TickRecord) {
    let TickRecord {
        unit,
        tick,
        stamp_us,
        phase,
        hold,
        t_max,
        distance: _,
        tracking_d: _,
        sensed,
        payload_height_estimate_m: _,
        press_m: _,
        goal_distance_m: _,
        team_sensed: _,
        team_previous: _,
        grasp_force_n: _,
        grasp_open: _,
        target: _,
        issued: _,
        peer_age_us,
        fault,
        rejected: _,
        deadline_misses,
        work_us: _,
    } = src;
    dst.unit = *unit;
    dst.tick = *tick;
    dst.stamp_us = *stamp_us;
    dst.phase = *phase;
    dst.hold = *hold;
    dst.t_max = *t_max;
    dst.sensed = *sensed;
    dst.peer_age_us.clone_from(peer_age_us);
    dst.fault.clone_from(fault);
    dst.deadline_misses = *deadline_misses;
}

impl Queue {
    fn new(team_size: usize) -> Self {
        Queue {
            records: (0..QUEUE_RECORDS)
                .map(|_| TickRecord::for_team(team_size))
                .collect(),
            len: 0,
            closed: false,
        }
    }
}

/// A unit's live ROS 2 publishing: the session, its tokens and the thread that publishes.
pub struct Ros2Publisher {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    session: zenoh::Session,
}

impl Ros2Publisher {
    /// Opens the ROS 2 session on `settings`, declares the node, the publishers and their
    /// liveliness tokens for the unit of `urdf`, and starts the publishing thread.
    pub async fn start(
        settings: &LiveSettings,
        urdf: &str,
        team_size: usize,
    ) -> Result<Self, LiveError> {
        let topics = UnitTopics::new(urdf, &settings.namespace).map_err(LiveError::Model)?;
        // rmw_zenoh's session defaults: a peer dialling the router, no multicast scouting; a
        // router that is not up yet is retried in the background, the unit does not wait.
        let config =
            crate::network::peer_config(&settings.connect, &[]).map_err(LiveError::Zenoh)?;
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
        let shared = Arc::new(Shared::new(team_size));
        let thread = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("ros2-publish".into())
                .spawn(move || {
                    let priority = lowest_priority();
                    info!(priority, "ROS 2 publishing thread up");
                    publish(&topics, outlets, tokens, &shared, team_size);
                })
                .map_err(|e| LiveError::Zenoh(format!("publishing thread: {e}")))?
        };
        Ok(Ros2Publisher {
            shared,
            thread: Some(thread),
            session,
        })
    }

    /// Hands tick record `r` to the publishing thread without waiting, allocating or waking
    /// anything (see the module docs).
    pub fn offer(&self, r: &TickRecord) {
        self.shared.offer(r);
    }

    /// Records offered but never published, and samples zenoh refused.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.shared.dropped.load(Ordering::Relaxed),
            self.shared.failed.load(Ordering::Relaxed),
        )
    }

    /// Tells the thread to stop: it publishes what is queued, drops its tokens and ends.
    fn stop(&self) {
        if let Ok(mut queue) = self.shared.queue.lock() {
            queue.closed = true;
        }
        if let Some(thread) = &self.thread {
            thread.thread().unpark();
        }
    }

    /// Stops the thread (its tokens go with it) and closes the session.
    pub async fn close(mut self) {
        self.stop();
        if let Some(thread) = self.thread.take() {
            let _ = tokio::task::spawn_blocking(move || thread.join()).await;
        }
        let _ = self.session.clone().close().await;
    }
}

impl Drop for Ros2Publisher {
    /// A publisher dropped without [`Ros2Publisher::close`] still stops its thread.
    fn drop(&mut self) {
        self.stop();
    }
}

/// Puts the calling thread at the lowest priority the kernel offers: Linux's `SCHED_IDLE`
/// (runs only on a core nothing else wants), else nice 19; with `SCHED_RESET_ON_FORK`, so a
/// thread it starts (a runtime zenoh creates lazily) does not inherit it. Names what it got.
#[cfg(target_os = "linux")]
fn lowest_priority() -> &'static str {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: pid 0 is the calling thread; `param` is a valid sched_param for SCHED_IDLE.
    let idle = unsafe {
        libc::sched_setscheduler(0, libc::SCHED_IDLE | libc::SCHED_RESET_ON_FORK, &param)
    };
    if idle == 0 {
        return "SCHED_IDLE";
    }
    // SAFETY: gettid has no preconditions; setpriority on a thread id renices that thread.
    let niced = unsafe {
        let tid = libc::gettid();
        libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 19)
    };
    if niced == 0 {
        "nice 19"
    } else {
        "unchanged (neither SCHED_IDLE nor nice 19 allowed)"
    }
}

#[cfg(not(target_os = "linux"))]
fn lowest_priority() -> &'static str {
    "unchanged (not Linux)"
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

/// rmw_zenoh's GID of the entity with liveliness key expression `token`: its XXH3-128 (seed 0),
/// the low 64 bits then the high 64, each little-endian (`liveliness_utils.cpp`, which
/// `memcpy`s `low64` then `high64` on a little-endian host).
pub fn gid(token: &str) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(token.as_bytes()).to_le_bytes()
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
        let gid = gid(&token);
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

/// The publishing thread: every [`PUBLISH_PERIOD`] it swaps the queue for its own spare one
/// (the only moment it holds the lock) and publishes each record taken, in order; the latched
/// topics at start and every [`LATCHED_REPEAT`]. On close it publishes what was queued and
/// ends, dropping the liveliness tokens.
fn publish(
    topics: &UnitTopics,
    mut out: Outlets,
    _tokens: Vec<LivelinessToken>,
    shared: &Shared,
    team_size: usize,
) {
    let mut taken = Queue::new(team_size);
    let mut buf = Vec::with_capacity(4096);
    let failed = &shared.failed;
    let mut latched_due = Instant::now();
    let mut stamp = Time::default();
    loop {
        let Some(closed) = shared.take(&mut taken) else {
            return;
        };
        for record in &taken.records[..taken.len] {
            let Some(now) = Time::from_us(record.stamp_us) else {
                failed.fetch_add(1, Ordering::Relaxed);
                continue;
            };
            stamp = now;
            out.joint_states
                .put(&topics.joint_state(record, stamp), &mut buf, failed);
            out.tf.put(&topics.tf(record, stamp), &mut buf, failed);
            out.diagnostics
                .put(&topics.diagnostics(record, stamp), &mut buf, failed);
        }
        if closed {
            return;
        }
        if Instant::now() >= latched_due {
            let tf_static = super::msgs::TfMessage {
                transforms: topics.tf_static(stamp),
            };
            out.tf_static.put(&tf_static, &mut buf, failed);
            out.robot_description
                .put(&topics.robot_description(), &mut buf, failed);
            latched_due = Instant::now() + LATCHED_REPEAT;
        }
        std::thread::park_timeout(PUBLISH_PERIOD);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(tick: u64) -> TickRecord {
        let mut r = TickRecord::for_team(2);
        r.tick = tick;
        r.stamp_us = 1_000_000 + tick * 20_000;
        r
    }

    #[test]
    fn offers_queue_in_order_and_what_does_not_fit_is_dropped_and_counted() {
        let shared = Shared::new(2);
        for tick in 1..=QUEUE_RECORDS as u64 + 3 {
            shared.offer(&record(tick));
        }
        assert_eq!(shared.dropped.load(Ordering::Relaxed), 3);
        let mut taken = Queue::new(2);
        assert_eq!(shared.take(&mut taken), Some(false));
        let ticks: Vec<u64> = taken.records[..taken.len].iter().map(|r| r.tick).collect();
        assert_eq!(ticks, (1..=QUEUE_RECORDS as u64).collect::<Vec<_>>());
        // The queue is empty again, with buffers to spare for the next offers.
        shared.offer(&record(99));
        assert_eq!(shared.take(&mut taken), Some(false));
        assert_eq!(taken.len, 1);
        assert_eq!(taken.records[0].tick, 99);
        assert_eq!(shared.dropped.load(Ordering::Relaxed), 3);
    }

    /// XXH3-128 as PyPI's `xxhash` 3.5.0 computes it (`xxh3_128_intdigest(s).to_bytes(16,
    /// "little")`), on each of the hash's length ranges (0–16, 17–128, 129–240, longer) and
    /// on a publisher token of the length a unit's have.
    #[test]
    fn gids_are_xxh3_128_as_the_reference_implementation_computes_it() {
        let token = "@ros2_lv/0/1f2e3d4c5b6a79881f2e3d4c5b6a7988/0/10/MP/%/%unit_0/moonhaul_unit/\
                     %unit_0%joint_states/sensor_msgs::msg::dds_::JointState_/\
                     RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e/\
                     ::,10:,:,:,,";
        assert_eq!(token.len(), 217);
        let hex = |g: [u8; 16]| g.iter().map(|b| format!("{b:02x}")).collect::<String>();
        for (input, expected) in [
            (String::new(), "7f498d4624c30160d8984701d306aa99"),
            ("a".repeat(16), "158d82c4dd505724d030680654509fff"),
            ("ab".repeat(50), "f35ddc919506e67eb8b729284b215bb7"),
            (token.to_owned(), "44e8e1a277f98215c46ff2841a25330e"),
            ("x".repeat(300), "5435c87d60b4d1a57abcd72aea375212"),
        ] {
            assert_eq!(hex(gid(&input)), expected, "length {}", input.len());
        }
    }

    /// What the thread builds from its partial copy is what the full record gives.
    #[test]
    fn the_published_fields_are_all_the_topics_read() {
        let urdf =
            std::fs::read_to_string(moonhaul_core::config::repo_file("assets/unit.urdf")).unwrap();
        let topics = UnitTopics::new(&urdf, "unit_1").unwrap();
        let mut full = record(7);
        full.unit = 1;
        full.phase = moonhaul_core::state::Phase::Transport;
        full.hold = Some(moonhaul_coord::HoldReason::NoAdmissibleStep);
        full.t_max = 0.25;
        full.sensed.arm.position_rad = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6, 0.7];
        full.sensed.arm.velocity_radps = [0.01; 7];
        full.sensed.wheels.position_rad = [1.0, -1.0];
        full.sensed.wheels.velocity_radps = [0.5, 0.4];
        full.sensed.base_pose.x_m = 0.3;
        full.sensed.base_pose.yaw_rad = 0.2;
        full.peer_age_us = vec![Some(40_000), None];
        full.fault = Some("drive: hardware write failed".into());
        full.deadline_misses = 3;
        let mut copy = TickRecord::for_team(2);
        copy_published(&mut copy, &full);
        let stamp = Time::from_us(full.stamp_us).unwrap();
        assert_eq!(
            topics.joint_state(&copy, stamp),
            topics.joint_state(&full, stamp)
        );
        assert_eq!(topics.tf(&copy, stamp), topics.tf(&full, stamp));
        assert_eq!(
            topics.diagnostics(&copy, stamp),
            topics.diagnostics(&full, stamp)
        );
    }

    #[test]
    fn an_offer_while_the_thread_holds_the_queue_is_dropped_not_waited_for() {
        let shared = Shared::new(2);
        let held = shared.queue.lock().unwrap();
        shared.offer(&record(1));
        drop(held);
        assert_eq!(shared.dropped.load(Ordering::Relaxed), 1);
        let mut taken = Queue::new(2);
        shared.take(&mut taken);
        assert_eq!(taken.len, 0);
    }

    /// The publishing thread's scheduling policy, found by its name among the process's
    /// threads.
    #[cfg(target_os = "linux")]
    fn publishing_thread_policy() -> Option<i32> {
        std::fs::read_dir("/proc/self/task").ok()?.find_map(|task| {
            let task = task.ok()?;
            let comm = std::fs::read_to_string(task.path().join("comm")).ok()?;
            (comm.trim() == "ros2-publish").then(|| {
                let tid: libc::pid_t = task.file_name().to_str()?.parse().ok()?;
                // SAFETY: sched_getscheduler only reads the policy of thread `tid`.
                Some(unsafe { libc::sched_getscheduler(tid) })
            })?
        })
    }

    /// Every offered tick reaches a bare zenoh peer as one `joint_states` sample, in order
    /// (the attachment's sequence numbers 1, 2, …), from a thread at `SCHED_IDLE`.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn every_offered_tick_is_published_once_in_order_by_an_idle_priority_thread() {
        let port = crate::network::free_loopback_port().unwrap();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let config = crate::network::peer_config(&[], std::slice::from_ref(&endpoint)).unwrap();
        let ros_side = zenoh::open(config).await.unwrap();
        let joint_states = ros_side
            .declare_subscriber("0/unit_0/joint_states/**")
            .await
            .unwrap();
        let urdf =
            std::fs::read_to_string(moonhaul_core::config::repo_file("assets/unit.urdf")).unwrap();
        let publisher = Ros2Publisher::start(
            &LiveSettings {
                domain_id: 0,
                namespace: "unit_0".into(),
                connect: vec![endpoint],
            },
            &urdf,
            2,
        )
        .await
        .unwrap();
        // Let the sessions connect and the subscription reach the publisher.
        tokio::time::sleep(Duration::from_millis(500)).await;
        #[cfg(target_os = "linux")]
        {
            let policy = publishing_thread_policy().expect("the publishing thread runs");
            assert_eq!(policy & !libc::SCHED_RESET_ON_FORK, libc::SCHED_IDLE);
        }
        // No more than the queue holds: a SCHED_IDLE thread runs only on otherwise idle CPU
        // time, so on a saturated machine (parallel tests, other jobs) it may not drain the
        // queue during the offers, and what is under test is order and once-only delivery,
        // not the drop rule (tested above). Spaced 2 ms apart, the offers still span several
        // of the thread's 10 ms polls.
        const TICKS: u64 = QUEUE_RECORDS as u64;
        for tick in 1..=TICKS {
            publisher.offer(&record(tick));
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        let mut sequences = Vec::new();
        while sequences.len() < TICKS as usize {
            // Generous for the same reason: the bound catches a lost tick, not a slow one.
            let sample = tokio::time::timeout(Duration::from_secs(60), joint_states.recv_async())
                .await
                .expect("every tick's joint_states within 60 s")
                .unwrap();
            let attachment = sample.attachment().unwrap().to_bytes();
            sequences.push(i64::from_le_bytes(attachment[..8].try_into().unwrap()));
        }
        assert_eq!(sequences, (1..=TICKS as i64).collect::<Vec<_>>());
        assert_eq!(publisher.counts(), (0, 0));
        publisher.close().await;
        let _ = ros_side.close().await;
    }
}

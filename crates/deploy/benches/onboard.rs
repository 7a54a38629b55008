//! Figures of the onboard runtime (`cargo bench -p moonhaul-deploy --bench onboard -- [--ticks N]
//! [--pings N] [--trials N]`):
//!
//! - **tick latency**: one unit's work per tick — validate the peer's frame, the tick (gate,
//!   observation, policy, clamp), seal its own frame, mock hardware read and write — on a team
//!   flying its mission; excludes waiting for the period;
//! - **peer round trip** on zenoh loopback: a sealed unit frame to a second session, validated
//!   there and answered with its own sealed frame;
//! - **halt latency**: two units ticking at 50 Hz on the wall clock over zenoh; at a random
//!   moment one dies (stops ticking and publishing); the time from its last message to the
//!   survivor's first held tick, over many trials;
//! - **tick with ROS 2 on and off** (`--ros2-ticks N`): unit 0's tick plus its hand-over to the
//!   live ROS 2 publisher, at 50 Hz on the wall clock, with publishing switched on and off in
//!   alternating blocks of 100 ticks in one run, as the daemon runs it (the tick on the
//!   runtime's `block_on` thread, the publisher on its own thread); the publisher sends to a
//!   zenoh peer on loopback that receives every sample. Besides the tick with the hand-over,
//!   the hand-over alone and how late each tick started after its due time (what a
//!   publisher busy on the runtime's workers, which drive the timer, would show).
//!
//! Percentiles are of the measured samples (nearest rank).

use std::time::{Duration, Instant};

use moonhaul_coord::auth::{KeyFile, Sealer};
use moonhaul_coord::message::{
    Body, Envelope, MessageBounds, OperatorCommand, Sender, PROTOCOL_VERSION,
};
use moonhaul_coord::{HoldReason, TeamSettings, Validator};
use moonhaul_core::config::repo_file;
use moonhaul_core::state::PlanarPose;
use moonhaul_deploy::cli_support::{load_policies, wall_us};
use moonhaul_deploy::daemon::mock_hardware;
use moonhaul_deploy::network::{self, Access, Keys, NetworkSettings, Role};
use moonhaul_deploy::record::TickRecord;
use moonhaul_deploy::tick::{Controller, Onboard, OnboardSettings};
use moonhaul_deploy::unit_config::UnitConfig;
use moonhaul_hal::unit::{MockUnit, UnitHardware, UnitReading};
use rand::Rng;

const PERIOD_US: u64 = 20_000;

fn settings(unit: usize) -> TeamSettings {
    TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: unit,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    }
}

/// One unit: its tick, mock drives, validator and sealer.
struct Unit {
    onboard: Onboard,
    hw: MockUnit,
    validator: Validator,
    sealer: Sealer,
    record: TickRecord,
    frame: Vec<u8>,
}

fn unit(i: usize, keys: &KeyFile, boot_us: u64) -> Unit {
    let start_pose = PlanarPose {
        x_m: 0.0,
        y_m: if i == 0 { -0.8 } else { 0.8 },
        yaw_rad: if i == 0 { 0.0 } else { std::f64::consts::PI },
    };
    let onboard_settings = OnboardSettings::shipped(settings(i), start_pose).unwrap();
    let config = UnitConfig::from_file(&repo_file("configs/unit.toml")).unwrap();
    let mut hw = mock_hardware(
        &config,
        &onboard_settings.spec,
        Duration::from_micros(PERIOD_US),
    )
    .unwrap();
    hw.activate().unwrap();
    let onboard = Onboard::new(
        onboard_settings,
        Controller::Learned(Box::new(
            load_policies(&repo_file("assets/policies")).unwrap(),
        )),
        boot_us,
    )
    .unwrap();
    Unit {
        onboard,
        hw,
        validator: Validator::new(&settings(i), keys, MessageBounds::shipped().unwrap()).unwrap(),
        sealer: keys.sealer(Sender::Unit(i)).unwrap(),
        record: TickRecord::for_team(2),
        frame: Vec::with_capacity(1024),
    }
}

type Sub = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// Two zenoh sessions on a loopback TCP link, each publishing one unit's state and
/// subscribed to the other's.
struct Link {
    sessions: [zenoh::Session; 2],
    publishers: [zenoh::pubsub::Publisher<'static>; 2],
    subscribers: [Sub; 2],
}

impl Link {
    async fn open(keys: &KeyFile) -> Link {
        let port = network::free_loopback_port().unwrap();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let access = |i| Access::new(keys, Role::Unit(i)).unwrap();
        let a = network::open(
            &NetworkSettings {
                connect: vec![],
                listen: vec![endpoint.clone()],
            },
            &access(0),
        )
        .await
        .unwrap();
        let b = network::open(
            &NetworkSettings {
                connect: vec![endpoint],
                listen: vec![],
            },
            &access(1),
        )
        .await
        .unwrap();
        let k = Keys::new("moonhaul");
        let publishers = [
            network::control_publisher(&a, k.unit_state(0))
                .await
                .unwrap(),
            network::control_publisher(&b, k.unit_state(1))
                .await
                .unwrap(),
        ];
        let subscribers = [
            a.declare_subscriber(k.unit_state(1)).await.unwrap(),
            b.declare_subscriber(k.unit_state(0)).await.unwrap(),
        ];
        // Let the sessions connect and the subscriptions propagate.
        tokio::time::sleep(Duration::from_millis(300)).await;
        Link {
            sessions: [a, b],
            publishers,
            subscribers,
        }
    }

    async fn close(self) {
        for s in self.sessions {
            let _ = s.close().await;
        }
    }
}

impl Unit {
    /// One tick on the wall clock on every frame waiting on `sub`, plus a newly stamped
    /// operator start when `start` gives the team's keys.
    fn tick_on(&mut self, sub: &Sub, start: Option<&KeyFile>) {
        let now = wall_us();
        let mut inbox = Vec::new();
        while let Ok(Some(s)) = sub.try_recv() {
            inbox.push(s.payload().to_bytes().into_owned());
        }
        inbox.extend(start.map(|keys| start_frame(keys, now)));
        let refs: Vec<&[u8]> = inbox.iter().map(|v| v.as_slice()).collect();
        self.tick(now, &refs);
    }

    /// One tick on `inbox` frames at `now_us`; the unit's own frame is left in `self.frame`.
    fn tick(&mut self, now_us: u64, inbox: &[&[u8]]) {
        let mut reading = UnitReading::default();
        let read = self.hw.read(&mut reading);
        for frame in inbox {
            if let Ok(e) = self.validator.receive_frame(frame, now_us) {
                self.onboard.receive(&e);
            }
        }
        let out = self.onboard.tick(
            now_us,
            read.is_ok().then_some(&reading),
            self.validator.counts(),
            &mut self.record,
        );
        let output = out.output;
        let _ = self.sealer.seal_into(out.message, &mut self.frame);
        let _ = self.hw.write(&output);
    }
}

fn start_frame(keys: &KeyFile, now_us: u64) -> Vec<u8> {
    keys.sealer(Sender::Operator)
        .unwrap()
        .seal(&Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender: Sender::Operator,
            seq: now_us,
            stamp_us: now_us,
            body: Body::Operator(OperatorCommand::Start { mission: 1 }),
        })
        .unwrap()
}

fn percentiles(label: &str, unit: &str, samples: &mut [f64]) {
    samples.sort_by(f64::total_cmp);
    let at =
        |q: f64| samples[((q * samples.len() as f64).ceil() as usize).clamp(1, samples.len()) - 1];
    println!(
        "{label}: n = {}, p50 {:.1} {unit}, p99 {:.1} {unit}, max {:.1} {unit}",
        samples.len(),
        at(0.5),
        at(0.99),
        samples[samples.len() - 1]
    );
}

/// Tick latency of unit 0 over `ticks` ticks of a mission (both units tick, only unit 0's work
/// is timed).
fn tick_latency(ticks: usize) {
    let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let boot = 1_000_000_000;
    let mut units = [unit(0, &keys, boot), unit(1, &keys, boot)];
    let mut samples = Vec::with_capacity(ticks);
    for k in 0..ticks as u64 {
        let now = boot + (k + 1) * PERIOD_US;
        let frames = [units[0].frame.clone(), units[1].frame.clone()];
        let start = start_frame(&keys, now);
        let mut inbox1: Vec<&[u8]> = vec![&frames[0]];
        let mut inbox0: Vec<&[u8]> = vec![&frames[1]];
        if k == 5 {
            inbox0.push(&start);
            inbox1.push(&start);
        }
        let t0 = Instant::now();
        units[0].tick(now, &inbox0);
        samples.push(t0.elapsed().as_secs_f64() * 1e6);
        units[1].tick(now, &inbox1);
    }
    percentiles(
        "tick latency (unit 0, mock drives, mission flying)",
        "us",
        &mut samples,
    );
}

async fn peer_round_trip(pings: usize) {
    let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let link = Link::open(&keys).await;
    let [pub_a, pub_b] = &link.publishers;
    let [sub_a, sub_b] = &link.subscribers;
    let boot = 1_000_000_000;
    let mut u0 = unit(0, &keys, boot);
    let mut u1 = unit(1, &keys, boot);
    let mut samples = Vec::with_capacity(pings);
    for k in 0..pings as u64 {
        let now = boot + (k + 1) * PERIOD_US;
        u0.tick(now, &[]);
        let t0 = Instant::now();
        network::put(pub_a, &u0.frame).await.unwrap();
        let got = sub_b
            .recv_async()
            .await
            .unwrap()
            .payload()
            .to_bytes()
            .into_owned();
        u1.tick(now, &[&got]);
        network::put(pub_b, &u1.frame).await.unwrap();
        let back = sub_a
            .recv_async()
            .await
            .unwrap()
            .payload()
            .to_bytes()
            .into_owned();
        let _ = u0.validator.receive_frame(&back, now);
        samples.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    percentiles(
        "peer round trip (zenoh TCP loopback, sealed + validated both ways, incl. one tick)",
        "us",
        &mut samples,
    );
    link.close().await;
}

async fn halt_latency(trials: usize) {
    let mut samples = Vec::with_capacity(trials);
    let mut rng = rand::rng();
    for _ in 0..trials {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let Link {
            sessions,
            publishers: [pub0, pub1],
            subscribers: [sub0, sub1],
        } = Link::open(&keys).await;
        let mut u1 = unit(1, &keys, wall_us());
        let boot = wall_us();
        let mut u0 = unit(0, &keys, boot);
        // The operator's start, re-sent (newly stamped) for the first 0.3 s as the console does.
        let start_for = Duration::from_millis(300);
        // Unit 1 ticks on its own schedule, offset by a random part of a period, and dies
        // (stops ticking and publishing) 0.5–1.0 s in.
        let die_after = Duration::from_millis(rng.random_range(500..1000));
        let offset = Duration::from_micros(rng.random_range(0..PERIOD_US));
        let last_sent = std::sync::Arc::new(std::sync::Mutex::new(None::<Instant>));
        let t_start = Instant::now();
        let peer = {
            let last_sent = last_sent.clone();
            let keys = keys.clone();
            tokio::spawn(async move {
                tokio::time::sleep(offset).await;
                let mut interval = tokio::time::interval(Duration::from_micros(PERIOD_US));
                interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                while t_start.elapsed() < die_after {
                    interval.tick().await;
                    u1.tick_on(&sub1, (t_start.elapsed() < start_for).then_some(&keys));
                    network::put(&pub1, &u1.frame).await.unwrap();
                    *last_sent.lock().unwrap() = Some(Instant::now());
                }
            })
        };
        let mut interval = tokio::time::interval(Duration::from_micros(PERIOD_US));
        interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut started = false;
        let latency = loop {
            interval.tick().await;
            u0.tick_on(&sub0, (t_start.elapsed() < start_for).then_some(&keys));
            network::put(&pub0, &u0.frame).await.unwrap();
            let held = matches!(u0.record.hold, Some(HoldReason::SafetyStop(_)));
            started |= !held && u0.record.phase != moonhaul_core::state::Phase::Idle;
            if started && held && peer.is_finished() {
                let last = last_sent.lock().unwrap().expect("the peer ran");
                break last.elapsed();
            }
            assert!(t_start.elapsed() < Duration::from_secs(10), "never halted");
        };
        samples.push(latency.as_secs_f64() * 1e3);
        for s in sessions {
            let _ = s.close().await;
        }
    }
    percentiles(
        "halt latency (peer's last message → survivor's first held tick, 50 Hz, bound 3 periods = 60 ms + one tick)",
        "ms",
        &mut samples,
    );
}

/// The arrival check's cost per frame on a flood of forged frames (sealed with another key
/// file, so the HMAC is computed and fails), and what a 10,000 frames/s flood costs the
/// receiving thread: the share of one core.
fn admission_cost(frames: usize) {
    let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let rogue = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let admission = moonhaul_coord::Validator::monitor(&keys).admission(Sender::Unit(1));
    // A real unit-state frame, sealed under the rogue key file.
    let mut sender = unit(1, &rogue, 1_000_000_000);
    sender.tick(1_000_000_000 + PERIOD_US, &[]);
    let forged = sender.frame;
    let mut samples = Vec::with_capacity(frames);
    for _ in 0..frames {
        let t0 = Instant::now();
        let refused = admission.check(std::hint::black_box(&forged)).is_err();
        samples.push(t0.elapsed().as_secs_f64() * 1e6);
        assert!(refused);
    }
    let mean_us = samples.iter().sum::<f64>() / samples.len() as f64;
    percentiles(
        &format!("arrival check of a forged {}-byte unit frame", forged.len()),
        "us",
        &mut samples,
    );
    println!(
        "a 10,000 frames/s flood: {:.1} % of one core on the receiving thread (mean {mean_us:.2} us)",
        mean_us * 1e-6 * 10_000.0 * 100.0
    );
}

/// Unit 0's tick at 50 Hz with its record offered to a live ROS 2 publisher in every other
/// block of 100 ticks (and not in the others), for `ticks` ticks; p50 and p99 of each.
async fn ros2_tick(ticks: usize) {
    use moonhaul_deploy::ros2::live::{LiveSettings, Ros2Publisher};
    const BLOCK: usize = 100;
    let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let port = network::free_loopback_port().unwrap();
    let config = network::peer_config(&[], &[format!("tcp/127.0.0.1:{port}")]).unwrap();
    let ros_side = zenoh::open(config).await.unwrap();
    let received = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let count = received.clone();
    let _sub = ros_side
        .declare_subscriber("0/**")
        .callback(move |_| {
            count.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        })
        .await
        .unwrap();
    let urdf = std::fs::read_to_string(repo_file("assets/unit.urdf")).unwrap();
    let publisher = Ros2Publisher::start(
        &LiveSettings {
            domain_id: 0,
            namespace: "unit_0".into(),
            connect: vec![format!("tcp/127.0.0.1:{port}")],
        },
        &urdf,
        2,
    )
    .await
    .unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let boot = wall_us();
    let mut units = [unit(0, &keys, boot), unit(1, &keys, boot)];
    let (mut on, mut off) = (Vec::new(), Vec::new());
    let (mut on_tick, mut handover) = (Vec::new(), Vec::new());
    let mut interval = tokio::time::interval(Duration::from_micros(PERIOD_US));
    let (mut late_on, mut late_off) = (Vec::new(), Vec::new());
    for k in 0..ticks {
        let due = interval.tick().await;
        let late = due.elapsed().as_secs_f64() * 1e6;
        let now = wall_us();
        let frames = [units[0].frame.clone(), units[1].frame.clone()];
        let start = start_frame(&keys, now);
        let mut inbox0: Vec<&[u8]> = vec![&frames[1]];
        let mut inbox1: Vec<&[u8]> = vec![&frames[0]];
        if k == 5 {
            inbox0.push(&start);
            inbox1.push(&start);
        }
        let publishing = (k / BLOCK) % 2 == 1;
        let t0 = Instant::now();
        units[0].tick(now, &inbox0);
        let t1 = Instant::now();
        if publishing {
            publisher.offer(&units[0].record);
        }
        let us = t0.elapsed().as_secs_f64() * 1e6;
        if publishing {
            on.push(us);
            late_on.push(late);
            on_tick.push((t1 - t0).as_secs_f64() * 1e6);
            handover.push(t1.elapsed().as_secs_f64() * 1e6);
        } else {
            off.push(us);
            late_off.push(late);
        }
        units[1].tick(now, &inbox1);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (dropped, failed) = publisher.counts();
    publisher.close().await;
    let _ = ros_side.close().await;
    println!(
        "ROS 2 publishing, alternating blocks of {BLOCK} ticks at 50 Hz: {} samples received \
         on the ROS side ({} records offered, {dropped} dropped, {failed} samples failed)",
        received.load(std::sync::atomic::Ordering::Relaxed),
        on.len()
    );
    percentiles("tick with ROS 2 off", "us", &mut off);
    percentiles("tick with ROS 2 on (incl. the hand-over)", "us", &mut on);
    percentiles("  of which the tick", "us", &mut on_tick);
    percentiles("  of which the hand-over", "us", &mut handover);
    percentiles(
        "tick's start after its due time, ROS 2 off",
        "us",
        &mut late_off,
    );
    percentiles(
        "tick's start after its due time, ROS 2 on",
        "us",
        &mut late_on,
    );
}

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let ticks = arg("--ticks", 3000);
    let pings = arg("--pings", 1000);
    let trials = arg("--trials", 100);
    tick_latency(ticks);
    admission_cost(arg("--forged", 100_000));
    let rt = moonhaul_deploy::cli_support::runtime().unwrap();
    rt.block_on(async {
        peer_round_trip(pings).await;
        halt_latency(trials).await;
        ros2_tick(arg("--ros2-ticks", 3000)).await;
    });
}

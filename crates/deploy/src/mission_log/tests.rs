use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

use foxglove::schemas::{FrameTransforms, SceneUpdate};
use foxglove::Context;
use moonhaul_coord::message::RejectCounts;

use super::read::{read_json_topic, TopicFilter};
use super::schema::{tick_schema, world_schema};
use super::*;
use crate::record::{TickRecord, WorldFrame};
use moonhaul_coord::HoldReason;
use moonhaul_core::config::repo_file;
use moonhaul_core::stacked::{StackedDistance, Subsystem};
use moonhaul_core::state::{Phase, UnitCommand, UnitState};
use moonhaul_core::unit::UnitSpec;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Instant;

/// The configs the test logs attach beside the unit URDF.
const CONFIGS: [&str; 2] = ["configs/gate.toml", "configs/sync.toml"];

fn inputs() -> LogInputs {
    let configs: Vec<_> = CONFIGS.iter().map(|c| repo_file(c)).collect();
    LogInputs::read(&repo_file("assets/unit.urdf"), &configs).unwrap()
}

fn tick(unit: usize, tick: u64) -> TickRecord {
    let mut sensed = UnitState::default();
    sensed.base_pose.x_m = tick as f64 * 0.01;
    sensed.base_pose.yaw_rad = 0.3 + tick as f64 * 0.01;
    sensed.wheels.position_rad = [0.1 * tick as f64, -0.05 * tick as f64];
    sensed.arm.position_rad = std::array::from_fn(|j| 0.25 - 0.07 * j as f64 + 1e-3 * tick as f64);
    let mut issued = UnitCommand::default();
    issued.arm_position_rad[1] = -0.5 + tick as f64 * 1e-3;
    TickRecord {
        unit,
        tick,
        stamp_us: tick * 20_000,
        phase: if tick < 10 { Phase::Idle } else { Phase::Lift },
        hold: (tick % 3 == 0).then_some(HoldReason::NoAdmissibleStep),
        t_max: 0.75,
        distance: Some(StackedDistance {
            value: 0.4,
            binding: Subsystem::Base(1),
        }),
        tracking_d: (tick > 1).then_some(0.1),
        sensed,
        payload_height_estimate_m: (tick > 10).then_some(0.01 * tick as f64),
        press_m: Some(-0.001),
        goal_distance_m: 2.0,
        team_sensed: vec![sensed, UnitState::default()],
        team_previous: vec![issued, UnitCommand::default()],
        grasp_force_n: Some(12.5),
        grasp_open: false,
        target: issued,
        issued,
        peer_age_us: vec![None, Some(20_000)],
        fault: (tick == 7).then(|| "drive 3: following error".into()),
        rejected: RejectCounts {
            stale: tick / 5,
            ..Default::default()
        },
        deadline_misses: 1,
        work_us: 350,
    }
}

fn frame(tick: u64, units: usize) -> WorldFrame {
    let t = tick as f64 * 0.02;
    WorldFrame {
        tick,
        stamp_us: tick * 20_000,
        payload_position_m: [0.1 * t, 0.0, 0.2 + 0.01 * t],
        payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
        payload_height_m: 0.01 * t,
        payload_tilt_deg: 0.5,
        payload_ground_contact: tick == 0,
        base_position_m: (0..units).map(|i| [0.1 * t, i as f64 - 0.5, 0.1]).collect(),
        base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; units],
        wheel_position_rad: (0..units).map(|i| [t, i as f64 - t]).collect(),
        arm_position_rad: (0..units)
            .map(|i| std::array::from_fn(|j| 0.1 * (i + j) as f64 - 0.2 * t))
            .collect(),
        unit_phase: (0..units)
            .map(|i| (i == 0).then_some(Phase::Lift))
            .collect(),
        grasp_closed: vec![true; units],
    }
}

/// Topic → (message encoding, schema name, messages as (log time ns, bytes)) of a finished
/// file, through the mcap crate's strict reader.
type Messages = BTreeMap<String, (String, String, Vec<(u64, Vec<u8>)>)>;

fn messages(path: &Path) -> Messages {
    let bytes = std::fs::read(path).unwrap();
    let mut out = Messages::new();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        let entry = out.entry(message.channel.topic.clone()).or_insert_with(|| {
            (
                message.channel.message_encoding.clone(),
                message
                    .channel
                    .schema
                    .as_ref()
                    .map_or(String::new(), |s| s.name.clone()),
                Vec::new(),
            )
        });
        entry.2.push((message.log_time, message.data.into_owned()));
    }
    out
}

#[test]
fn unit_log_round_trips_with_its_stamps_as_log_time() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit-1.mcap");
    let records: Vec<TickRecord> = (1..=60).map(|k| tick(1, k)).collect();
    let mut log = UnitLog::create(&path, 1, &inputs()).unwrap();
    for r in &records {
        log.write(r).unwrap();
    }
    log.finish().unwrap();
    assert_eq!(read_unit_log(&path).unwrap(), records);

    let bytes = std::fs::read(&path).unwrap();
    assert!(bytes.ends_with(mcap::MAGIC), "finished file has its footer");
    let topics = messages(&path);
    assert_eq!(topics.keys().collect::<Vec<_>>(), [TF_TOPIC, "/unit1/tick"]);
    let (encoding, schema, msgs) = &topics["/unit1/tick"];
    assert_eq!(
        (encoding.as_str(), schema.as_str()),
        ("json", "moonhaul.TickRecord")
    );
    let times: Vec<u64> = msgs.iter().map(|m| m.0).collect();
    let expected: Vec<u64> = records.iter().map(|r| r.stamp_us * 1000).collect();
    assert_eq!(times, expected);
    let (_, schema, tf) = &topics[TF_TOPIC];
    assert_eq!(schema, "foxglove.FrameTransforms");
    assert_eq!(tf.iter().map(|m| m.0).collect::<Vec<_>>(), expected);
}

/// The pose of `frame` by composing `transforms` from `root` down, checking every transform is
/// stamped `stamp`.
fn resolve(transforms: &FrameTransforms, root: &str, frame: &str) -> Isometry3<f64> {
    if frame == root {
        return Isometry3::identity();
    }
    let t = transforms
        .transforms
        .iter()
        .find(|t| t.child_frame_id == frame)
        .unwrap_or_else(|| panic!("no transform to {frame}"));
    let (p, q) = (t.translation.unwrap(), t.rotation.unwrap());
    resolve(transforms, root, &t.parent_frame_id)
        * Isometry3::from_parts(
            Translation3::new(p.x, p.y, p.z),
            UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
        )
}

fn assert_close(a: &Isometry3<f64>, b: &Isometry3<f64>) {
    let d = a.inverse() * b;
    assert!(
        d.translation.vector.norm() < 1e-9 && d.rotation.angle() < 1e-9,
        "{a} != {b}"
    );
}

#[test]
fn unit_log_tf_puts_every_link_where_the_sensed_joints_do() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit-1.mcap");
    let mut log = UnitLog::create(&path, 1, &inputs()).unwrap();
    let records: Vec<TickRecord> = (1..=5).map(|k| tick(1, k)).collect();
    for r in &records {
        log.write(r).unwrap();
    }
    log.finish().unwrap();
    let spec = UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap();
    let tree =
        moonhaul_core::kinematics::KinematicTree::from_file(repo_file("assets/unit.urdf")).unwrap();
    let tf = &messages(&path)[TF_TOPIC].2;
    for (r, (_, data)) in records.iter().zip(tf) {
        let decoded = <FrameTransforms as foxglove::Decode>::decode(&data[..]).unwrap();
        // One transform per URDF joint, and the base's.
        assert_eq!(decoded.transforms.len(), tree.joints().len() + 1);
        for link in tree.links() {
            let frame = format!("unit1/{}", link.name);
            assert!(
                decoded.transforms.iter().any(|t| t.child_frame_id == frame),
                "no {frame}"
            );
        }
        let pose = &r.sensed.base_pose;
        let base = Isometry3::new(
            Vector3::new(pose.x_m, pose.y_m, 0.0),
            Vector3::z() * pose.yaw_rad,
        ) * spec.ground_to_base();
        assert_close(&resolve(&decoded, "world", "unit1/base_link"), &base);
        let ee = base * spec.arm.forward(&r.sensed.arm.position_rad).unwrap();
        assert_close(&resolve(&decoded, "world", "unit1/ee"), &ee);
        let stamp = decoded.transforms[0].timestamp.unwrap();
        assert_eq!(
            u64::from(stamp.sec()) * 1_000_000 + u64::from(stamp.nsec()) / 1000,
            r.stamp_us
        );
    }
}

#[test]
fn logs_attach_the_urdf_and_configs_they_were_recorded_with() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit-0.mcap");
    let mut log = UnitLog::create(&path, 0, &inputs()).unwrap();
    log.write(&tick(0, 1)).unwrap();
    // Readable before the log is finished: a killed writer's log carries them too.
    log.flush().unwrap();
    let early = read_attachments(&path).unwrap();
    log.finish().unwrap();
    let all = read_attachments(&path).unwrap();
    assert_eq!(all.end, LogEnd::Finished);
    assert!(matches!(early.end, LogEnd::Truncated { .. }));
    assert_eq!(early.records, all.records);
    let files: Vec<_> = std::iter::once("assets/unit.urdf")
        .chain(CONFIGS)
        .map(repo_file)
        .collect();
    assert_eq!(all.records.len(), files.len());
    for ((name, data), file) in all.records.iter().zip(&files) {
        assert_eq!(name, &file.display().to_string());
        assert_eq!(data, &std::fs::read(file).unwrap());
    }
    // A config that cannot be read is named before any log is created.
    let missing = dir.path().join("nope.toml");
    let e = LogInputs::read(
        &repo_file("assets/unit.urdf"),
        std::slice::from_ref(&missing),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains(&missing.display().to_string()), "{e}");
}

#[test]
fn a_unit_log_says_what_flew_it_and_attaches_the_policies() {
    let dir = tempfile::tempdir().unwrap();
    let policies: Vec<_> = ["lift", "transport", "place"]
        .map(|p| repo_file(&format!("assets/policies/{p}.safetensors")))
        .to_vec();
    let learned = dir.path().join("unit-1.mcap");
    let inputs_learned = inputs().flown_by("learned", &policies).unwrap();
    let mut log = UnitLog::create(&learned, 1, &inputs_learned).unwrap();
    log.write(&tick(1, 1)).unwrap();
    log.finish().unwrap();
    let metadata = read_unit_log_contents(&learned).unwrap().metadata;
    assert_eq!(metadata["unit"], "1");
    assert_eq!(metadata["controller"], "learned");
    let attached = read_attachments(&learned).unwrap().records;
    for file in &policies {
        let (_, data) = attached
            .iter()
            .find(|(name, _)| name == &file.display().to_string())
            .unwrap_or_else(|| panic!("{} not attached", file.display()));
        assert_eq!(data, &std::fs::read(file).unwrap());
    }
    // A scripted unit attaches no policy; a log of no controller says none.
    let scripted = dir.path().join("unit-0.mcap");
    let inputs_scripted = inputs().flown_by("scripted", &[]).unwrap();
    UnitLog::create(&scripted, 0, &inputs_scripted)
        .unwrap()
        .finish()
        .unwrap();
    assert_eq!(
        read_unit_log_contents(&scripted).unwrap().metadata["controller"],
        "scripted"
    );
    let plain = dir.path().join("unit-2.mcap");
    UnitLog::create(&plain, 2, &inputs())
        .unwrap()
        .finish()
        .unwrap();
    assert!(!read_unit_log_contents(&plain)
        .unwrap()
        .metadata
        .contains_key("controller"));
    // A policy file that cannot be read is named before any log is created.
    let missing = dir.path().join("lift.safetensors");
    let e = inputs()
        .flown_by("learned", std::slice::from_ref(&missing))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains(&missing.display().to_string()), "{e}");
}

#[test]
fn chunks_are_compressed_and_span_at_most_a_second_of_log_time() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("world.mcap");
    // 20 s of log time, written far faster than the wall clock.
    let mut log = WorldLog::create(&path, [0.5, 0.4, 0.3], 2, &inputs()).unwrap();
    for k in 0..1000 {
        log.write(&frame(k, 2)).unwrap();
    }
    log.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    assert!(
        summary.chunk_indexes.len() >= 20,
        "{}",
        summary.chunk_indexes.len()
    );
    let (mut compressed, mut uncompressed) = (0, 0);
    for chunk in &summary.chunk_indexes {
        assert_eq!(chunk.compression, "zstd");
        assert!(
            chunk.message_end_time - chunk.message_start_time < 1_000_000_000,
            "{chunk:?}"
        );
        compressed += chunk.compressed_size;
        uncompressed += chunk.uncompressed_size;
    }
    assert!(
        compressed * 4 < uncompressed,
        "{compressed} of {uncompressed} bytes"
    );
    assert_eq!(read_world_log(&path).unwrap().len(), 1000);
}

#[test]
fn schemas_name_every_field() {
    let keys = |v: serde_json::Value| -> BTreeSet<String> {
        v.as_object().unwrap().keys().cloned().collect()
    };
    let properties = |schema: serde_json::Value| keys(schema["properties"].clone());
    let record = serde_json::to_value(tick(0, 3)).unwrap();
    assert_eq!(properties(tick_schema()), keys(record.clone()));
    assert_eq!(
        keys(tick_schema()["properties"]["rejected"]["properties"].clone()),
        keys(record["rejected"].clone())
    );
    assert_eq!(
        properties(world_schema()),
        keys(serde_json::to_value(frame(3, 2)).unwrap())
    );
}

#[test]
fn truncated_log_gives_its_complete_prefix() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit-0.mcap");
    let records: Vec<TickRecord> = (1..=120).map(|k| tick(0, k)).collect();
    let mut log = UnitLog::create(&path, 0, &inputs()).unwrap();
    for chunk in records.chunks(10) {
        for r in chunk {
            log.write(r).unwrap();
        }
        log.flush().unwrap();
    }
    log.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let cut_path = dir.path().join("cut.mcap");
    let mut last = 0;
    let mut partial = BTreeSet::new();
    let step = (bytes.len() / 500).max(1);
    for cut in (0..bytes.len()).step_by(step).chain([bytes.len() - 1]) {
        std::fs::write(&cut_path, &bytes[..cut]).unwrap();
        let got = read_unit_log(&cut_path)
            .unwrap_or_else(|e| panic!("cut at {cut} of {}: {e}", bytes.len()));
        assert_eq!(got[..], records[..got.len()], "cut at {cut}");
        assert!(
            got.len() >= last,
            "cut at {cut}: fewer records than a shorter cut"
        );
        last = got.len();
        partial.insert(got.len());
    }
    assert_eq!(last, records.len(), "all records come before the summary");
    // Every flushed chunk becomes readable on its own.
    for n in (10..=120).step_by(10) {
        assert!(
            partial.contains(&n),
            "no cut gave the first {n} records: {partial:?}"
        );
    }
}

/// Set in the child process of `killed_writer_loses_at_most_the_last_second`: where it
/// writes its log.
const CHILD_LOG_ENV: &str = "MOONHAUL_TEST_KILLED_LOG";

/// The writer `killed_writer_loses_at_most_the_last_second` SIGKILLs: logs a record every
/// 10 ms and prints each one's tick once written, for up to a minute.
#[test]
#[ignore = "the child of killed_writer_loses_at_most_the_last_second"]
fn killed_writer_child() {
    let Some(path) = std::env::var_os(CHILD_LOG_ENV) else {
        return;
    };
    let mut log = UnitLog::create(Path::new(&path), 0, &inputs()).unwrap();
    let start = Instant::now();
    let mut k = 0;
    while start.elapsed() < Duration::from_secs(60) {
        k += 1;
        log.write(&tick(0, k)).unwrap();
        println!("wrote {k}");
        std::thread::sleep(Duration::from_millis(10));
    }
    log.finish().unwrap();
}

#[test]
fn killed_writer_loses_at_most_the_last_second() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit-0.mcap");
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args([
            "mission_log::tests::killed_writer_child",
            "--exact",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_LOG_ENV, &path)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(k) = line.strip_prefix("wrote ").and_then(|k| k.parse().ok()) {
                let _ = tx.send((k, Instant::now()));
            }
        }
    });
    let mut written: Vec<(u64, Instant)> = Vec::new();
    loop {
        let next = rx.recv_timeout(Duration::from_secs(60));
        let Ok(next) = next else {
            let _ = child.kill();
            panic!("the child stopped writing: {next:?}");
        };
        written.push(next);
        if next.1 - written[0].1 >= Duration::from_secs(3) {
            break;
        }
    }
    let killed_at = Instant::now();
    child.kill().unwrap();
    child.wait().unwrap();

    // Written more than a flush period (plus scheduling slack on a loaded machine) before
    // the kill: these must have reached the file.
    let old = written
        .iter()
        .filter(|(_, at)| *at + FLUSH_PERIOD + Duration::from_millis(500) <= killed_at)
        .map(|(k, _)| *k)
        .max()
        .unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert!(
        !bytes.ends_with(mcap::MAGIC),
        "a killed writer leaves no footer"
    );
    let records = read_unit_log(&path).unwrap();
    let ticks: Vec<u64> = records.iter().map(|r| r.tick).collect();
    assert_eq!(ticks, (1..=ticks.len() as u64).collect::<Vec<_>>());
    assert!(
        ticks.len() as u64 >= old,
        "{} records read back; {old} were written over 1.5 s before the kill",
        ticks.len()
    );
    assert_eq!(
        records[..],
        (1..=ticks.len() as u64)
            .map(|k| tick(0, k))
            .collect::<Vec<_>>()[..]
    );
}

fn error_text(result: Result<Vec<TickRecord>, LogError>) -> String {
    result.map(|r| r.len()).unwrap_err().to_string()
}

#[test]
fn garbage_is_an_error_naming_the_file_and_record() {
    let dir = tempfile::tempdir().unwrap();
    let name = |p: &Path| p.display().to_string();

    let random = dir.path().join("random.mcap");
    std::fs::write(
        &random,
        (0..4000u32)
            .map(|i| (i * 7919 % 251) as u8)
            .collect::<Vec<_>>(),
    )
    .unwrap();
    let e = error_text(read_unit_log(&random));
    assert!(e.contains(&name(&random)) && e.contains("record 1"), "{e}");

    // A chunk whose CRC does not match its records; one whose compressed bytes are damaged.
    let path = dir.path().join("unit-0.mcap");
    let mut log = UnitLog::create(&path, 0, &inputs()).unwrap();
    for k in 1..=20 {
        log.write(&tick(0, k)).unwrap();
    }
    log.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let chunk = &mcap::Summary::read(&bytes).unwrap().unwrap().chunk_indexes[0];
    let start = chunk.chunk_start_offset as usize;
    // Opcode, record length, start and end time, uncompressed size: then the CRC.
    let crc_at = start + 1 + 8 + 3 * 8;
    for (at, needle) in [
        (crc_at, "CRC"),
        (start + chunk.chunk_length as usize - 20, ""),
    ] {
        let mut flipped_bytes = bytes.clone();
        flipped_bytes[at] ^= 0x5a;
        let flipped = dir.path().join("flipped.mcap");
        std::fs::write(&flipped, &flipped_bytes).unwrap();
        let e = error_text(read_unit_log(&flipped));
        assert!(
            e.contains(&name(&flipped)) && e.contains("record") && e.contains(needle),
            "{e}"
        );
    }

    // Valid MCAP, but the message is not a TickRecord.
    let bogus = dir.path().join("bogus.mcap");
    {
        let context = Context::new();
        let writer = context
            .mcap_writer()
            .create(BufWriter::new(File::create(&bogus).unwrap()))
            .unwrap();
        let channel = context
            .channel_builder("/unit0/tick")
            .message_encoding("json")
            .build_raw()
            .unwrap();
        channel.log(br#"{"unit": 0}"#);
        writer.close().unwrap();
    }
    let e = error_text(read_unit_log(&bogus));
    assert!(
        e.contains(&name(&bogus)) && e.contains("message 1 on /unit0/tick"),
        "{e}"
    );

    // Not a regular file; larger than the cap.
    let e = error_text(read_unit_log(dir.path()));
    assert!(e.contains("not a regular file"), "{e}");
    let e = read_json_topic::<TickRecord>(&path, 100, &TopicFilter::unit())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&name(&path)) && e.contains("larger than 100 bytes"),
        "{e}"
    );
}

#[test]
fn a_log_of_the_other_kind_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let unit = dir.path().join("unit-0.mcap");
    let mut log = UnitLog::create(&unit, 0, &inputs()).unwrap();
    log.write(&tick(0, 1)).unwrap();
    log.finish().unwrap();
    let world = dir.path().join("world.mcap");
    let mut log = WorldLog::create(&world, [0.4, 0.3, 0.2], 2, &inputs()).unwrap();
    log.write(&frame(0, 2)).unwrap();
    log.finish().unwrap();
    let e = read_world_log(&unit).unwrap_err().to_string();
    assert!(
        e.contains("is not a world log") && e.contains("/unit0/tick"),
        "{e}"
    );
    let e = error_text(read_unit_log(&world));
    assert!(e.contains("is not a unit log"), "{e}");
}

#[test]
fn world_log_round_trips_and_draws_in_3d() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("world.mcap");
    let size = [0.6, 0.4, 0.3];
    // 2.5 s of frames at 50 Hz.
    let frames: Vec<WorldFrame> = (0..125).map(|k| frame(k, 2)).collect();
    let mut log = WorldLog::create(&path, size, 2, &inputs()).unwrap();
    for f in &frames {
        log.write(f).unwrap();
    }
    let e = log.write(&frame(200, 3)).unwrap_err().to_string();
    assert!(e.contains("team of 2") && e.contains("tick 200"), "{e}");
    log.finish().unwrap();
    assert_eq!(read_world_log(&path).unwrap(), frames);

    let topics = messages(&path);
    assert_eq!(
        topics.keys().collect::<Vec<_>>(),
        [SCENE_TOPIC, TF_TOPIC, WORLD_TOPIC]
    );
    let (encoding, schema, tf) = &topics[TF_TOPIC];
    assert_eq!(
        (encoding.as_str(), schema.as_str()),
        ("protobuf", "foxglove.FrameTransforms")
    );
    // Per frame: the payload, then each unit's links.
    assert_eq!(tf.len(), 3 * frames.len());
    let decode = |k: usize| {
        let (time, data) = &tf[k];
        assert_eq!(*time, frames[k / 3].stamp_us * 1000);
        <FrameTransforms as foxglove::Decode>::decode(&data[..]).unwrap()
    };
    let payload = decode(300);
    assert_eq!(payload.transforms.len(), 1);
    assert_eq!(payload.transforms[0].parent_frame_id, "world");
    assert_eq!(payload.transforms[0].child_frame_id, "payload");
    let p = payload.transforms[0].translation.unwrap();
    assert_eq!([p.x, p.y, p.z], frames[100].payload_position_m);
    let spec = UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap();
    for unit in 0..2 {
        let links = decode(301 + unit);
        let f = &frames[100];
        let [x, y, z] = f.base_position_m[unit];
        let base = Isometry3::translation(x, y, z) * spec.ground_to_base();
        let root = format!("truth/unit{unit}/base_link");
        assert_close(&resolve(&links, "world", &root), &base);
        let ee = base * spec.arm.forward(&f.arm_position_rad[unit]).unwrap();
        assert_close(
            &resolve(&links, "world", &format!("truth/unit{unit}/ee")),
            &ee,
        );
    }

    // The cube at start and once a second after: 0, 1, 2 s.
    let (_, schema, scene) = &topics[SCENE_TOPIC];
    assert_eq!(schema, "foxglove.SceneUpdate");
    let times: Vec<u64> = scene.iter().map(|m| m.0).collect();
    assert_eq!(times, [0, 1_000_000_000, 2_000_000_000]);
    let update = <SceneUpdate as foxglove::Decode>::decode(&scene[0].1[..]).unwrap();
    let entity = &update.entities[0];
    assert_eq!(entity.frame_id, "payload");
    assert!(entity.frame_locked);
    let s = entity.cubes[0].size.unwrap();
    assert_eq!([s.x, s.y, s.z], size);
}

#[test]
fn two_logs_in_one_process_do_not_mix() {
    let dir = tempfile::tempdir().unwrap();
    let paths = [
        dir.path().join("unit-0.mcap"),
        dir.path().join("unit-1.mcap"),
    ];
    let mut logs = [
        UnitLog::create(&paths[0], 0, &inputs()).unwrap(),
        UnitLog::create(&paths[1], 1, &inputs()).unwrap(),
    ];
    for k in 1..=30 {
        for (unit, log) in logs.iter_mut().enumerate() {
            log.write(&tick(unit, k)).unwrap();
        }
    }
    for log in logs {
        log.finish().unwrap();
    }
    for (unit, path) in paths.iter().enumerate() {
        let records = read_unit_log(path).unwrap();
        assert_eq!(records, (1..=30).map(|k| tick(unit, k)).collect::<Vec<_>>());
        let topics = messages(path);
        assert_eq!(
            topics.keys().cloned().collect::<Vec<_>>(),
            [TF_TOPIC.to_owned(), unit_topic(unit)]
        );
    }
}

#[test]
fn refuses_to_write_through_a_non_file() {
    let dir = tempfile::tempdir().unwrap();
    let e = UnitLog::create(dir.path(), 0, &inputs())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("not a regular file"), "{e}");
}

/// `assets/foxglove/mission_layout.json` plots and draws only what the logs write: every
/// message path names a topic of a unit or world log and a field of its schema, and the 3-D
/// panel's topics are the logs' `/tf` and `/scene`.
#[test]
fn the_foxglove_layout_names_what_the_logs_write() {
    let text = std::fs::read_to_string(repo_file("assets/foxglove/mission_layout.json")).unwrap();
    let layout: serde_json::Value = serde_json::from_str(&text).unwrap();
    let panels = layout["configById"].as_object().unwrap();
    let mut paths = 0;
    for (id, panel) in panels {
        for path in panel["paths"].as_array().into_iter().flatten() {
            let value = path["value"].as_str().unwrap();
            let (topic, field) = value.split_once('.').unwrap();
            let schema = if topic == WORLD_TOPIC {
                world_schema()
            } else if (0..2).any(|i| topic == unit_topic(i)) {
                tick_schema()
            } else {
                panic!("{id}: {value} is on no topic the logs write")
            };
            assert!(
                schema["properties"].get(field).is_some(),
                "{id}: {value}: no field {field}"
            );
            paths += 1;
        }
        if let Some(topics) = panel["topics"].as_object() {
            for topic in topics.keys() {
                assert!(
                    [TF_TOPIC, SCENE_TOPIC].contains(&topic.as_str()),
                    "{id}: {topic}"
                );
            }
        }
    }
    // Height, phase, t_max; and the 3-D panel.
    assert!(paths >= 5, "{paths}");
    assert!(panels.keys().any(|id| id.starts_with("3D!")));
}

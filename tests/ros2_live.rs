//! A mock unit started with `--ros2-connect` against a bare zenoh peer from PyPI's
//! `eclipse-zenoh` listening there (`tests/ros2/listen_live.py`): it receives the unit's
//! `0/unit_0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_<hash>` samples, which
//! rosbags' CDR codec decodes as JointState with nine joints, with rmw_zenoh's attachment, and
//! sees the node's and publishers' liveliness tokens; the hashes are rosbags' for Jazzy.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

use common::{keys, ros2_python, wait_bounded, Daemon};

#[test]
fn a_mock_units_topics_reach_a_bare_zenoh_peer_in_rmw_zenohs_format() {
    let Some(python) = ros2_python("a_mock_units_topics_reach_a_bare_zenoh_peer") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut listener = Command::new(&python)
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/ros2/listen_live.py"
        ))
        .args([&endpoint, "unit_0", "30"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(listener.stdout.take().unwrap()).lines();
    let first = lines.next().unwrap().unwrap();
    assert_eq!(first, "ready");
    let mut unit = Daemon::unit(
        dir.path(),
        &keys,
        0,
        "mock",
        &["--listen", "tcp/127.0.0.1:0"],
        &["--ros2-connect", &endpoint, "--max-runtime-s", "20"],
    );
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let out = wait_bounded(listener, Duration::from_secs(60));
    let report = rest.join("\n");
    unit.signal("-TERM");
    assert!(unit.wait(Duration::from_secs(20)).success());
    assert!(
        out.status.success() && report.contains("live ok"),
        "{report}\n{}\nunit: {}",
        String::from_utf8_lossy(&out.stderr),
        std::fs::read_to_string(dir.path().join("unit-0.log")).unwrap_or_default()
    );
}

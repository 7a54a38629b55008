//! End-to-end tests of `moonhaul urdf check` and `moonhaul urdf fk` on the Panda test arm and on
//! malformed URDFs.

use std::process::Output;

mod common;
use common::*;

const PANDA: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/crates/core/tests/data/panda.urdf"
);
const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/crates/core/tests/data/fk_reference.json"
);

fn fk(args: &[&str]) -> Output {
    let mut all = vec!["urdf", "fk", PANDA, "--base", "panda_link0"];
    all.extend_from_slice(args);
    moonhaul(&all)
}

fn check_urdf_text(body: &str) -> Output {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.urdf");
    std::fs::write(&path, format!(r#"<robot name="bad">{body}</robot>"#)).unwrap();
    moonhaul(&["urdf", "check", path.to_str().unwrap()])
}

#[test]
fn check_prints_tree_limits_masses_and_dof() {
    let out = stdout(&moonhaul(&["urdf", "check", PANDA]));
    assert!(out.contains("panda_link0 (2.900 kg)"), "{out}");
    assert!(out.contains(
        "joint panda_joint1: revolute, axis (0, 0, 1), lower -2.9671 rad, upper 2.9671 rad, \
         effort 87 N·m, velocity 2.175 rad/s"
    ));
    assert!(out.contains("joint panda_finger_joint1: prismatic, axis (0, 1, 0), lower 0 m"));
    assert!(out.contains("joint panda_joint8: fixed"));
    assert!(
        out.contains("13 links, total mass 17.960 kg; 12 joints, 9 DOF"),
        "{out}"
    );
    // The physical data that was checked.
    assert!(
        out.contains(
            "  inertial: centre of mass (0, 0, 0.05) m, principal moments 0.1, 0.1, 0.1 kg·m²"
        ),
        "{out}"
    );
    assert!(out.contains("  collision: mesh package://meshes/collision/link0.obj"));
    assert!(out.contains("checked: 11 inertials"), "{out}");
}

#[test]
fn check_rejects_missing_link_and_cycle_naming_the_element() {
    let err = stderr(&check_urdf_text(
        r#"<link name="a"/>
        <joint name="to_ghost" type="fixed"><parent link="a"/><child link="ghost"/></joint>"#,
    ));
    assert!(err.contains("bad.urdf"), "{err}");
    assert!(
        err.contains(r#"joint "to_ghost" refers to missing link "ghost""#),
        "{err}"
    );

    let err = stderr(&check_urdf_text(
        r#"<link name="root"/><link name="a"/><link name="b"/>
        <joint name="ab" type="fixed"><parent link="a"/><child link="b"/></joint>
        <joint name="ba" type="fixed"><parent link="b"/><child link="a"/></joint>"#,
    ));
    assert!(err.contains("is on a cycle"), "{err}");
}

#[test]
fn check_rejects_unphysical_urdfs_naming_file_and_element() {
    let cases = [
        (
            r#"<link name="arm_link_3"><inertial><mass value="2"/>
            <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="-1"/></inertial></link>"#,
            r#"link "arm_link_3": inertial inertia is not positive semi-definite"#,
        ),
        (
            r#"<link name="arm_link_3"><inertial><mass value="2"/>
            <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="5"/></inertial></link>"#,
            "triangle inequality",
        ),
        (
            r#"<link name="a"/><link name="b"/>
            <joint name="elbow" type="revolute"><parent link="a"/><child link="b"/>
                <limit lower="-1" upper="1" effort="10" velocity="inf"/></joint>"#,
            r#"joint "elbow": limit velocity is inf"#,
        ),
        (
            r#"<link name="wheel"><collision><geometry><sphere radius="0"/></geometry></collision>
            </link>"#,
            r#"link "wheel": collision #1: sphere radius 0 m"#,
        ),
        (
            &format!(r#"<link name="a">{}</link>"#, "<x>".repeat(100)),
            "nests elements more than 64 deep",
        ),
    ];
    for (body, needle) in cases {
        let err = stderr(&check_urdf_text(body));
        assert!(err.contains("bad.urdf") && err.contains(needle), "{err}");
    }

    let dir = tempfile::tempdir().unwrap();
    let big = dir.path().join("huge.urdf");
    std::fs::write(&big, " ".repeat(5 << 20)).unwrap();
    let err = stderr(&moonhaul(&["urdf", "check", big.to_str().unwrap()]));
    assert!(
        err.contains("huge.urdf") && err.contains("larger than"),
        "{err}"
    );
}

#[test]
fn check_prints_a_10k_link_chain_in_linear_output() {
    const LINKS: usize = 10_000;
    let mut urdf = String::from(r#"<robot name="chain"><link name="l0"/>"#);
    for i in 1..LINKS {
        urdf += &format!(
            r#"<link name="l{i}"><inertial><mass value="1"/>
            <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
            <joint name="j{i}" type="revolute"><parent link="l{}"/><child link="l{i}"/>
            <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"#,
            i - 1
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("chain.urdf");
    std::fs::write(&path, urdf + "</robot>").unwrap();
    let out = stdout(&moonhaul(&["urdf", "check", path.to_str().unwrap()]));
    assert!(
        out.contains("[depth 9999] l9999 (1.000 kg)"),
        "{}",
        &out[out.len() - 500..]
    );
    assert!(out.contains("10000 links, total mass 9999.000 kg; 9999 joints, 9999 DOF"));
    // Indentation is capped: output grows linearly with the chain, not with its square.
    assert!(out.len() < 1000 * LINKS, "{} bytes", out.len());
}

#[test]
fn check_rejects_unreadable_file_naming_it() {
    let err = stderr(&moonhaul(&["urdf", "check", "/nonexistent/arm.urdf"]));
    assert!(err.contains("/nonexistent/arm.urdf"), "{err}");
}

#[test]
fn fk_json_matches_reference_fixture() {
    let fixture: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(FIXTURE).unwrap()).unwrap();
    let chain = &fixture["chains"][0];
    assert_eq!(chain["tip"], "panda_grasptarget");
    let config = chain["configs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| {
            c["q"]
                .as_array()
                .unwrap()
                .iter()
                .any(|v| v.as_f64() != Some(0.0))
        })
        .unwrap();
    let q: Vec<String> = config["q"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.to_string())
        .collect();
    assert!(
        q.iter().any(|v| v.starts_with('-')),
        "want a negative value"
    );

    let out = stdout(&fk(&[
        "--tip",
        "panda_grasptarget",
        "--q",
        &q.join(","),
        "--json",
    ]));
    assert_eq!(out.lines().count(), 1, "{out}");
    let pose: serde_json::Value = serde_json::from_str(&out).unwrap();
    let values = |v: &serde_json::Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let rotation = values(&pose["rotation_xyzw"]);
    assert!(rotation[3] >= 0.0);
    for (key, got) in [
        ("translation", values(&pose["translation"])),
        ("rotation_xyzw", rotation),
    ] {
        for (g, e) in got.iter().zip(values(&config[key])) {
            assert!((g - e).abs() < 1e-9, "{key}: {got:?} vs {}", config[key]);
        }
    }
}

#[test]
fn fk_human_output_and_zero_dof_chain() {
    let out = stdout(&fk(&["--tip", "panda_link1", "--q=-0.5"]));
    assert!(
        out.contains("translation (m):     0.000000 0.000000 0.333000"),
        "{out}"
    );
    assert!(
        out.contains("rpy (rad):           0.000000 0.000000 -0.500000"),
        "{out}"
    );
    // panda_link0 → panda_link0 has no movable joints, so --q may be omitted.
    let out = stdout(&fk(&["--tip", "panda_link0", "--json"]));
    assert_eq!(
        out.trim(),
        r#"{"translation":[0.0,0.0,0.0],"rotation_xyzw":[0.0,0.0,0.0,1.0]}"#
    );
}

#[test]
fn fk_rejects_wrong_count_and_bad_values() {
    let err = stderr(&fk(&["--tip", "panda_link3", "--q", "0.1,-0.2"]));
    assert!(
        err.contains("[panda_joint1, panda_joint2, panda_joint3]")
            && err.contains("expected 3 joint values, got 2"),
        "{err}"
    );
    // panda_joint4 reaches [-3.1416, 0] rad: 0.5 is not a configuration of the arm.
    let err = stderr(&fk(&["--tip", "panda_link4", "--q", "0,0,0,0.5"]));
    assert!(
        err.contains("--q entry 4") && err.contains("panda_joint4") && err.contains("-3.1416"),
        "{err}"
    );
    let err = stderr(&fk(&["--tip", "panda_link1", "--q", "1e308"]));
    assert!(err.contains("panda_joint1"), "{err}");
    let err = stderr(&fk(&["--tip", "panda_link2", "--q", "0.1,abc"]));
    assert!(err.contains(r#"--q entry 2 ("abc")"#), "{err}");
    let err = stderr(&fk(&["--tip", "nose", "--q", "0"]));
    assert!(err.contains(r#"unknown link "nose""#), "{err}");
}

/// A URDF of a base with two wheels on `continuous` joints, as `wheel` gives them (with or
/// without a `<limit>`), and a one-joint revolute arm.
fn wheeled(wheel_limit: &str) -> String {
    let wheel = |side: &str, y: f64| {
        format!(
            r#"<link name="wheel_{side}"/>
            <joint name="wheel_{side}_joint" type="continuous">
                <parent link="base"/><child link="wheel_{side}"/>
                <origin xyz="0 {y} 0.1"/><axis xyz="0 1 0"/>{wheel_limit}</joint>"#
        )
    };
    format!(
        r#"<robot name="rover"><link name="base"/>{}{}
        <link name="arm"/>
        <joint name="shoulder" type="revolute"><parent link="base"/><child link="arm"/>
            <origin xyz="0 0 0.5"/><axis xyz="0 0 1"/>
            <limit lower="-1" upper="1" effort="10" velocity="2"/></joint></robot>"#,
        wheel("left", 0.2),
        wheel("right", -0.2)
    )
}

#[test]
fn continuous_joints_without_limit_pass_check_and_fk() {
    let dir = tempfile::tempdir().unwrap();
    for (name, limit) in [
        ("bare.urdf", ""),
        ("limited.urdf", r#"<limit effort="5" velocity="20"/>"#),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, wheeled(limit)).unwrap();
        let path = path.to_str().unwrap();
        let out = stdout(&moonhaul(&["urdf", "check", path]));
        if limit.is_empty() {
            // Unknown, not zero.
            assert!(
                out.contains(
                    "joint wheel_left_joint: continuous, axis (0, 1, 0), unlimited, effort not \
                     given, velocity not given"
                ),
                "{out}"
            );
        } else {
            assert!(out.contains("effort 5 N·m, velocity 20 rad/s"), "{out}");
        }
        // A wheel turned half a turn: its frame rotates about the axle, the origin stays.
        let out = stdout(&moonhaul(&[
            "urdf",
            "fk",
            path,
            "--base",
            "base",
            "--tip",
            "wheel_left",
            "--q",
            "3.14159",
            "--json",
        ]));
        let value: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        let t = value["translation"].as_array().unwrap();
        let expected = [0.0, 0.2, 0.1];
        for (got, want) in t.iter().zip(expected) {
            assert!((got.as_f64().unwrap() - want).abs() < 1e-9, "{out}");
        }
    }
    // Revolute and prismatic joints still need theirs (the URDF format requires it).
    for kind in ["revolute", "prismatic"] {
        let err = stderr(&check_urdf_text(&format!(
            r#"<link name="a"/><link name="b"/>
            <joint name="slide" type="{kind}"><parent link="a"/><child link="b"/></joint>"#
        )));
        assert!(
            err.contains(r#"joint "slide" has no <limit>"#) && err.contains("bad.urdf"),
            "{kind}: {err}"
        );
    }
}

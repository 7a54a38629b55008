//! Payloads loaded from URDF files: a conforming one is grasped and held like a shipped one;
//! every violation of the payload convention is refused, naming the file and the fault.

use std::path::{Path, PathBuf};

use moonhaul_core::state::UnitCommand;
use moonhaul_sim::scene::UNITS;
use moonhaul_sim::{Env, EnvOptions, PayloadKind, SceneModel, SimConfig};

fn scene() -> SceneModel {
    SceneModel::new(SimConfig::shipped().unwrap()).unwrap()
}

/// The inertial of a solid box of `mass` kg and `size` m (a negative mass keeps the
/// magnitudes, for the sign check).
fn inertial(mass: f64, [x, y, z]: [f64; 3]) -> String {
    let m = mass.abs() / 12.0;
    format!(
        "<inertial><mass value=\"{mass}\"/><inertia ixx=\"{}\" ixy=\"0\" ixz=\"0\" iyy=\"{}\" \
         iyz=\"0\" izz=\"{}\"/></inertial>",
        m * (y * y + z * z),
        m * (x * x + z * z),
        m * (x * x + y * y)
    )
}

fn box_collision([x, y, z]: [f64; 3]) -> String {
    format!("<collision><geometry><box size=\"{x} {y} {z}\"/></geometry></collision>")
}

/// A payload URDF whose one link is `link` with `body` inside.
fn urdf(link: &str, body: &str) -> String {
    format!(
        "<?xml version=\"1.0\"?>\n<robot name=\"p\"><link name=\"{link}\">{body}</link></robot>\n"
    )
}

/// The brief's example: a 0.5 × 0.3 × 0.2 m, 6 kg box.
fn crate_small() -> String {
    let size = [0.5, 0.3, 0.2];
    urdf("payload", &(inertial(6.0, size) + &box_collision(size)))
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_payload_file_loads_grasps_and_is_held() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), "crate_small.urdf", &crate_small());
    let mut scene = scene();
    assert_eq!(scene.payload_name(PayloadKind::Box), "box");
    assert_eq!(scene.payload_name(PayloadKind::Custom), "custom");
    // Before a file is added, a custom episode is an error, not a panic.
    let options = EnvOptions {
        randomize: false,
        payload: Some(PayloadKind::Custom),
        start_lift_m: 0.0,
    };
    assert!(Env::new(&scene, 0, options).is_err());

    assert_eq!(scene.add_payload_file(&path).unwrap(), PayloadKind::Custom);
    assert_eq!(scene.payload_name(PayloadKind::Custom), "crate_small");
    let payload = &scene.payloads[&PayloadKind::Custom];
    assert!((payload.model.mass_kg() - 6.0).abs() < 1e-12);
    assert!((payload.half_extents_m - nalgebra::Vector3::new(0.25, 0.15, 0.1)).norm() < 1e-12);
    assert!(payload.max_lift_m() > 0.0);

    let q = payload.grasp_q_rad;
    let mut env = Env::new(&scene, 0, options).unwrap();
    assert_eq!(env.payload_kind(), PayloadKind::Custom);
    let hold = [UnitCommand {
        arm_position_rad: q,
        ..UnitCommand::default()
    }; UNITS];
    for _ in 0..25 {
        env.step(&scene, &hold);
    }
    let s = env.state(&scene);
    assert!(s.is_finite(), "{s:?}");
    assert!(s.units.iter().all(|u| u.grasp.attached) && !s.grasp_broken);
    assert!(s.payload.height_m.abs() < 0.02, "{s:?}");

    // A second file replaces the first; the randomization can carry it.
    let other = write(dir.path(), "crate_other.urdf", &crate_small());
    scene.add_payload_file(&other).unwrap();
    assert_eq!(scene.payload_name(PayloadKind::Custom), "crate_other");
    scene.config.randomization.payloads = vec![PayloadKind::Custom];
    scene.config.randomization.generated_payloads.share = 0.0;
    let env = Env::new(&scene, 3, EnvOptions::default()).unwrap();
    assert_eq!(env.payload_kind(), PayloadKind::Custom);
}

#[test]
fn malformed_payload_files_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let size = [0.5, 0.3, 0.2];
    let mass = inertial(6.0, size);
    let boxed = box_collision(size);
    let tall = [0.5, 0.3, 3.0];
    let cases = [
        (
            "no_payload_link",
            urdf("crate", &(mass.clone() + &boxed)),
            "\"payload\"",
        ),
        (
            "two_links",
            crate_small().replace(
                "</robot>",
                "<link name=\"tag\"/><joint name=\"j\" type=\"fixed\"><parent link=\"payload\"/>\
                 <child link=\"tag\"/></joint></robot>",
            ),
            "exactly one link",
        ),
        (
            "two_colliders",
            urdf("payload", &(mass.clone() + &boxed + &boxed)),
            "2 <collision>",
        ),
        ("no_collider", urdf("payload", &mass), "0 <collision>"),
        (
            "sphere",
            urdf(
                "payload",
                &(mass.clone()
                    + "<collision><geometry><sphere radius=\"0.2\"/></geometry></collision>"),
            ),
            "not a <box>",
        ),
        (
            "long_side_y",
            urdf(
                "payload",
                &(inertial(6.0, [0.3, 0.5, 0.2]) + &box_collision([0.3, 0.5, 0.2])),
            ),
            "long side",
        ),
        (
            "offset_box",
            urdf(
                "payload",
                &(mass.clone()
                    + "<collision><origin xyz=\"0.1 0 0\"/><geometry><box size=\"0.5 0.3 0.2\"/>\
                       </geometry></collision>"),
            ),
            "origin",
        ),
        ("massless", urdf("payload", &boxed), "positive mass"),
        (
            "zero_mass",
            urdf("payload", &(inertial(0.0, size) + &boxed)),
            "positive mass",
        ),
        (
            "negative_mass",
            urdf("payload", &(inertial(-6.0, size) + &boxed)),
            "negative",
        ),
        (
            "out_of_reach",
            urdf("payload", &(inertial(6.0, tall) + &box_collision(tall))),
            "not graspable",
        ),
        ("not_xml", "payload".to_string(), "not_xml"),
    ];
    let mut scene = scene();
    let good = write(dir.path(), "good.urdf", &crate_small());
    scene.add_payload_file(&good).unwrap();
    for (name, text, needle) in cases {
        let path = write(dir.path(), &format!("{name}.urdf"), &text);
        let message = scene.add_payload_file(&path).unwrap_err().to_string();
        assert!(
            message.contains(&format!("{name}.urdf")) && message.contains(needle),
            "{name}: {message}"
        );
        // A refused file leaves the loaded one in place.
        assert_eq!(scene.payload_name(PayloadKind::Custom), "good");
    }
    let missing = dir.path().join("missing.urdf");
    let message = scene.add_payload_file(&missing).unwrap_err().to_string();
    assert!(message.contains("missing.urdf"), "{message}");
}

//! Forward kinematics of the Franka Panda arm checked against an independent implementation.
//!
//! `tests/data/fk_reference.json` was produced by `tests/data/gen_fk_fixture.py` with pinocchio
//! (PyPI `pin` 4.1.0, `framesForwardKinematics`, double precision, its own urdfdom parser) and
//! cross-checked by that script against pybullet 3.2.7 (`getLinkState(...,
//! computeForwardKinematics=True)` link frames, agreeing within 1e-6; pybullet stores URDF
//! geometry in single precision, so it is not the stored reference). Command, from the
//! repository root:
//!
//! ```text
//! python3 -m venv /tmp/fkvenv && /tmp/fkvenv/bin/pip install pin==4.1.0 pybullet==3.2.7 numpy
//! /tmp/fkvenv/bin/python crates/core/tests/data/gen_fk_fixture.py
//! ```
//!
//! `tests/data/panda.urdf` is pybullet_data's `franka_panda/panda.urdf`, byte for byte (see
//! `tests/data/README.md`). The fixture covers four chains: base to grasp target (7 DOF),
//! base to a finger (7 revolute + 1 prismatic), finger to finger (up then down) and hand to
//! link 3 (all upward), at zeros, both limits, negative, mixed and random joint values.

use moonhaul_core::kinematics::KinematicTree;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::Deserialize;

/// The reference is double precision, so agreement is far tighter than the 1e-6 m / 1e-6 rad
/// the onboard controller needs.
const TOLERANCE: f64 = 1e-9;

#[derive(Deserialize)]
struct Fixture {
    chains: Vec<ChainFixture>,
}

#[derive(Deserialize)]
struct ChainFixture {
    base: String,
    tip: String,
    joints: Vec<String>,
    configs: Vec<Config>,
}

#[derive(Deserialize)]
struct Config {
    q: Vec<f64>,
    translation: [f64; 3],
    rotation_xyzw: [f64; 4],
}

fn data(file: &str) -> String {
    format!("{}/tests/data/{file}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn panda_forward_kinematics_matches_pinocchio() {
    let tree = KinematicTree::from_file(data("panda.urdf")).unwrap();
    let fixture: Fixture =
        serde_json::from_str(&std::fs::read_to_string(data("fk_reference.json")).unwrap()).unwrap();
    assert_eq!(fixture.chains.len(), 4);
    for chain_fixture in &fixture.chains {
        let chain = tree.chain(&chain_fixture.base, &chain_fixture.tip).unwrap();
        assert_eq!(
            chain.joint_names().collect::<Vec<_>>(),
            chain_fixture.joints
        );
        assert!(chain_fixture.configs.len() >= 7);
        for config in &chain_fixture.configs {
            let [x, y, z, w] = config.rotation_xyzw;
            let expected = Isometry3::from_parts(
                Translation3::from(config.translation),
                UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
            );
            let delta = expected.inverse() * chain.forward(&config.q).unwrap();
            let (translation_error, angle_error) =
                (delta.translation.vector.norm(), delta.rotation.angle());
            assert!(
                translation_error < TOLERANCE && angle_error < TOLERANCE,
                "{} -> {} at q = {:?}: translation error {translation_error:e} m, \
                 rotation error {angle_error:e} rad",
                chain_fixture.base,
                chain_fixture.tip,
                config.q
            );
        }
    }
}

//! The generated payload family: every member is a valid, graspable payload drawn inside the
//! configured ranges, the same family from the same config in any process, carried by the
//! configured share of worlds, and held like a shipped payload.

use std::time::Instant;

use moonhaul_core::state::UnitCommand;
use moonhaul_sim::scene::UNITS;
use moonhaul_sim::{Env, EnvOptions, PayloadKind, SceneModel, SimConfig};

#[test]
fn the_family_is_drawn_inside_its_ranges_and_is_reproducible() {
    let config = SimConfig::shipped().unwrap();
    let family = config.randomization.generated_payloads.clone();
    assert!(family.count > 0, "the shipped config generates a family");
    let t0 = Instant::now();
    let scene = SceneModel::new(config.clone()).unwrap();
    eprintln!(
        "scene with {} generated payloads built in {:.2} s",
        family.count,
        t0.elapsed().as_secs_f64()
    );
    let mut heights = Vec::new();
    for i in 0..family.count {
        let kind = PayloadKind::Generated(i);
        assert_eq!(scene.payload_name(kind), format!("gen{i}"));
        assert_eq!(format!("gen{i}").parse::<PayloadKind>().unwrap(), kind);
        let p = scene.payload(kind).unwrap();
        let size = p.half_extents_m * 2.0;
        for (axis, range) in [family.size_x_m, family.size_y_m, family.size_z_m]
            .iter()
            .enumerate()
        {
            assert!(
                (range[0]..=range[1]).contains(&size[axis]),
                "gen{i} axis {axis}: {size:?} outside {range:?}"
            );
        }
        let mass = p.model.mass_kg();
        assert!((family.mass_kg[0]..=family.mass_kg[1]).contains(&mass));
        let com = p.model.bodies[0].inertia.com_m;
        for axis in 0..3 {
            assert!(
                com[axis].abs() <= family.com_offset_m[axis] + 1e-12,
                "{com:?}"
            );
        }
        assert!(
            p.max_lift_m() > 0.3,
            "gen{i} lifts only {} m",
            p.max_lift_m()
        );
        heights.push(size.z);
    }
    // The family spans its height range (the grasp height is what the lift must learn).
    let (lo, hi) = heights
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &z| (l.min(z), h.max(z)));
    let span = family.size_z_m[1] - family.size_z_m[0];
    assert!(hi - lo > 0.6 * span, "heights {heights:?}");
    // A second scene from the same config holds the same family.
    let again = SceneModel::new(config).unwrap();
    for i in 0..family.count {
        let (a, b) = (
            scene.payload(PayloadKind::Generated(i)).unwrap(),
            again.payload(PayloadKind::Generated(i)).unwrap(),
        );
        assert_eq!(a.half_extents_m, b.half_extents_m);
        assert_eq!(a.grasp_q_rad, b.grasp_q_rad);
        assert_eq!(a.model.mass_kg(), b.model.mass_kg());
    }
    // A member the scene does not hold is an error naming it, not a panic.
    let missing = PayloadKind::Generated(family.count);
    let message = scene.payload(missing).unwrap_err().to_string();
    assert!(message.contains("generated"), "{message}");
}

#[test]
fn worlds_carry_the_family_at_its_share_and_hold_it() {
    let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
    let family = &scene.config.randomization.generated_payloads;
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(5);
    let n = 4000;
    let draws: Vec<_> = (0..n)
        .map(|_| scene.config.randomization.draw(&mut rng).payload)
        .collect();
    let generated = draws
        .iter()
        .filter(|p| matches!(p, PayloadKind::Generated(_)))
        .count() as f64
        / n as f64;
    // Binomial(4000, share): 5 standard deviations.
    let sd = (family.share * (1.0 - family.share) / n as f64).sqrt();
    assert!((generated - family.share).abs() < 5.0 * sd, "{generated}");
    for i in 0..family.count {
        assert!(
            draws.contains(&PayloadKind::Generated(i)),
            "gen{i} never drawn"
        );
    }

    // The lowest and the tallest member are grasped and held at rest like a shipped payload.
    let by_height = |pick: fn(f64, f64) -> bool| {
        (0..family.count)
            .map(PayloadKind::Generated)
            .reduce(|a, b| {
                let z = |k| scene.payload(k).unwrap().half_extents_m.z;
                if pick(z(b), z(a)) {
                    b
                } else {
                    a
                }
            })
            .unwrap()
    };
    for kind in [by_height(|a, b| a < b), by_height(|a, b| a > b)] {
        let options = EnvOptions {
            randomize: true,
            payload: Some(kind),
            start_lift_m: 0.0,
        };
        let mut env = Env::new(&scene, 1, options).unwrap();
        assert_eq!(env.payload_kind(), kind);
        let hold = [UnitCommand {
            arm_position_rad: scene.payload(kind).unwrap().grasp_q_rad,
            ..UnitCommand::default()
        }; UNITS];
        for _ in 0..25 {
            env.step(&scene, &hold);
        }
        let s = env.state(&scene);
        assert!(s.units.iter().all(|u| u.grasp.attached) && !s.grasp_broken);
        assert!(s.payload.height_m.abs() < 0.03, "{kind:?}: {s:?}");
    }
}

#[test]
fn bad_family_settings_are_refused_by_field() {
    let text =
        std::fs::read_to_string(moonhaul_core::config::repo_file("configs/sim.toml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("control.toml"),
        std::fs::read_to_string(
            moonhaul_core::config::repo_file("configs/sim.toml").with_file_name("control.toml"),
        )
        .unwrap(),
    )
    .unwrap();
    for (from, to, field) in [
        ("count = 32", "count = 65", "generated_payloads.count"),
        ("share = 0.5", "share = 1.5", "generated_payloads.share"),
        (
            "size_x_m = [0.35, 1.0]",
            "size_x_m = [0.2, 1.0]",
            "generated_payloads.size_x_m",
        ),
        (
            "com_offset_m = [0.05, 0.0, 0.015]",
            "com_offset_m = [0.05, 0.0, 0.5]",
            "generated_payloads.com_offset_m",
        ),
        (
            "payloads = [\"box\", \"bricks\"]",
            "payloads = [\"box\", { generated = 1 }]",
            "randomization.payloads",
        ),
    ] {
        assert!(text.contains(from), "{from}");
        let path = dir.path().join("sim.toml");
        std::fs::write(&path, text.replace(from, to)).unwrap();
        let message = SimConfig::load(&path).unwrap_err().to_string();
        assert!(message.contains(field), "{to}: {message}");
    }
}

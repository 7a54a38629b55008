//! `moonhaul eval` end to end on hand-built policies whose increment is zero (they hold): every
//! case runs, the CSVs land where documented, the metrics recomputed from the CSVs equal the
//! reported ones, and a policy of another observation layout, action map or phase is refused by
//! name.

mod common;

use std::collections::BTreeMap;
use std::path::Path;

use common::{fails_naming, moonhaul, stdout};
use moonhaul_core::action::ActionMap;
use moonhaul_core::observation::{
    layout_fields, ACTOR_OBS_DIM, LAYOUT_FIELDS_KEY, LAYOUT_VERSION_KEY, OBS_LAYOUT_VERSION,
};
use moonhaul_core::policy::{
    ActionAffine, Activation, Linear, ObsNormalizer, Policy, PolicyMetadata, Tensor,
};
use moonhaul_core::state::{Phase, UNIT_ACTION_DIM};
use moonhaul_sim::task::{PhaseTask, TaskConfig};
use moonhaul_sim::{SceneModel, SimConfig};

/// A zero-weight policy: its increment is always zero, so it holds the command it starts from
/// (the anchor on the sensed joints). `layout`/`action_map`: whether the file records this
/// build's observation layout and action map.
fn hold_policy(task: &PhaseTask, layout: bool, action_map: bool) -> Policy {
    let mut extra = BTreeMap::new();
    if layout {
        extra.insert(LAYOUT_VERSION_KEY.into(), OBS_LAYOUT_VERSION.to_string());
        extra.insert(LAYOUT_FIELDS_KEY.into(), layout_fields());
    }
    if action_map {
        for (k, v) in ActionMap::metadata() {
            extra.insert(k.into(), v);
        }
    }
    let metadata = PolicyMetadata {
        phase: task.phase,
        obs_dim: ACTOR_OBS_DIM,
        action_dim: UNIT_ACTION_DIM,
        hidden_sizes: vec![],
        activation: Activation::Elu,
        obs_clip: None,
        extra,
    };
    let vector = |v: &[f64]| Tensor::vector(v.iter().map(|&x| x as f32).collect());
    let layer = Linear {
        weight: Tensor::new(
            vec![UNIT_ACTION_DIM, ACTOR_OBS_DIM],
            vec![0.0; UNIT_ACTION_DIM * ACTOR_OBS_DIM],
        )
        .unwrap(),
        bias: vector(&[0.0; UNIT_ACTION_DIM]),
    };
    let norm = ObsNormalizer {
        mean: vector(&[0.0; ACTOR_OBS_DIM]),
        std: vector(&[1.0; ACTOR_OBS_DIM]),
    };
    let action = ActionAffine {
        scale: vector(&task.action_map().step),
        offset: vector(&[0.0; UNIT_ACTION_DIM]),
    };
    Policy::new(metadata, vec![layer], norm, action).unwrap()
}

fn write_policies(dir: &Path, layout: bool, action_map: bool) {
    let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
    let tasks = TaskConfig::shipped().unwrap();
    let sync = moonhaul_coord::SyncConfig::shipped().unwrap();
    for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
        let task = PhaseTask::new(phase, tasks, sync, &scene).unwrap();
        hold_policy(&task, layout, action_map)
            .write_file(dir.join(format!("{}.safetensors", phase.name())))
            .unwrap();
    }
}

#[test]
fn eval_writes_every_case_and_its_metrics_recompute_from_the_csvs() {
    let dir = tempfile::tempdir().unwrap();
    let policies = dir.path().join("policies");
    std::fs::create_dir(&policies).unwrap();
    write_policies(&policies, true, true);
    let out = dir.path().join("out");
    let (p, o) = (policies.to_str().unwrap(), out.to_str().unwrap());
    let args = [
        "eval",
        "--policies",
        p,
        "--payload",
        "box",
        "--episodes",
        "2",
        "--no-scripted",
        "--json",
    ];
    let run = moonhaul(&[&args[..], &["--out", o]].concat());
    // Stdout is the JSON alone; the progress goes to stderr, a line per finished run (5 cases,
    // then the deployed missions) when stderr is not a terminal.
    let mut reported: serde_json::Value = serde_json::from_str(&stdout(&run)).unwrap();
    let progress = String::from_utf8_lossy(&run.stderr);
    for line in [
        "eval: [1/6] box lift-0.3 learned: 2 episodes in ",
        "eval: [5/6] box place learned: 2 episodes in ",
        "eval: [6/6] box learned deployed: 2 missions in ",
    ] {
        assert!(progress.contains(line), "no {line:?} in {progress}");
    }
    let box_ = &reported["box"];
    assert_eq!(box_["episodes"], 2);
    for h in ["0.3", "0.5", "0.75"] {
        let lift = &box_["lift"][h];
        // Holding still never lifts: the error is the whole target height.
        let error = lift["final_height_error_mm"]["mean"].as_f64().unwrap();
        let target_mm = h.parse::<f64>().unwrap() * 1000.0;
        assert!((error - target_mm).abs() < 20.0, "{h}: {error}");
        assert_eq!(lift["success_rate"]["mean"], 0.0);
        // Each metric the paper reports carries its figure, the one the table prints.
        assert!(lift["final_height_error_mm"]["paper"].as_f64().unwrap() > 5.0);
        assert!(lift["success_rate"].get("paper").is_none());
    }
    assert_eq!(box_["lift"]["0.5"]["final_height_error_mm"]["paper"], 17.4);
    assert_eq!(box_["place"]["touchdown_speed_mps"]["paper"], 0.030);
    assert!(
        box_["transport"]["rms_velocity_error_mps"]["mean"]
            .as_f64()
            .unwrap()
            > 0.05
    );
    for case in ["lift-0.3", "lift-0.5", "lift-0.75", "transport", "place"] {
        for episode in ["000.csv", "001.csv"] {
            assert!(
                out.join("box").join(case).join(episode).is_file(),
                "{case}/{episode}"
            );
        }
    }
    // A placement runs the mission's `after_release_s` past the place episode's training
    // length, so its steady window can follow a release; the holding policy never releases
    // and runs to that limit.
    let place_csv = std::fs::read_to_string(out.join("box/place/000.csv")).unwrap();
    let last_t_s: f64 = place_csv
        .lines()
        .last()
        .and_then(|row| row.split(',').next())
        .and_then(|t| t.parse().ok())
        .unwrap();
    let limit_s = TaskConfig::shipped().unwrap().place.duration_s
        + moonhaul_core::scripted::MissionPlan::shipped()
            .unwrap()
            .after_release_s;
    assert!((last_t_s - limit_s).abs() < 1e-9, "{last_t_s} s");
    let recomputed: serde_json::Value = serde_json::from_str(&stdout(&moonhaul(&[
        "eval",
        "--recompute",
        o,
        "--payload",
        "box",
    ])))
    .unwrap();
    // The deployed stack ran too (every case was asked for), through the onboard tick: a hold
    // policy never lifts, so its missions stay in lift, holding their commands (every step
    // admissible, the drives on them).
    let learned = reported["box"]
        .as_object_mut()
        .unwrap()
        .remove("learned")
        .unwrap();
    let deployed = &learned["deployed"];
    assert_eq!(deployed["transport"]["reached_rate"], 0.0);
    assert_eq!(deployed["clamp"]["completed_rate"], 0.0);
    assert_eq!(deployed["clamp"]["no_step_fraction"], 0.0);
    assert!(deployed["clamp"]["mean_t_max"].as_f64().unwrap() > 0.99);
    let mean_d = deployed["clamp"]["mean_tracking_d"].as_f64().unwrap();
    assert!(mean_d < 0.2);
    // Per phase: every loaded tick was in lift; the phases never reached have none.
    let by_phase = &deployed["clamp"]["mean_tracking_d_by_phase"];
    assert_eq!(by_phase["lift"].as_f64(), Some(mean_d), "{by_phase}");
    assert!(
        by_phase["transport"].is_null() && by_phase["place"].is_null(),
        "{by_phase}"
    );
    assert!(deployed["max_grasp_force_n"].as_f64().unwrap() > 0.0);
    assert!(out.join("box/deployed/lift-0.3/000.csv").is_file());
    assert_eq!(recomputed, reported);
    // The table says the same below the metrics, and stdout holds nothing else.
    let table_args: Vec<&str> = args.iter().copied().filter(|a| *a != "--json").collect();
    let table = stdout(&moonhaul(&table_args));
    let by_phase = format!(
        "gate+clamp, learned: 0/2 missions completed; mean d(U_{{k−1}}, Y_k) loaded: lift {:.3}, \
         transport -, place - (all {:.3})",
        mean_d, mean_d
    );
    assert!(table.contains(&by_phase), "no {by_phase:?} in\n{table}");
    assert!(!table.contains("eval: "), "{table}");
    // A second run into the same folder would replace the first one's files: only with
    // --force.
    let err = fails_naming(&[&args[..], &["--out", o]].concat(), "--force");
    assert!(err.contains(o), "{err}");
}

#[test]
fn policies_of_another_layout_action_map_or_phase_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    write_policies(dir.path(), false, true);
    let p = dir.path().to_str().unwrap();
    let err = fails_naming(
        &[
            "eval",
            "--policies",
            p,
            "--episodes",
            "1",
            "--payload",
            "box",
        ],
        "lift.safetensors",
    );
    assert!(err.contains("observation layout"), "{err}");
    // A policy of absolute targets (the action map before the increment) is refused too.
    write_policies(dir.path(), true, false);
    let err = fails_naming(
        &[
            "eval",
            "--policies",
            p,
            "--episodes",
            "1",
            "--payload",
            "box",
        ],
        "lift.safetensors",
    );
    assert!(
        err.contains("action map") && err.contains("retrain"),
        "{err}"
    );
    write_policies(dir.path(), true, true);
    std::fs::copy(
        dir.path().join("lift.safetensors"),
        dir.path().join("place.safetensors"),
    )
    .unwrap();
    let err = fails_naming(
        &[
            "eval",
            "--policies",
            p,
            "--episodes",
            "1",
            "--payload",
            "box",
        ],
        "place.safetensors",
    );
    assert!(err.contains("drives lift"), "{err}");
}

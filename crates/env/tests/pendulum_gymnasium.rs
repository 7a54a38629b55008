//! Replays gymnasium's own Pendulum-v1 trajectories (`tests/data/pendulum_v1.json`, made by
//! `tests/data/gen_pendulum_fixture.py`) through the Rust implementation.

use moonhaul_env::pendulum::{Pendulum, MAX_EPISODE_STEPS};
use serde_json::Value;

fn f(v: &Value) -> f64 {
    v.as_f64().expect("fixture number")
}

#[test]
fn matches_gymnasium_step_for_step() {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/pendulum_v1.json"
    ))
    .expect("fixture present");
    let fixture: Value = serde_json::from_str(&text).expect("fixture is JSON");
    let trajectories = fixture["trajectories"].as_array().expect("trajectories");
    assert!(trajectories.len() >= 4);
    for t in trajectories {
        // f64 actions: gymnasium computes in f64 like we do, so only libm ulps may differ.
        // f32 actions: NumPy 2 evaluates gymnasium's torque terms in float32 (NEP 50).
        let tol = if t["action_dtype"] == "float64" {
            1e-12
        } else {
            1e-5
        };
        let init = t["initial_state"].as_array().expect("initial_state");
        let mut p = Pendulum {
            theta_rad: f(&init[0]),
            theta_dot_radps: f(&init[1]),
        };
        let steps = t["steps"].as_array().expect("steps");
        assert_eq!(steps.len(), MAX_EPISODE_STEPS as usize);
        let mut worst: f64 = 0.0;
        for (k, s) in steps.iter().enumerate() {
            let reward = p.step(f(&s["action"]));
            let state = s["state"].as_array().expect("state");
            worst = worst
                .max((reward - f(&s["reward"])).abs())
                .max((p.theta_rad - f(&state[0])).abs())
                .max((p.theta_dot_radps - f(&state[1])).abs());
            let obs = p.observation();
            for (j, o) in s["obs"].as_array().expect("obs").iter().enumerate() {
                // gymnasium returns float32 observations.
                worst = worst.max((f64::from(obs[j] as f32) - f(o)).abs());
            }
            assert_eq!(s["terminated"], false, "step {k}");
            assert_eq!(
                s["truncated"],
                k + 1 == MAX_EPISODE_STEPS as usize,
                "step {k}"
            );
        }
        assert!(
            worst <= tol,
            "seed {} {}: max deviation {worst:e}",
            t["seed"],
            t["action_dtype"]
        );
    }
}

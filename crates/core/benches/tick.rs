//! Per-call cost of the core math the onboard daemon runs every control tick (20 ms at the
//! paper's 50 Hz): the stacked metric for N = 2, forward kinematics of a 7-joint arm chain,
//! and a policy forward pass with the paper's [256, 128, 64] lift/place network.
//!
//! Run: `cargo bench -p moonhaul-core --bench tick` (or `cargo xtask demo`). Prints the median
//! time per call over several batches and the share of a 20 ms tick it takes.

use moonhaul_core::kinematics::KinematicTree;
use moonhaul_core::policy::{
    ActionAffine, Activation, Linear, ObsNormalizer, Policy, PolicyMetadata, Tensor,
};
use moonhaul_core::stacked::{StackedState, SyncTolerances, UnitPoses};
use moonhaul_core::state::Phase;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2};
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

const TICK: Duration = Duration::from_millis(20);
const BATCHES: usize = 15;

/// Median time per call over `BATCHES` batches of `calls` calls each.
fn time_per_call(name: &str, calls: usize, mut f: impl FnMut()) {
    for _ in 0..calls {
        f(); // warm-up: caches, branch predictors, lazy page faults
    }
    let mut per_call: Vec<f64> = (0..BATCHES)
        .map(|_| {
            let start = Instant::now();
            for _ in 0..calls {
                f();
            }
            start.elapsed().as_secs_f64() / calls as f64
        })
        .collect();
    per_call.sort_by(f64::total_cmp);
    let median = per_call[BATCHES / 2];
    println!(
        "{name:<44} {:>9.3} µs/call  {:>12.0} calls/s  {:>8.4} % of a 20 ms tick",
        median * 1e6,
        1.0 / median,
        100.0 * median / TICK.as_secs_f64()
    );
}

/// Deterministic pseudo-random numbers in [-1, 1) (xorshift64*), so the bench needs no RNG crate.
struct Numbers(u64);

impl Numbers {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11;
        bits as f64 / (1u64 << 52) as f64 - 1.0
    }

    fn tensor(&mut self, shape: Vec<usize>, scale: f64) -> Tensor {
        let len = shape.iter().product();
        let data = (0..len).map(|_| (scale * self.next()) as f32).collect();
        Tensor::new(shape, data).expect("shape matches length")
    }
}

fn random_policy(obs_dim: usize, hidden: &[usize], action_dim: usize, rng: &mut Numbers) -> Policy {
    let sizes: Vec<usize> = std::iter::once(obs_dim)
        .chain(hidden.iter().copied())
        .chain([action_dim])
        .collect();
    let layers = sizes
        .windows(2)
        .map(|io| {
            let bound = 1.0 / (io[0] as f64).sqrt();
            Linear {
                weight: rng.tensor(vec![io[1], io[0]], bound),
                bias: rng.tensor(vec![io[1]], bound),
            }
        })
        .collect();
    let metadata = PolicyMetadata {
        phase: Phase::Lift,
        obs_dim,
        action_dim,
        hidden_sizes: hidden.to_vec(),
        activation: Activation::Elu,
        obs_clip: Some(5.0),
        extra: Default::default(),
    };
    let obs_norm = ObsNormalizer {
        mean: rng.tensor(vec![obs_dim], 0.1),
        std: Tensor::vector(vec![1.0; obs_dim]),
    };
    let action = ActionAffine {
        scale: Tensor::vector(vec![0.5; action_dim]),
        offset: Tensor::vector(vec![0.0; action_dim]),
    };
    Policy::new(metadata, layers, obs_norm, action).expect("valid random policy")
}

fn random_team(rng: &mut Numbers) -> StackedState {
    let unit = |rng: &mut Numbers| UnitPoses {
        arm: Isometry3::from_parts(
            Translation3::new(rng.next(), rng.next(), rng.next()),
            UnitQuaternion::from_euler_angles(rng.next(), rng.next(), rng.next()),
        ),
        base_xy_m: Vector2::new(rng.next(), rng.next()),
    };
    StackedState {
        units: vec![unit(rng), unit(rng)],
    }
}

fn main() {
    let mut rng = Numbers(0x9e37_79b9_7f4a_7c15);

    let (x, y) = (random_team(&mut rng), random_team(&mut rng));
    // The paper's tolerances (configs/sync.toml).
    let tol = SyncTolerances {
        arm_translation_m: 0.03,
        arm_rotation_deg: 5.0,
        base_xy_m: [0.02, 0.02],
    };
    time_per_call("stacked metric d(X, Y), N = 2", 200_000, || {
        black_box(
            black_box(&x)
                .distance(black_box(&y), &tol)
                .expect("same team"),
        );
    });

    let arm = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/panda.urdf");
    let chain = KinematicTree::from_file(&arm)
        .and_then(|tree| tree.chain("panda_link0", "panda_grasptarget"))
        .expect("bundled Panda URDF loads");
    let q = [0.3, -0.5, 0.2, -1.2, 0.4, 0.9, -0.1];
    time_per_call("forward kinematics, 7-joint Panda chain", 200_000, || {
        black_box(chain.forward(black_box(&q)).expect("7 joint values"));
    });

    let policy = random_policy(80, &[256, 128, 64], 18, &mut rng);
    let mut scratch = policy.scratch();
    let obs: Vec<f64> = (0..80).map(|_| rng.next()).collect();
    let mut action = [0.0; 18];
    time_per_call(
        "policy MLP 80 → [256, 128, 64] → 18, ELU",
        5_000,
        || {
            policy
                .act(black_box(&obs), &mut scratch, &mut action)
                .expect("sizes match");
            black_box(&action);
        },
    );
}

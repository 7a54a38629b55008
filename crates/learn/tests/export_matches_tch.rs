//! The onboard runtime (pure-Rust MLP in moonhaul-core) computes the same actions as the
//! trainer's tch forward pass, normalizer included, before and after a trip through the file.
//! The critic reads a wider (privileged) observation and its normalizer is not exported.

use moonhaul_core::policy::Policy;
use moonhaul_core::state::Phase;
use moonhaul_learn::actor_critic::ActorCritic;
use moonhaul_learn::config::{PolicyConfig, StdType};
use moonhaul_learn::export::export_policy;
use moonhaul_learn::runner::{to_f64, to_tensor};
use tch::{Device, Kind, Tensor};

#[test]
fn core_runtime_equals_tch_forward_within_1e_5() {
    tch::manual_seed(11);
    let (obs_dim, action_dim) = (80, 18);
    let config = PolicyConfig {
        actor_hidden: vec![256, 128, 64],
        critic_hidden: vec![64],
        init_std: 1.0,
        actor_output_gain: 1.0,
        std_type: StdType::Scalar,
        obs_normalization: true,
    };
    let critic_obs_dim = obs_dim + 7;
    let mut ac = ActorCritic::new(obs_dim, critic_obs_dim, action_dim, &config);
    // A non-trivial normalizer: per-feature offsets and scales far from (0, 1).
    let scale = Tensor::linspace(0.1, 20.0, obs_dim as i64, (Kind::Float, Device::Cpu));
    let offset = Tensor::linspace(-5.0, 7.0, obs_dim as i64, (Kind::Float, Device::Cpu));
    let opts = (Kind::Float, Device::Cpu);
    for _ in 0..4 {
        ac.update_normalizers(
            &(Tensor::randn([256, obs_dim as i64], opts) * &scale + &offset),
            &(Tensor::randn([256, critic_obs_dim as i64], opts) * 3.0 - 1.0),
        );
    }
    let action_scale: Vec<f64> = (0..action_dim).map(|i| 0.5 + i as f64 * 0.1).collect();
    let action_offset: Vec<f64> = (0..action_dim).map(|i| i as f64 * 0.01 - 0.05).collect();
    let policy = export_policy(
        &ac,
        Phase::Lift,
        &action_scale,
        &action_offset,
        Default::default(),
    )
    .unwrap();

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lift.safetensors");
    policy.write_file(&path).unwrap();
    let loaded = Policy::from_file(&path).unwrap();
    assert_eq!(loaded, policy);
    assert_eq!(loaded.obs_dim(), obs_dim);

    let n = 64;
    let obs =
        Tensor::randn([n as i64, obs_dim as i64], (Kind::Float, Device::Cpu)) * &scale + &offset;
    let obs = to_f64(&obs).unwrap();
    let mean = ac.act_deterministic(&to_tensor(&obs, n, obs_dim));
    let expected = to_f64(&mean).unwrap();
    let mut scratch = loaded.scratch();
    let mut action = vec![0.0; action_dim];
    let mut worst: f64 = 0.0;
    for i in 0..n {
        loaded
            .act(
                &obs[i * obs_dim..(i + 1) * obs_dim],
                &mut scratch,
                &mut action,
            )
            .unwrap();
        for (k, a) in action.iter().enumerate() {
            let tch_action = action_offset[k] + action_scale[k] * expected[i * action_dim + k];
            worst = worst.max((a - tch_action).abs());
        }
    }
    assert!(worst <= 1e-5, "max |core - tch| = {worst:e}");
}

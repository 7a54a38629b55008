//! rsl_rl's `EmpiricalNormalization`: running mean and variance of the observations over every
//! batch seen, applied as `(x − mean) / (std + ε)`. Exported with the policy (ε folded into
//! the std), because the onboard network only works on the inputs it was trained on.

use tch::{Kind, Tensor};

/// rsl_rl's default ε, added to the std (not the variance); the exported file holds `std + ε`.
pub const EPS: f64 = moonhaul_env::export::NORMALIZER_EPS;

#[derive(Debug)]
pub struct EmpiricalNormalizer {
    mean: Tensor,
    var: Tensor,
    /// `√var + ε`, recomputed when the statistics change rather than on every
    /// [`EmpiricalNormalizer::normalize`]: the rollout normalizes twice per step and the update
    /// once per minibatch, while the statistics change once per step.
    std: Tensor,
    count: i64,
}

fn std_of(var: &Tensor) -> Tensor {
    var.sqrt() + EPS
}

impl EmpiricalNormalizer {
    /// Identity statistics (mean 0, variance 1) for `dim` features.
    pub fn new(dim: i64) -> Self {
        let var = Tensor::ones([dim], (Kind::Float, tch::Device::Cpu));
        EmpiricalNormalizer {
            mean: Tensor::zeros([dim], (Kind::Float, tch::Device::Cpu)),
            std: std_of(&var),
            var,
            count: 0,
        }
    }

    /// Restores saved statistics (checkpoint resume).
    pub fn from_parts(mean: Tensor, var: Tensor, count: i64) -> Self {
        EmpiricalNormalizer {
            std: std_of(&var),
            mean,
            var,
            count,
        }
    }

    /// Folds a batch `[B, dim]` into the running statistics (parallel-variance update).
    pub fn update(&mut self, x: &Tensor) {
        tch::no_grad(|| {
            let batch = x.size()[0];
            self.count += batch;
            let rate = batch as f64 / self.count as f64;
            let var_x = x.var_dim(0, false, false);
            let mean_x = x.mean_dim(0, false, Kind::Float);
            let delta = &mean_x - &self.mean;
            self.mean += &delta * rate;
            self.var += (var_x - &self.var + &delta * (&mean_x - &self.mean)) * rate;
            self.std = std_of(&self.var);
        });
    }

    pub fn normalize(&self, x: &Tensor) -> Tensor {
        (x - &self.mean) / &self.std
    }

    pub fn mean(&self) -> &Tensor {
        &self.mean
    }

    pub fn var(&self) -> &Tensor {
        &self.var
    }

    pub fn count(&self) -> i64 {
        self.count
    }

    /// The divisor the network sees: `√var + ε`, strictly positive.
    pub fn export_std(&self) -> Tensor {
        self.std.copy()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_statistics_equal_whole_data_statistics() {
        tch::manual_seed(3);
        let data = Tensor::randn([300, 4], (Kind::Float, tch::Device::Cpu)) * 3.0 + 5.0;
        let mut norm = EmpiricalNormalizer::new(4);
        for chunk in data.split(100, 0) {
            norm.update(&chunk);
        }
        let mean_err = (norm.mean() - data.mean_dim(0, false, Kind::Float))
            .abs()
            .max();
        let var_err = (norm.var() - data.var_dim(0, false, false)).abs().max();
        assert!(mean_err.double_value(&[]) < 1e-4 && var_err.double_value(&[]) < 1e-3);
        assert_eq!(norm.count(), 300);
        let z = norm.normalize(&data);
        assert!(z.mean(Kind::Float).double_value(&[]).abs() < 1e-4);
    }
}

//! Adam as `torch.optim.Adam` computes it (rsl_rl's optimizer, PyTorch defaults), plus the
//! global gradient-norm clip of `torch.nn.utils.clip_grad_norm_`.
//!
//! Written here rather than taken from `tch::nn::Optimizer` because that wraps libtorch's C++
//! optimizer, whose moment estimates cannot be read or restored: a resumed run would restart
//! Adam from zero. Here the state is plain named tensors that a checkpoint carries.

use tch::nn::VarStore;
use tch::Tensor;

/// PyTorch's defaults (rsl_rl constructs `torch.optim.Adam(params, lr=...)`).
pub const BETA1: f64 = 0.9;
pub const BETA2: f64 = 0.999;
pub const EPS: f64 = 1e-8;

#[derive(Debug)]
pub struct Adam {
    /// Parameters by variable-store name, sorted by name (a stable order for checkpoints).
    params: Vec<(String, Tensor)>,
    exp_avg: Vec<Tensor>,
    exp_avg_sq: Vec<Tensor>,
    step: i64,
    lr: f64,
}

impl Adam {
    /// Optimises every variable of `vs`.
    pub fn new(vs: &VarStore, lr: f64) -> Self {
        Self::over(vs, lr, |_| true)
    }

    /// Optimises the variables of `vs` whose names `keep` accepts, e.g. the actor's alone
    /// (`actor.`): the others never move, whatever gradients they hold.
    pub fn over(vs: &VarStore, lr: f64, keep: impl Fn(&str) -> bool) -> Self {
        let mut params: Vec<(String, Tensor)> = vs
            .variables()
            .into_iter()
            .filter(|(name, _)| keep(name))
            .collect();
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let zeros = |p: &[(String, Tensor)]| p.iter().map(|(_, t)| t.zeros_like()).collect();
        Adam {
            exp_avg: zeros(&params),
            exp_avg_sq: zeros(&params),
            params,
            step: 0,
            lr,
        }
    }

    pub fn lr(&self) -> f64 {
        self.lr
    }

    pub fn set_lr(&mut self, lr: f64) {
        self.lr = lr;
    }

    /// Steps taken so far (the bias-correction exponent).
    pub fn step_count(&self) -> i64 {
        self.step
    }

    pub fn zero_grad(&mut self) {
        for (_, p) in &mut self.params {
            p.zero_grad();
        }
    }

    /// Scales all gradients together so that their joint L2 norm is at most `max_norm`;
    /// returns the norm before clipping.
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        tch::no_grad(|| {
            let grads: Vec<Tensor> = self
                .params
                .iter()
                .map(|(_, p)| p.grad())
                .filter(Tensor::defined)
                .collect();
            if grads.is_empty() {
                return 0.0;
            }
            let norms: Vec<Tensor> = grads.iter().map(|g| g.norm()).collect();
            let total = Tensor::stack(&norms, 0).norm().double_value(&[]);
            let coef = (max_norm / (total + 1e-6)).min(1.0);
            if coef < 1.0 {
                for mut g in grads {
                    let _ = g.g_mul_scalar_(coef);
                }
            }
            total
        })
    }

    /// One Adam update of every parameter that has a gradient.
    pub fn step(&mut self) {
        self.step += 1;
        let bias1 = 1.0 - BETA1.powi(self.step as i32);
        let bias2_sqrt = (1.0 - BETA2.powi(self.step as i32)).sqrt();
        let step_size = self.lr / bias1;
        tch::no_grad(|| {
            for (((_, p), m), v) in self
                .params
                .iter_mut()
                .zip(&mut self.exp_avg)
                .zip(&mut self.exp_avg_sq)
            {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let _ = m.lerp_(&g, 1.0 - BETA1);
                let _ = v.g_mul_scalar_(BETA2);
                let _ = v.addcmul_(&(&g * (1.0 - BETA2)), &g);
                let denom = v.sqrt() / bias2_sqrt + EPS;
                let _ = p.g_sub_(&(&*m / denom * step_size));
            }
        });
    }

    /// `(name, exp_avg, exp_avg_sq)` per parameter, for checkpoints.
    pub fn moments(&self) -> impl Iterator<Item = (&str, &Tensor, &Tensor)> {
        self.params
            .iter()
            .zip(self.exp_avg.iter().zip(&self.exp_avg_sq))
            .map(|((n, _), (m, v))| (n.as_str(), m, v))
    }

    /// Restores the moments and step count; `find(name)` yields each parameter's saved
    /// `(exp_avg, exp_avg_sq)`. Fails with the name of the first missing or misshapen one.
    pub fn restore(
        &mut self,
        step: i64,
        mut find: impl FnMut(&str) -> Option<(Tensor, Tensor)>,
    ) -> Result<(), String> {
        for (((name, p), m), v) in self
            .params
            .iter()
            .zip(&mut self.exp_avg)
            .zip(&mut self.exp_avg_sq)
        {
            let (saved_m, saved_v) =
                find(name).ok_or_else(|| format!("no Adam moments for `{name}`"))?;
            if saved_m.size() != p.size() || saved_v.size() != p.size() {
                return Err(format!(
                    "Adam moments of `{name}` do not match its shape {:?}",
                    p.size()
                ));
            }
            *m = saved_m;
            *v = saved_v;
        }
        self.step = step;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{nn, Device, Kind};

    #[test]
    fn matches_pytorch_adam_on_a_quadratic() {
        // Reference: torch.optim.Adam([p], lr=0.1) on loss = sum(p^2) from p = [1, -2], three
        // steps, as printed by PyTorch 2.13.
        let vs = nn::VarStore::new(Device::Cpu);
        let p = vs
            .root()
            .var_copy("p", &Tensor::from_slice(&[1.0f32, -2.0]));
        let mut adam = Adam::new(&vs, 0.1);
        for _ in 0..3 {
            adam.zero_grad();
            p.square().sum(Kind::Float).backward();
            adam.step();
        }
        let got: Vec<f32> = Vec::try_from(&p).unwrap();
        let expected = [0.701_586_3f32, -1.700_623_4];
        for (g, e) in got.iter().zip(expected) {
            assert!((g - e).abs() < 1e-5, "{got:?} vs {expected:?}");
        }
    }

    #[test]
    fn clips_the_joint_gradient_norm() {
        let vs = nn::VarStore::new(Device::Cpu);
        let a = vs.root().var_copy("a", &Tensor::from_slice(&[0.0f32]));
        let b = vs.root().var_copy("b", &Tensor::from_slice(&[0.0f32]));
        let mut adam = Adam::new(&vs, 0.1);
        adam.zero_grad();
        (&a * 3.0 + &b * 4.0).sum(Kind::Float).backward();
        let norm = adam.clip_grad_norm(1.0);
        assert!((norm - 5.0).abs() < 1e-6);
        let (ga, gb) = (a.grad().double_value(&[0]), b.grad().double_value(&[0]));
        assert!((ga - 0.6).abs() < 1e-5 && (gb - 0.8).abs() < 1e-5);
    }
}

//! Multilayer perceptrons as rsl_rl builds them: linear layers with ELU between them and a linear
//! output, initialised the way PyTorch's `nn.Linear` is.
//!
//! tch's `nn::linear` defaults differ from PyTorch's: tch draws weights from Kaiming-uniform with
//! the ReLU gain (bound √6/√fan_in), whereas PyTorch's `nn.Linear.reset_parameters` uses
//! `kaiming_uniform_(a=√5)`, i.e. bound 1/√fan_in, for the weights and U(±1/√fan_in) for the
//! bias. The paper trains with rsl_rl on PyTorch, so we reproduce PyTorch's initialisation.

use tch::nn::{self, Module};
use tch::Tensor;

/// An MLP `in → hidden… → out` with ELU after every hidden layer and a linear output.
#[derive(Debug)]
pub struct Mlp {
    layers: Vec<nn::Linear>,
}

/// PyTorch's default initialisation of an `nn.Linear(fan_in, ·)`: U(±1/√fan_in) for both the
/// weight and the bias.
pub fn pytorch_linear_config(fan_in: i64) -> nn::LinearConfig {
    let bound = 1.0 / (fan_in as f64).sqrt();
    let init = nn::Init::Uniform {
        lo: -bound,
        up: bound,
    };
    nn::LinearConfig {
        ws_init: init,
        bs_init: Some(init),
        bias: true,
    }
}

impl Mlp {
    /// Creates the layers under `path` as `0.weight`, `0.bias`, `1.weight`, … in order.
    pub fn new(path: &nn::Path, input_dim: i64, hidden: &[i64], output_dim: i64) -> Self {
        let dims: Vec<i64> = std::iter::once(input_dim)
            .chain(hidden.iter().copied())
            .chain(std::iter::once(output_dim))
            .collect();
        let layers = dims
            .windows(2)
            .enumerate()
            .map(|(i, w)| nn::linear(path / i, w[0], w[1], pytorch_linear_config(w[0])))
            .collect();
        Mlp { layers }
    }

    /// The linear layers, input first.
    pub fn layers(&self) -> &[nn::Linear] {
        &self.layers
    }
}

impl Module for Mlp {
    /// ELU runs in place on each hidden layer's linear output (`elu_`): one activation-sized
    /// allocation less per layer, and autograd then differentiates ELU through its result
    /// (`grad · (y + α)` where `y < 0`) instead of recomputing `exp` of the input, which was a
    /// visible share of the backward pass. The linear layer (`addmm`) keeps its inputs, not its
    /// output, for backward, so overwriting the output is safe. Same values as `elu()` forward;
    /// the gradient equals rsl_rl's up to float rounding of `α·eˣ` versus `y + α`.
    fn forward(&self, xs: &Tensor) -> Tensor {
        let last = self.layers.len() - 1;
        self.layers
            .iter()
            .enumerate()
            .fold(xs.shallow_clone(), |x, (i, layer)| {
                let mut y = layer.forward(&x);
                if i < last {
                    let _ = y.elu_();
                }
                y
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn layer_shapes_and_pytorch_init_bounds() {
        tch::manual_seed(0);
        let vs = nn::VarStore::new(Device::Cpu);
        let mlp = Mlp::new(&vs.root(), 48, &[256, 128, 64], 18);
        let shapes: Vec<Vec<i64>> = mlp.layers().iter().map(|l| l.ws.size()).collect();
        assert_eq!(
            shapes,
            vec![vec![256, 48], vec![128, 256], vec![64, 128], vec![18, 64]]
        );
        for layer in mlp.layers() {
            let fan_in = layer.ws.size()[1] as f64;
            let bound = 1.0 / fan_in.sqrt();
            let w_max = layer.ws.abs().max().double_value(&[]);
            let b_max = layer.bs.as_ref().unwrap().abs().max().double_value(&[]);
            assert!(
                w_max <= bound && b_max <= bound,
                "init exceeds 1/sqrt(fan_in)"
            );
            // A uniform draw of thousands of values comes close to its bound; tch's default
            // Kaiming init (bound sqrt(6/fan_in)) would exceed it by 2.4x.
            assert!(w_max > 0.9 * bound);
        }
    }

    #[test]
    fn forward_matches_manual_elu_composition() {
        tch::manual_seed(1);
        let vs = nn::VarStore::new(Device::Cpu);
        let mlp = Mlp::new(&vs.root(), 3, &[5], 2);
        let x = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
        let l = mlp.layers();
        let h = x.matmul(&l[0].ws.tr()) + l[0].bs.as_ref().unwrap();
        let h = h.clamp_min(0.0) + (h.clamp_max(0.0).exp() - 1.0);
        let expected = h.matmul(&l[1].ws.tr()) + l[1].bs.as_ref().unwrap();
        let diff = (mlp.forward(&x) - expected).abs().max().double_value(&[]);
        assert!(diff < 1e-6, "max abs difference {diff}");
    }
}

//! The diagonal Gaussian action distribution, with the formulas of `torch.distributions.Normal`
//! summed over the action dimension (as rsl_rl's `GaussianDistribution` does).

use tch::{Kind, Tensor};

/// `ln √(2π)`.
const LN_SQRT_2PI: f64 = 0.918_938_533_204_672_7;

/// Log density of `x` under N(mean, std²), summed over the last dimension.
pub fn log_prob(x: &Tensor, mean: &Tensor, std: &Tensor) -> Tensor {
    let per_dim = -(x - mean).square() / (std.square() * 2.0) - std.log() - LN_SQRT_2PI;
    per_dim.sum_dim_intlist(-1, false, Kind::Float)
}

/// Entropy `½ + ln √(2π) + ln σ`, summed over the last dimension.
pub fn entropy(std: &Tensor) -> Tensor {
    (std.log() + 0.5 + LN_SQRT_2PI).sum_dim_intlist(-1, false, Kind::Float)
}

/// KL(old ‖ new), summed over the last dimension: what rsl_rl's adaptive schedule watches.
pub fn kl(old_mean: &Tensor, old_std: &Tensor, new_mean: &Tensor, new_std: &Tensor) -> Tensor {
    let var_ratio = (old_std / new_std).square();
    let t1 = ((old_mean - new_mean) / new_std).square();
    ((&var_ratio + t1 - 1.0 - var_ratio.log()) * 0.5).sum_dim_intlist(-1, false, Kind::Float)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: &[f32]) -> Tensor {
        Tensor::from_slice(v).view([1, v.len() as i64])
    }

    #[test]
    fn closed_forms_match_hand_values() {
        // N(0, 1) at 1: -1/2 - ln sqrt(2 pi); N(1, 2) at 1: -ln 2 - ln sqrt(2 pi).
        let lp = log_prob(&t(&[1.0, 1.0]), &t(&[0.0, 1.0]), &t(&[1.0, 2.0])).double_value(&[0]);
        let expected = -0.5 - 2.0f64.ln() - 2.0 * LN_SQRT_2PI;
        assert!((lp - expected).abs() < 1e-6, "{lp} vs {expected}");
        let h = entropy(&Tensor::from_slice(&[1.0f32, 2.0])).double_value(&[]);
        assert!((h - (1.0 + 2.0 * LN_SQRT_2PI + 2.0f64.ln())).abs() < 1e-6);
        // KL(N(0,1) || N(1,2)) = ln 2 + (1 + 1) / 8 - 1/2.
        let k = kl(&t(&[0.0]), &t(&[1.0]), &t(&[1.0]), &t(&[2.0])).double_value(&[0]);
        assert!((k - (2.0f64.ln() + 0.25 - 0.5)).abs() < 1e-6);
        let same = kl(&t(&[0.3]), &t(&[0.7]), &t(&[0.3]), &t(&[0.7])).double_value(&[0]);
        assert!(same.abs() < 1e-7);
    }
}

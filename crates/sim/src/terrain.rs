//! Randomized terrain heightfields (paper, Sec. VI-A): perturbations of peak-to-peak amplitude
//! ≤ 0.02 m with spatial correlation length in [0.05, 0.15] m.
//!
//! A field is white Gaussian noise on a regular grid smoothed by a separable Gaussian kernel of
//! standard deviation σ_k = ℓ/2. The autocorrelation of such a field is exp(−r²/(4σ_k²)), which
//! falls to 1/e at r = 2σ_k = ℓ: we call ℓ the correlation length. The smoothed field is then
//! shifted to a zero mean and scaled to the drawn peak-to-peak amplitude exactly. The
//! amplitude is drawn uniformly in [0, max] so training also sees near-flat ground.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Ranges of the terrain randomization.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainRandomization {
    /// Largest peak-to-peak height of the perturbation, m (paper: 0.02).
    pub max_peak_to_peak_m: f64,
    /// Range of the correlation length ℓ, m (paper: [0.05, 0.15]).
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub correlation_length_m: [f64; 2],
}

/// A square heightfield centred on the world origin; `heights_m[row * cols + col]`, rows along
/// +Y and columns along +X, `spacing_m` apart.
#[derive(Debug, Clone, PartialEq)]
pub struct Heightfield {
    pub rows: usize,
    pub cols: usize,
    pub spacing_m: f64,
    pub heights_m: Vec<f64>,
    /// The correlation length this field was generated with, m.
    pub correlation_length_m: f64,
}

impl Heightfield {
    /// Largest minus smallest height, m.
    pub fn peak_to_peak_m(&self) -> f64 {
        let (lo, hi) = self
            .heights_m
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &h| {
                (lo.min(h), hi.max(h))
            });
        hi - lo
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TerrainError {
    #[error("terrain: {field} = {value} is invalid: {reason}")]
    Invalid {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
}

impl TerrainRandomization {
    fn validate(&self, cells: usize, spacing_m: f64) -> Result<(), TerrainError> {
        let [lo, hi] = self.correlation_length_m;
        let invalid = |field, value, reason| {
            Err(TerrainError::Invalid {
                field,
                value,
                reason,
            })
        };
        if !(self.max_peak_to_peak_m.is_finite() && self.max_peak_to_peak_m >= 0.0) {
            return invalid(
                "max_peak_to_peak_m",
                self.max_peak_to_peak_m,
                "must be finite and >= 0",
            );
        }
        if !(lo.is_finite() && lo > 0.0 && hi.is_finite() && hi >= lo) {
            return invalid("correlation_length_m", lo, "needs 0 < low <= high");
        }
        if !(spacing_m.is_finite() && spacing_m > 0.0) {
            return invalid("spacing_m", spacing_m, "must be finite and > 0");
        }
        if cells < 2 {
            return invalid("cells", cells as f64, "needs at least 2 cells per side");
        }
        Ok(())
    }

    /// Draws one heightfield of `cells × cells` samples `spacing_m` apart.
    pub fn sample<R: Rng + ?Sized>(
        &self,
        cells: usize,
        spacing_m: f64,
        rng: &mut R,
    ) -> Result<Heightfield, TerrainError> {
        self.validate(cells, spacing_m)?;
        let [lo, hi] = self.correlation_length_m;
        let correlation_length_m = rng.random_range(lo..=hi);
        let peak_to_peak = rng.random_range(0.0..=self.max_peak_to_peak_m);
        let noise: Vec<f64> = (0..cells * cells)
            .map(|_| StandardNormal.sample(rng))
            .collect();
        let kernel = gaussian_kernel(correlation_length_m / 2.0 / spacing_m);
        let mut heights = blur_rows(&noise, cells, &kernel);
        heights = transpose(
            &blur_rows(&transpose(&heights, cells), cells, &kernel),
            cells,
        );
        let mean = heights.iter().sum::<f64>() / heights.len() as f64;
        let mut field = Heightfield {
            rows: cells,
            cols: cells,
            spacing_m,
            heights_m: heights.iter().map(|h| h - mean).collect(),
            correlation_length_m,
        };
        let current = field.peak_to_peak_m();
        let scale = if current > 0.0 {
            peak_to_peak / current
        } else {
            0.0
        };
        field.heights_m.iter_mut().for_each(|h| *h *= scale);
        Ok(field)
    }
}

/// Normalized Gaussian kernel with standard deviation `sigma_cells`, truncated at 3σ.
fn gaussian_kernel(sigma_cells: f64) -> Vec<f64> {
    let radius = (3.0 * sigma_cells).ceil() as isize;
    let weights: Vec<f64> = (-radius..=radius)
        .map(|i| (-(i as f64).powi(2) / (2.0 * sigma_cells * sigma_cells)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.into_iter().map(|w| w / total).collect()
}

/// Convolves every row with `kernel`, wrapping around the edges so the field's statistics are
/// the same everywhere.
fn blur_rows(values: &[f64], cols: usize, kernel: &[f64]) -> Vec<f64> {
    let radius = (kernel.len() / 2) as isize;
    let mut out = vec![0.0; values.len()];
    for (row_in, row_out) in values.chunks(cols).zip(out.chunks_mut(cols)) {
        for (c, o) in row_out.iter_mut().enumerate() {
            *o = kernel
                .iter()
                .enumerate()
                .map(|(k, w)| {
                    let src = (c as isize + k as isize - radius).rem_euclid(cols as isize);
                    w * row_in[src as usize]
                })
                .sum();
        }
    }
    out
}

fn transpose(values: &[f64], n: usize) -> Vec<f64> {
    (0..n * n).map(|i| values[(i % n) * n + i / n]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const PAPER: TerrainRandomization = TerrainRandomization {
        max_peak_to_peak_m: 0.02,
        correlation_length_m: [0.05, 0.15],
    };

    /// Empirical autocorrelation along rows at a lag of `lag` cells.
    fn autocorrelation(field: &Heightfield, lag: usize) -> f64 {
        let n = field.cols;
        let h = &field.heights_m;
        let var: f64 = h.iter().map(|x| x * x).sum::<f64>();
        let cov: f64 = (0..n * n)
            .map(|i| h[i] * h[(i / n) * n + (i % n + lag) % n])
            .sum();
        cov / var
    }

    #[test]
    fn amplitude_and_lengths_stay_in_the_papers_ranges() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..20 {
            let field = PAPER.sample(128, 0.01, &mut rng).unwrap();
            assert!(field.peak_to_peak_m() <= 0.02 + 1e-12);
            assert!((0.05..=0.15).contains(&field.correlation_length_m));
            let mean = field.heights_m.iter().sum::<f64>() / field.heights_m.len() as f64;
            assert!(mean.abs() < 1e-12);
        }
    }

    #[test]
    fn correlation_falls_to_one_over_e_at_the_correlation_length() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let fixed = TerrainRandomization {
            correlation_length_m: [0.10, 0.10],
            ..PAPER
        };
        // Average over fields: one 4 m × 4 m field holds only ~1600 correlation cells.
        let lag = 10; // 0.10 m at 0.01 m spacing
        let mean: f64 = (0..8)
            .map(|_| autocorrelation(&fixed.sample(400, 0.01, &mut rng).unwrap(), lag))
            .sum::<f64>()
            / 8.0;
        assert!(
            (mean - (-1.0f64).exp()).abs() < 0.05,
            "autocorrelation at l: {mean}"
        );
    }

    #[test]
    fn same_seed_same_field_and_bad_ranges_rejected() {
        let a = PAPER
            .sample(32, 0.01, &mut ChaCha8Rng::seed_from_u64(1))
            .unwrap();
        let b = PAPER
            .sample(32, 0.01, &mut ChaCha8Rng::seed_from_u64(1))
            .unwrap();
        assert_eq!(a, b);
        let bad = TerrainRandomization {
            correlation_length_m: [0.15, 0.05],
            ..PAPER
        };
        let err = bad
            .sample(32, 0.01, &mut ChaCha8Rng::seed_from_u64(1))
            .unwrap_err();
        assert!(err.to_string().contains("correlation_length_m"));
    }
}

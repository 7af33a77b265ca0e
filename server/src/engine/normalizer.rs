//! Normalizers on tensors: the map between a dataset's raw units and the normalized units
//! models work in.
//!
//! Per coordinate, along the last dimension for trajectories `[B, H, D]` (D = action_dim +
//! obs_dim, each row `[action | observation]`) and over all trailing elements for samples
//! `[B, *shape]`. The [`Normalizer`] itself (its kinds, lengths and checks) is the shared
//! schema's, part of every manifest; this file adds its arithmetic ([`Normalize`]).

use tch::{Kind, Tensor};

pub use relreward_proto::schema::manifest::Normalizer;

/// Ranges narrower than this are treated as constant coordinates: they normalize to 0 rather
/// than dividing by zero (a constant coordinate carries no information either way).
const MIN_RANGE: f64 = 1e-12;

/// (offset, scale) per coordinate such that x_norm = (x - offset) * scale.
fn affine(n: &Normalizer) -> Option<(Vec<f64>, Vec<f64>)> {
    match n {
        Normalizer::Identity => None,
        Normalizer::Limits { min, max } => {
            let offset = min.iter().zip(max).map(|(lo, hi)| (lo + hi) / 2.0).collect();
            let scale =
                min.iter().zip(max).map(|(lo, hi)| if hi - lo > MIN_RANGE { 2.0 / (hi - lo) } else { 0.0 }).collect();
            Some((offset, scale))
        }
        Normalizer::Gaussian { mean, std } => {
            Some((mean.clone(), std.iter().map(|&s| if s > MIN_RANGE { 1.0 / s } else { 0.0 }).collect()))
        }
    }
}

/// Per-coordinate tensors shaped to broadcast against `x` (coordinates = trailing elements of
/// one item; `item_dims` is the number of dimensions after the batch dimension that the
/// coordinates span: 1 for trajectories' last dim, all for samples).
fn broadcast(v: &[f64], x: &Tensor, item_dims: usize) -> Tensor {
    let size = x.size();
    let keep = size.len().saturating_sub(item_dims);
    let mut shape: Vec<i64> = vec![1; keep];
    shape.extend_from_slice(&size[keep..]);
    super::upload(&Tensor::from_slice(v).to_kind(Kind::Float), x.device()).expect("a float32 upload").reshape(&shape)
}

/// A normalizer's arithmetic, on tensors and on host floats.
pub trait Normalize {
    /// Raw → normalized. Differentiable (so gradients can be chained through it).
    fn normalize(&self, x: &Tensor, item_dims: usize) -> Tensor;
    /// Raw → normalized on host float32 values, in place, without a tensor (per-request work
    /// that stays off libtorch). `values` holds whole items row-major, so element k is
    /// coordinate k mod the coordinate count. The same float32 arithmetic as
    /// [`Normalize::normalize`] ((x - offset) * scale, each step rounded to float32), so the
    /// same numbers.
    fn normalize_values(&self, values: &mut [f32]);
    /// Normalized → raw. Constant coordinates come back as their constant.
    fn unnormalize(&self, x: &Tensor, item_dims: usize) -> Tensor;
    /// d x_norm / d x_raw per coordinate, broadcast against `x`: a gradient with respect to
    /// normalized inputs times this is the gradient with respect to raw inputs.
    fn jacobian(&self, x: &Tensor, item_dims: usize) -> Tensor;
}

impl Normalize for Normalizer {
    fn normalize(&self, x: &Tensor, item_dims: usize) -> Tensor {
        match affine(self) {
            None => x.shallow_clone(),
            Some((offset, scale)) => (x - broadcast(&offset, x, item_dims)) * broadcast(&scale, x, item_dims),
        }
    }

    fn normalize_values(&self, values: &mut [f32]) {
        let Some((offset, scale)) = affine(self) else { return };
        let offset: Vec<f32> = offset.iter().map(|&o| o as f32).collect();
        let scale: Vec<f32> = scale.iter().map(|&s| s as f32).collect();
        for item in values.chunks_mut(offset.len().max(1)) {
            for ((v, o), s) in item.iter_mut().zip(&offset).zip(&scale) {
                *v = (*v - o) * s;
            }
        }
    }

    fn unnormalize(&self, x: &Tensor, item_dims: usize) -> Tensor {
        match affine(self) {
            None => x.shallow_clone(),
            Some((offset, scale)) => {
                let inv: Vec<f64> = scale.iter().map(|&s| if s > 0.0 { 1.0 / s } else { 0.0 }).collect();
                x * broadcast(&inv, x, item_dims) + broadcast(&offset, x, item_dims)
            }
        }
    }

    fn jacobian(&self, x: &Tensor, item_dims: usize) -> Tensor {
        match affine(self) {
            None => Tensor::ones([1], (Kind::Float, x.device())),
            Some((_, scale)) => broadcast(&scale, x, item_dims),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: &[f32], shape: &[i64]) -> Tensor {
        Tensor::from_slice(v).reshape(shape)
    }

    fn close(a: &Tensor, b: &Tensor) -> bool {
        a.allclose(b, 1e-6, 1e-6, false)
    }

    #[test]
    fn limits_map_min_max_to_minus_one_one_and_back() {
        let n = Normalizer::Limits { min: vec![0.0, -2.0], max: vec![10.0, 2.0] };
        let x = t(&[0.0, -2.0, 10.0, 2.0, 5.0, 0.0], &[1, 3, 2]);
        let y = n.normalize(&x, 1);
        assert!(close(&y, &t(&[-1.0, -1.0, 1.0, 1.0, 0.0, 0.0], &[1, 3, 2])));
        assert!(close(&n.unnormalize(&y, 1), &x));
    }

    #[test]
    fn gaussian_and_constant_coordinates() {
        let n = Normalizer::Gaussian { mean: vec![1.0, 3.0], std: vec![2.0, 0.0] };
        let x = t(&[5.0, 3.0], &[1, 2]);
        let y = n.normalize(&x, 1);
        assert!(close(&y, &t(&[2.0, 0.0], &[1, 2])));
        assert!(close(&n.unnormalize(&y, 1), &x), "constant coordinate restored");
    }

    #[test]
    fn jacobian_matches_autograd() {
        let n = Normalizer::Limits { min: vec![1.0, 0.0, -4.0], max: vec![3.0, 10.0, 4.0] };
        let x = t(&[1.5, 2.0, 0.3, 2.5, 7.0, -1.0], &[2, 3]).set_requires_grad(true);
        let y = n.normalize(&x, 1);
        let w = t(&[1.0, -2.0, 0.5, 3.0, 1.0, -1.0], &[2, 3]);
        let g = Tensor::run_backward(&[(&y * &w).sum(Kind::Float)], &[&x], false, false);
        assert!(close(&g[0], &(&w * n.jacobian(&x, 1))));
    }

    #[test]
    fn host_values_normalize_to_the_tensor_path_bit_for_bit() {
        let x: Vec<f32> = (0..24).map(|i| (i as f32 * 0.731).sin() * 7.0 + 0.1).collect();
        for (n, item_dims) in [
            (Normalizer::Limits { min: vec![-3.3, 0.0, 1e-13], max: vec![9.1, 1.0, 1e-13] }, 1),
            (Normalizer::Gaussian { mean: (0..6).map(|i| i as f64 * 0.37).collect(), std: vec![0.3; 6] }, 2),
        ] {
            let shape: &[i64] = if item_dims == 1 { &[2, 4, 3] } else { &[4, 2, 3] };
            let want = Vec::<f32>::try_from(&n.normalize(&t(&x, shape), item_dims).view(-1)).expect("f32");
            let mut got = x.clone();
            n.normalize_values(&mut got);
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
        }
        let mut same = x.clone();
        Normalizer::Identity.normalize_values(&mut same);
        assert_eq!(same, x);
    }

    #[test]
    fn samples_normalize_over_all_trailing_elements() {
        let n = Normalizer::Gaussian { mean: vec![0.0, 1.0, 2.0, 3.0], std: vec![1.0; 4] };
        let x = t(&[0.0, 1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 4.0], &[2, 2, 2]);
        let y = n.normalize(&x, 2);
        assert!(close(&y, &t(&[0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0], &[2, 2, 2])));
    }
}

//! DDPM beta schedules and every quantity derived from them.
//!
//! Everything is computed once, in float64, when a model is loaded: the sampling and training
//! loops only index tables. Each table is kept twice: as `Vec<f64>` (exact values, for scalar
//! use and for tests against PyTorch) and as a float32 tensor `[T]` that [`Schedule::extract`]
//! gathers per batch element.
//!
//! Time index convention (Diffuser's): `t` runs over `0..T`; `t = T - 1` is the noisiest step
//! and `t = 0` the last denoising step. `alphas_cumprod[t]` is abar_t = prod_{s <= t} alpha_s
//! and `alphas_cumprod_prev[t]` is abar_{t-1}, with abar_{-1} = 1.
//!
//! Cosine schedules: the Nichol & Dhariwal form evaluates abar at x / T for x = 0..T. Diffuser's
//! `cosine_beta_schedule` evaluates it at `linspace(0, T + 1, T + 1) / (T + 1)`, which is the
//! same grid i / T written differently, so the two agree up to float64 rounding (~1e-16). They
//! are kept as separate kinds so a manifest names the exact code path its model was trained
//! with, and each is computed the way its source writes it.

use std::sync::Mutex;

use tch::{Device, Kind, Tensor};

use super::manifest::{MAX_TIMESTEPS, ScheduleSpec};
use crate::error::{Error, Result};

/// Upper clip on betas for the cosine schedules: the last raw cosine beta is ~1 (abar(T) is
/// ~0) and would make every later quantity blow up.
const MAX_COSINE_BETA: f64 = 0.999;

/// Floor on the posterior variance before its logarithm: it is exactly 0 at t = 0.
const MIN_POSTERIOR_VARIANCE: f64 = 1e-20;

/// One per-timestep table of a [`Schedule`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Table {
    /// beta_t.
    Betas,
    /// alpha_t = 1 - beta_t.
    Alphas,
    /// abar_t = prod_{s <= t} alpha_s.
    AlphasCumprod,
    /// abar_{t-1}, with abar_{-1} = 1.
    AlphasCumprodPrev,
    /// sqrt(abar_t).
    SqrtAlphasCumprod,
    /// sqrt(1 - abar_t).
    SqrtOneMinusAlphasCumprod,
    /// sqrt(1 / abar_t).
    SqrtRecipAlphasCumprod,
    /// sqrt(1 / abar_t - 1).
    SqrtRecipm1AlphasCumprod,
    /// beta_t (1 - abar_{t-1}) / (1 - abar_t): variance of q(x_{t-1} | x_t, x0).
    PosteriorVariance,
    /// log(max(posterior variance, 1e-20)).
    PosteriorLogVarianceClipped,
    /// beta_t sqrt(abar_{t-1}) / (1 - abar_t): weight of x0 in the posterior mean.
    PosteriorMeanCoef1,
    /// (1 - abar_{t-1}) sqrt(alpha_t) / (1 - abar_t): weight of x_t in the posterior mean.
    PosteriorMeanCoef2,
}

impl Table {
    pub const ALL: [Table; 12] = [
        Table::Betas,
        Table::Alphas,
        Table::AlphasCumprod,
        Table::AlphasCumprodPrev,
        Table::SqrtAlphasCumprod,
        Table::SqrtOneMinusAlphasCumprod,
        Table::SqrtRecipAlphasCumprod,
        Table::SqrtRecipm1AlphasCumprod,
        Table::PosteriorVariance,
        Table::PosteriorLogVarianceClipped,
        Table::PosteriorMeanCoef1,
        Table::PosteriorMeanCoef2,
    ];

    /// The snake_case name Diffuser gives the buffer (also the key in the PyTorch cross-check).
    pub fn name(self) -> &'static str {
        match self {
            Table::Betas => "betas",
            Table::Alphas => "alphas",
            Table::AlphasCumprod => "alphas_cumprod",
            Table::AlphasCumprodPrev => "alphas_cumprod_prev",
            Table::SqrtAlphasCumprod => "sqrt_alphas_cumprod",
            Table::SqrtOneMinusAlphasCumprod => "sqrt_one_minus_alphas_cumprod",
            Table::SqrtRecipAlphasCumprod => "sqrt_recip_alphas_cumprod",
            Table::SqrtRecipm1AlphasCumprod => "sqrt_recipm1_alphas_cumprod",
            Table::PosteriorVariance => "posterior_variance",
            Table::PosteriorLogVarianceClipped => "posterior_log_variance_clipped",
            Table::PosteriorMeanCoef1 => "posterior_mean_coef1",
            Table::PosteriorMeanCoef2 => "posterior_mean_coef2",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// A DDPM noise schedule with all derived tables (see the module doc for conventions).
#[derive(Debug)]
pub struct Schedule {
    n_timesteps: usize,
    values: Vec<Vec<f64>>,
    /// float32 `[T]` on the CPU, in [`Table::ALL`] order.
    tensors: Vec<Tensor>,
    /// The same tables on the last accelerator asked for, copied there once: gathering from
    /// the CPU tables for a `t` on a GPU would upload a table at every coefficient.
    on_device: Mutex<Option<(Device, Vec<Tensor>)>>,
}

impl Clone for Schedule {
    fn clone(&self) -> Self {
        // Tables are never written after construction, so sharing storage is safe.
        Self {
            n_timesteps: self.n_timesteps,
            values: self.values.clone(),
            tensors: self.tensors.iter().map(Tensor::shallow_clone).collect(),
            on_device: Mutex::new(None),
        }
    }
}

impl Schedule {
    /// Builds the betas of `spec` for `n_timesteps` steps and derives every table.
    ///
    /// Fails with `InvalidArgument` when T is out of range, explicit betas do not number T, or
    /// the schedule produces a beta outside (0, 1) (e.g. the linear schedule for T <= 20, whose
    /// betas scaled by 1000 / T reach 1).
    pub fn new(spec: &ScheduleSpec, n_timesteps: usize) -> Result<Self> {
        let t = n_timesteps;
        if t == 0 || t > MAX_TIMESTEPS {
            return Err(Error::invalid(format!("schedule: n_timesteps {t} is outside 1..={MAX_TIMESTEPS}")));
        }
        let betas = match spec {
            ScheduleSpec::Linear => {
                let scale = 1000.0 / t as f64;
                linspace(1e-4 * scale, 0.02 * scale, t)
            }
            ScheduleSpec::Cosine { s } => {
                check_cosine_s(*s)?;
                let abar: Vec<f64> = (0..=t).map(|x| cosine_abar(x as f64 / t as f64, *s)).collect();
                let abar: Vec<f64> = abar.iter().map(|a| a / abar[0]).collect();
                abar.windows(2).map(|w| (1.0 - w[1] / w[0]).min(MAX_COSINE_BETA)).collect()
            }
            ScheduleSpec::DiffuserCosine { s } => {
                check_cosine_s(*s)?;
                let steps = t + 1;
                let x = linspace(0.0, steps as f64, steps);
                let abar: Vec<f64> = x.iter().map(|&x| cosine_abar(x / steps as f64, *s)).collect();
                let abar: Vec<f64> = abar.iter().map(|a| a / abar[0]).collect();
                abar.windows(2).map(|w| (1.0 - w[1] / w[0]).clamp(0.0, MAX_COSINE_BETA)).collect()
            }
            ScheduleSpec::Betas { betas } => {
                if betas.len() != t {
                    return Err(Error::invalid(format!(
                        "schedule.betas: {} values but n_timesteps is {t}",
                        betas.len()
                    )));
                }
                betas.clone()
            }
        };
        Self::from_betas(betas)
    }

    /// Derives every table from explicit betas, each in (0, 1).
    pub fn from_betas(betas: Vec<f64>) -> Result<Self> {
        let t = betas.len();
        if t == 0 || t > MAX_TIMESTEPS {
            return Err(Error::invalid(format!("schedule: {t} betas, expected 1..={MAX_TIMESTEPS}")));
        }
        if let Some(i) = betas.iter().position(|b| !(b.is_finite() && *b > 0.0 && *b < 1.0)) {
            return Err(Error::invalid(format!(
                "schedule: beta[{i}] = {} is not in (0, 1) (T = {t}; the linear schedule needs T > 20)",
                crate::fields::number(betas[i])
            )));
        }
        let alphas: Vec<f64> = betas.iter().map(|b| 1.0 - b).collect();
        let abar: Vec<f64> = alphas
            .iter()
            .scan(1.0, |acc, a| {
                *acc *= a;
                Some(*acc)
            })
            .collect();
        let abar_prev: Vec<f64> = std::iter::once(1.0).chain(abar[..t - 1].iter().copied()).collect();
        let map = |f: &dyn Fn(usize) -> f64| -> Vec<f64> { (0..t).map(f).collect() };
        let posterior_variance = map(&|i| betas[i] * (1.0 - abar_prev[i]) / (1.0 - abar[i]));
        let mut values = vec![Vec::new(); Table::ALL.len()];
        values[Table::SqrtAlphasCumprod.index()] = map(&|i| abar[i].sqrt());
        values[Table::SqrtOneMinusAlphasCumprod.index()] = map(&|i| (1.0 - abar[i]).sqrt());
        values[Table::SqrtRecipAlphasCumprod.index()] = map(&|i| (1.0 / abar[i]).sqrt());
        values[Table::SqrtRecipm1AlphasCumprod.index()] = map(&|i| (1.0 / abar[i] - 1.0).sqrt());
        values[Table::PosteriorLogVarianceClipped.index()] =
            posterior_variance.iter().map(|v| v.max(MIN_POSTERIOR_VARIANCE).ln()).collect();
        values[Table::PosteriorMeanCoef1.index()] = map(&|i| betas[i] * abar_prev[i].sqrt() / (1.0 - abar[i]));
        values[Table::PosteriorMeanCoef2.index()] = map(&|i| (1.0 - abar_prev[i]) * alphas[i].sqrt() / (1.0 - abar[i]));
        values[Table::PosteriorVariance.index()] = posterior_variance;
        values[Table::Betas.index()] = betas;
        values[Table::Alphas.index()] = alphas;
        values[Table::AlphasCumprod.index()] = abar;
        values[Table::AlphasCumprodPrev.index()] = abar_prev;

        // abar can underflow to 0 for long schedules with large betas; then 1 / abar is
        // infinite and sampling would produce NaN. Refuse such a schedule up front.
        for table in Table::ALL {
            let v = &values[table.index()];
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(Error::invalid(format!(
                    "schedule: {}[{i}] is {} (abar_t underflows; betas too large for T = {t})",
                    table.name(),
                    v[i]
                )));
            }
        }
        if let Some(i) = values[Table::AlphasCumprod.index()].iter().position(|a| *a <= 0.0) {
            return Err(Error::invalid(format!("schedule: alphas_cumprod[{i}] underflows to 0 (T = {t})")));
        }

        let tensors = values
            .iter()
            .map(|v| {
                let f: Vec<f32> = v.iter().map(|&x| x as f32).collect();
                Tensor::f_from_slice(&f)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { n_timesteps: t, values, tensors, on_device: Mutex::new(None) })
    }

    /// T, the number of diffusion steps.
    pub fn n_timesteps(&self) -> usize {
        self.n_timesteps
    }

    /// The exact float64 values of a table, indexed by t in `0..T`.
    pub fn values(&self, table: Table) -> &[f64] {
        &self.values[table.index()]
    }

    /// One float64 value; `None` when `t >= T`.
    pub fn get(&self, table: Table, t: usize) -> Option<f64> {
        self.values[table.index()].get(t).copied()
    }

    /// The float32 CPU tensor `[T]` of a table.
    pub fn tensor(&self, table: Table) -> &Tensor {
        &self.tensors[table.index()]
    }

    /// Checks that `t` is an int64 vector (of length `batch` when given) with values in
    /// `0..T`.
    pub fn check_t(&self, t: &Tensor, batch: Option<i64>) -> Result<()> {
        let size = t.size();
        let kind = t.f_kind()?;
        if size.len() != 1 || kind != Kind::Int64 {
            return Err(Error::invalid(format!("t: expected an int64 tensor [B], got {kind:?} {size:?}")));
        }
        if let Some(b) = batch
            && size[0] != b
        {
            return Err(Error::invalid(format!("t: expected shape [{b}] (one step per batch element), got {size:?}")));
        }
        if size[0] > 0 {
            // One read of [min, max] from the device (each read waits for its queue).
            let (lo, hi) = t.f_aminmax(None::<i64>, false)?;
            let bounds = Tensor::f_stack(&[lo, hi], 0)?.f_to_device(Device::Cpu)?;
            let (lo, hi) = (bounds.f_int64_value(&[0])?, bounds.f_int64_value(&[1])?);
            if lo < 0 || hi >= self.n_timesteps as i64 {
                return Err(Error::invalid(format!(
                    "t: values must lie in 0..{} (T = {}), got min {lo}, max {hi}",
                    self.n_timesteps, self.n_timesteps
                )));
            }
        }
        Ok(())
    }

    /// Gathers `table[t[b]]` for each batch element and shapes it `[B, 1, ..., 1]` (`x_ndim`
    /// dimensions in all) to broadcast against an `x` of that rank. float32, on `t`'s device.
    pub fn extract(&self, table: Table, t: &Tensor, x_ndim: usize) -> Result<Tensor> {
        self.check_t(t, None)?;
        if x_ndim == 0 {
            return Err(Error::invalid("extract: x must have a batch dimension (x_ndim >= 1)"));
        }
        let mut shape = vec![1i64; x_ndim];
        shape[0] = t.size()[0];
        let device = t.device();
        let out = if device == Device::Cpu {
            self.tensor(table).f_index_select(0, t)?
        } else {
            let mut cached = self.on_device.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            let tables = match &mut *cached {
                Some((d, tables)) if *d == device => tables,
                slot => {
                    let tables =
                        self.tensors.iter().map(|x| super::upload(x, device)).collect::<tch::Result<Vec<_>>>()?;
                    &mut slot.insert((device, tables)).1
                }
            };
            tables[table.index()].f_index_select(0, t)?
        };
        Ok(out.f_reshape(&shape)?)
    }
}

fn check_cosine_s(s: f64) -> Result<()> {
    if s.is_finite() && (0.0..1.0).contains(&s) {
        Ok(())
    } else {
        Err(Error::invalid(format!("schedule.s: {} is not in [0, 1)", crate::fields::number(s))))
    }
}

/// Unnormalized cosine abar at fraction `u` of the way through the process.
fn cosine_abar(u: f64, s: f64) -> f64 {
    ((u + s) / (1.0 + s) * std::f64::consts::FRAC_PI_2).cos().powi(2)
}

/// `n` evenly spaced values from `start` to `stop` inclusive, computed as numpy's linspace
/// does (start + i * step, the last value set to `stop` exactly).
fn linspace(start: f64, stop: f64, n: usize) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![start],
        _ => {
            let step = (stop - start) / (n - 1) as f64;
            let mut v: Vec<f64> = (0..n).map(|i| start + i as f64 * step).collect();
            v[n - 1] = stop;
            v
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * (1.0 + b.abs())
    }

    #[test]
    fn linear_endpoints_scale_with_t() {
        let s = Schedule::new(&ScheduleSpec::Linear, 1000).expect("linear 1000");
        let b = s.values(Table::Betas);
        assert!(close(b[0], 1e-4) && close(b[999], 0.02), "{} {}", b[0], b[999]);
        let s = Schedule::new(&ScheduleSpec::Linear, 100).expect("linear 100");
        assert!(close(s.values(Table::Betas)[0], 1e-3) && close(s.values(Table::Betas)[99], 0.2));
        let err = Schedule::new(&ScheduleSpec::Linear, 20).expect_err("beta 1.0").to_string();
        assert!(err.contains("beta[19] = 1") && err.contains("T > 20"), "{err}");
    }

    #[test]
    fn cosine_kinds_agree_and_clip_the_last_beta() {
        for t in [1, 20, 100] {
            let a = Schedule::new(&ScheduleSpec::Cosine { s: 0.008 }, t).expect("cosine");
            let b = Schedule::new(&ScheduleSpec::DiffuserCosine { s: 0.008 }, t).expect("diffuser");
            for table in Table::ALL {
                for (x, y) in a.values(table).iter().zip(b.values(table)) {
                    assert!((x - y).abs() <= 1e-9 * (1.0 + y.abs()), "{} T={t}: {x} vs {y}", table.name());
                }
            }
            assert_eq!(a.values(Table::Betas)[t - 1], MAX_COSINE_BETA);
        }
    }

    #[test]
    fn derived_identities_hold() {
        let s = Schedule::new(&ScheduleSpec::Cosine { s: 0.008 }, 50).expect("cosine");
        let v = |table| s.values(table);
        for t in 0..50 {
            let abar = v(Table::AlphasCumprod)[t];
            let prev = if t == 0 { 1.0 } else { v(Table::AlphasCumprod)[t - 1] };
            assert!(close(v(Table::AlphasCumprodPrev)[t], prev));
            assert!(close(abar, prev * v(Table::Alphas)[t]));
            // With zero noise (x_t = sqrt(abar_t) x0) the posterior mean is sqrt(abar_{t-1}) x0.
            let m = v(Table::PosteriorMeanCoef1)[t] + v(Table::PosteriorMeanCoef2)[t] * abar.sqrt();
            assert!(close(m, prev.sqrt()), "t={t}: {m} vs {}", prev.sqrt());
        }
        assert_eq!(v(Table::PosteriorVariance)[0], 0.0);
        assert!(close(v(Table::PosteriorLogVarianceClipped)[0], (1e-20f64).ln()));
    }

    #[test]
    fn explicit_betas_are_checked() {
        let ok = Schedule::new(&ScheduleSpec::Betas { betas: vec![0.1, 0.2, 0.3] }, 3).expect("betas");
        assert!(close(ok.values(Table::AlphasCumprod)[2], 0.9 * 0.8 * 0.7));
        let err = Schedule::new(&ScheduleSpec::Betas { betas: vec![0.1, 0.2] }, 3).expect_err("count").to_string();
        assert!(err.contains("2 values but n_timesteps is 3"), "{err}");
        let err = Schedule::new(&ScheduleSpec::Betas { betas: vec![0.1, 1.0] }, 2).expect_err("range").to_string();
        assert!(err.contains("beta[1]"), "{err}");
        let err = Schedule::from_betas(vec![0.999; 20_000]).expect_err("underflow").to_string();
        assert!(err.contains("underflow"), "{err}");
        assert!(Schedule::new(&ScheduleSpec::Cosine { s: 1.5 }, 3).is_err());
        assert!(Schedule::new(&ScheduleSpec::Linear, 0).is_err());
    }

    #[test]
    fn extract_gathers_and_broadcasts() {
        let s = Schedule::new(&ScheduleSpec::Linear, 100).expect("linear");
        let t = Tensor::from_slice(&[0i64, 99, 5]);
        let e = s.extract(Table::Betas, &t, 4).expect("extract");
        assert_eq!(e.size(), vec![3, 1, 1, 1]);
        assert_eq!(e.kind(), Kind::Float);
        for (i, &ti) in [0usize, 99, 5].iter().enumerate() {
            let got = e.double_value(&[i as i64, 0, 0, 0]);
            assert!((got - s.values(Table::Betas)[ti]).abs() < 1e-8);
        }
        let bad = s.extract(Table::Betas, &Tensor::from_slice(&[100i64]), 2).expect_err("range").to_string();
        assert!(bad.contains("0..100") && bad.contains("max 100"), "{bad}");
        let bad = s.extract(Table::Betas, &Tensor::from_slice(&[1.0f32]), 2).expect_err("kind").to_string();
        assert!(bad.contains("int64"), "{bad}");
        let bad = s.check_t(&Tensor::from_slice(&[1i64, 2]), Some(3)).expect_err("len").to_string();
        assert!(bad.contains("expected shape [3]"), "{bad}");
    }
}

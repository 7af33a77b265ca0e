//! DDIM (Song, Meng & Ermon 2021, eq. 12 and 16) with diffusers' `DDIMScheduler` conventions,
//! so that a model imported from diffusers samples here as it does there (checked to 1e-5 per
//! step by client/python/tests/test_ddim.py).
//!
//! - [`Ddim`]: the options (steps, eta, timestep spacing, final alpha) and their checks.
//! - [`Ddim::timesteps`]: the step subset, as diffusers' `set_timesteps` spaces it.
//! - [`Ddim::prev`] and [`coefs`]: where one step lands and its coefficients.
//!
//! One step from x_t at diffusion index t (0-based, as relreward and diffusers index their
//! tables), with a = abar_t and a' = abar_prev:
//!
//! ```text
//! x0 = the net's x0 estimate (clamped to [-1, 1] with the manifest's clip_denoised)
//! eps = the net's eps estimate (never clamped: diffusers' use_clipped_model_output false)
//! sigma = eta sqrt((1 - a') / (1 - a) (1 - a / a'))
//! x_prev = sqrt(a') x0 + sqrt(1 - a' - sigma^2) eps + sigma z
//! ```
//!
//! Two diffusers conventions are kept on purpose, although they surprise: the step from t
//! lands on prev = t - floor(T / n) whatever the spacing (for "trailing" and "linspace" with
//! T not divisible by n that is not the next timestep of the subset), and a step with
//! prev < 0 uses a' = 1 (`set_alpha_to_one`, the default) or abar_0. Refusing these would make
//! an imported model sample differently here than in diffusers, which is what this module is
//! for. diffusers' `steps_offset` (0 here) and thresholding are not offered.

use crate::error::{Error, Result};

/// How the step subset is spaced over 0..T (diffusers' `timestep_spacing`; Lin et al. 2023,
/// table 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Spacing {
    /// t = k floor(T / n), k = n-1 .. 0 (diffusers' DDIMScheduler default).
    Leading,
    /// t = round(T - k T / n) - 1, k = 0 .. n-1: starts at T - 1.
    Trailing,
    /// t = round(linspace(0, T - 1, n)), reversed (ties to even, as numpy rounds).
    Linspace,
}

impl Spacing {
    pub fn name(self) -> &'static str {
        match self {
            Self::Leading => "leading",
            Self::Trailing => "trailing",
            Self::Linspace => "linspace",
        }
    }
}

/// DDIM options of one sampling run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ddim {
    /// Denoising steps n, 1..=T.
    pub n_steps: usize,
    /// 0: deterministic DDIM; 1: the DDPM-like posterior variance on the subset.
    pub eta: f64,
    pub spacing: Spacing,
    /// abar used by a step that lands before 0: 1 (true, diffusers' default) or abar_0.
    pub set_alpha_to_one: bool,
}

/// Coefficients of one step: x_prev = x0_coef x0 + eps_coef eps + sigma z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefs {
    pub x0_coef: f64,
    pub eps_coef: f64,
    pub sigma: f64,
}

/// The coefficients of a step from abar_t = `a` to abar_prev = `a_prev` with `eta`.
pub fn coefs(a: f64, a_prev: f64, eta: f64) -> Coefs {
    let variance = (1.0 - a_prev) / (1.0 - a) * (1.0 - a / a_prev);
    let sigma = eta * variance.max(0.0).sqrt();
    // Non-negative for eta <= 1 (sigma^2 <= 1 - a'); max(0) only absorbs rounding.
    let eps_coef = (1.0 - a_prev - sigma * sigma).max(0.0).sqrt();
    Coefs { x0_coef: a_prev.sqrt(), eps_coef, sigma }
}

impl Ddim {
    /// Checks the options against a model with `big_t` diffusion steps; errors name the field
    /// under `field` (e.g. "ddim").
    pub fn check(&self, big_t: usize, field: &str) -> Result<()> {
        if self.n_steps == 0 || self.n_steps > big_t {
            return Err(Error::invalid(format!(
                "{field}.n_steps: {} must be in 1..={big_t} (the model's T: DDIM takes a subset of its steps)",
                self.n_steps
            )));
        }
        if !(self.eta.is_finite() && (0.0..=1.0).contains(&self.eta)) {
            return Err(Error::invalid(format!(
                "{field}.eta: {} must be in [0, 1] (0 deterministic DDIM, 1 the posterior's variance; above 1 \
                 sqrt(1 - abar_prev - sigma^2) is not real)",
                self.eta
            )));
        }
        Ok(())
    }

    /// The step subset, first (noisiest) first, as diffusers' `DDIMScheduler.set_timesteps`.
    pub fn timesteps(&self, big_t: usize) -> Vec<usize> {
        let n = self.n_steps.max(1);
        match self.spacing {
            Spacing::Leading => {
                let ratio = big_t / n;
                (0..n).rev().map(|k| k * ratio).collect()
            }
            Spacing::Trailing => {
                let ratio = big_t as f64 / n as f64;
                // numpy's arange(T, 0, -ratio): ceil((0 - T) / -ratio) values T + k (-ratio).
                let count = ((0.0 - big_t as f64) / -ratio).ceil() as usize;
                (0..count)
                    .map(|k| big_t as f64 + k as f64 * -ratio)
                    .map(|v| (v.round_ties_even() as usize).saturating_sub(1))
                    .collect()
            }
            Spacing::Linspace => {
                let last = (big_t - 1) as f64;
                let at = |k: usize| if n == 1 { 0.0 } else { last * k as f64 / (n - 1) as f64 };
                (0..n).rev().map(|k| at(k).round_ties_even() as usize).collect()
            }
        }
    }

    /// Where the step from `t` lands: t - floor(T / n), `None` below 0 (then the final alpha).
    pub fn prev(&self, t: usize, big_t: usize) -> Option<usize> {
        t.checked_sub(big_t / self.n_steps.max(1))
    }

    /// abar at the landing point of the step from `t`, given the model's abar table.
    pub fn abar_prev(&self, t: usize, abar: &[f64]) -> f64 {
        match self.prev(t, abar.len()) {
            Some(p) => abar[p],
            None if self.set_alpha_to_one => 1.0,
            None => abar[0],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ddim(n_steps: usize, spacing: Spacing) -> Ddim {
        Ddim { n_steps, eta: 0.0, spacing, set_alpha_to_one: true }
    }

    #[test]
    fn timesteps_follow_diffusers_spacings() {
        // Values from diffusers' set_timesteps formulas worked by hand.
        assert_eq!(ddim(5, Spacing::Leading).timesteps(20), vec![16, 12, 8, 4, 0]);
        assert_eq!(ddim(3, Spacing::Leading).timesteps(20), vec![12, 6, 0]);
        // arange(20, 0, -6.667) = 20, 13.33, 6.67 -> 20, 13, 7, minus 1.
        assert_eq!(ddim(3, Spacing::Trailing).timesteps(20), vec![19, 12, 6]);
        assert_eq!(ddim(5, Spacing::Trailing).timesteps(20), vec![19, 15, 11, 7, 3]);
        // linspace(0, 19, 3) = 0, 9.5, 19: 9.5 rounds to even (10).
        assert_eq!(ddim(3, Spacing::Linspace).timesteps(20), vec![19, 10, 0]);
        assert_eq!(ddim(4, Spacing::Linspace).timesteps(20), vec![19, 13, 6, 0]);
        assert_eq!(ddim(1, Spacing::Linspace).timesteps(20), vec![0]);
        assert_eq!(ddim(20, Spacing::Leading).timesteps(20), (0..20).rev().collect::<Vec<_>>());
        assert_eq!(ddim(20, Spacing::Trailing).timesteps(20), (0..20).rev().collect::<Vec<_>>());
        // prev = t - floor(T / n), whatever the spacing.
        let d = ddim(3, Spacing::Trailing);
        assert_eq!((d.prev(19, 20), d.prev(12, 20), d.prev(6, 20), d.prev(5, 20)), (Some(13), Some(6), Some(0), None));
    }

    #[test]
    fn coefficients_match_a_hand_computation() {
        // a = 0.5, a' = 0.8: variance = (0.2 / 0.5) (1 - 0.625) = 0.15.
        let c = coefs(0.5, 0.8, 0.0);
        assert!((c.x0_coef - 0.8f64.sqrt()).abs() < 1e-15);
        assert!((c.eps_coef - 0.2f64.sqrt()).abs() < 1e-15);
        assert_eq!(c.sigma, 0.0);
        let c = coefs(0.5, 0.8, 0.5);
        assert!((c.sigma - 0.5 * 0.15f64.sqrt()).abs() < 1e-15);
        assert!((c.eps_coef - (0.2f64 - 0.25 * 0.15).sqrt()).abs() < 1e-15);
        // eta = 1 on consecutive steps is DDPM's posterior variance beta_t (1 - a') / (1 - a).
        let (a_prev, beta) = (0.9f64, 0.1f64);
        let a = a_prev * (1.0 - beta);
        let c = coefs(a, a_prev, 1.0);
        assert!((c.sigma.powi(2) - beta * (1.0 - a_prev) / (1.0 - a)).abs() < 1e-15);
        // The final step with alpha one: no noise, x_prev = x0.
        let c = coefs(0.99, 1.0, 1.0);
        assert_eq!((c.x0_coef, c.eps_coef, c.sigma), (1.0, 0.0, 0.0));
    }

    #[test]
    fn options_are_checked_naming_the_field() {
        let bad = |d: Ddim| d.check(20, "ddim").expect_err("bad").to_string();
        assert!(bad(ddim(0, Spacing::Leading)).contains("ddim.n_steps: 0 must be in 1..=20"));
        assert!(bad(ddim(21, Spacing::Leading)).contains("ddim.n_steps: 21"));
        assert!(bad(Ddim { eta: 1.5, ..ddim(5, Spacing::Leading) }).contains("ddim.eta: 1.5"));
        assert!(bad(Ddim { eta: f64::NAN, ..ddim(5, Spacing::Leading) }).contains("ddim.eta"));
        assert!(ddim(20, Spacing::Trailing).check(20, "ddim").is_ok());
        let abar = [0.99, 0.9, 0.5];
        let d = ddim(3, Spacing::Leading);
        assert_eq!((d.abar_prev(2, &abar), d.abar_prev(0, &abar)), (0.9, 1.0));
        assert_eq!(Ddim { set_alpha_to_one: false, ..d }.abar_prev(0, &abar), 0.99);
    }
}

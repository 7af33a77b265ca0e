//! How big a run is: [`Size`] presets, every size of a run ([`Sizes`]), `--config`'s
//! `[extract]` table over them, and the fingerprints that name a run's models after its sizes
//! (so a rerun with the same sizes reuses them, and one with other sizes does not).

use std::collections::hash_map::DefaultHasher;
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use serde::{Deserialize, Serialize};

use crate::UsageError;

/// How big a run is: the steps, batches and networks; the horizon comes from the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Size {
    /// Seconds: checks that every step runs (tests); numbers are meaningless.
    Tiny,
    /// Minutes on a 2-core CPU: MLP denoisers, a few thousand steps.
    Default,
    /// The paper's sizes (TemporalUnet, horizon 256, T = 100, 100k reward steps): hours, for a
    /// GPU machine.
    Full,
}

/// Every size of a run. [`Sizes::preset`] fills them, the data sets `horizon` and `window`,
/// `--config`'s `[extract]` table overrides any of them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Sizes {
    pub horizon: u32,
    /// Transitions per window of the windowed-MLP reward (divides `horizon`).
    pub window: u32,
    pub n_timesteps: u32,
    /// `[diffusion] architecture` of the diffusion models, as a TOML value.
    pub diffusion_architecture: toml::Value,
    pub diffusion_steps: u64,
    pub diffusion_batch: u64,
    pub reward_steps: u64,
    pub reward_batch: u64,
    pub reward_lr: f64,
    pub reward_hidden: Vec<u32>,
    /// Algorithm 2's chains.
    pub num_chains: u32,
    /// Windows scored per class by the evaluation at most.
    pub max_windows: u64,
}

/// `--config`'s `[extract]` table: any field of [`Sizes`].
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SizeOverrides {
    horizon: Option<u32>,
    window: Option<u32>,
    n_timesteps: Option<u32>,
    diffusion_architecture: Option<toml::Value>,
    diffusion_steps: Option<u64>,
    diffusion_batch: Option<u64>,
    reward_steps: Option<u64>,
    reward_batch: Option<u64>,
    reward_lr: Option<f64>,
    reward_hidden: Option<Vec<u32>>,
    num_chains: Option<u32>,
    max_windows: Option<u64>,
}

fn arch(kind: &str, pairs: &[(&str, Vec<i64>)], dim: Option<i64>) -> toml::Value {
    let mut t = toml::Table::new();
    t.insert("kind".into(), toml::Value::String(kind.into()));
    for (k, v) in pairs {
        t.insert((*k).into(), toml::Value::Array(v.iter().map(|&x| toml::Value::Integer(x)).collect()));
    }
    if let Some(d) = dim {
        t.insert("dim".into(), toml::Value::Integer(d));
    }
    toml::Value::Table(t)
}

impl Sizes {
    /// The steps, batches and networks of a size, with a horizon and window to be replaced
    /// by the data's.
    pub fn preset(size: Size) -> Self {
        match size {
            Size::Tiny => Self {
                horizon: 16,
                window: 4,
                n_timesteps: 10,
                diffusion_architecture: arch("mlp", &[("hidden", vec![64, 64])], None),
                diffusion_steps: 200,
                diffusion_batch: 32,
                reward_steps: 200,
                reward_batch: 32,
                reward_lr: 1e-3,
                reward_hidden: vec![32, 32],
                num_chains: 64,
                max_windows: 2_000,
            },
            Size::Default => Self {
                horizon: 16,
                window: 4,
                n_timesteps: 20,
                diffusion_architecture: arch("mlp", &[("hidden", vec![256, 256, 256])], None),
                diffusion_steps: 4_000,
                diffusion_batch: 64,
                reward_steps: 3_000,
                reward_batch: 64,
                reward_lr: 1e-3,
                reward_hidden: vec![128, 64, 32],
                num_chains: 512,
                max_windows: 50_000,
            },
            Size::Full => Self {
                horizon: 256,
                window: 4,
                n_timesteps: 100,
                diffusion_architecture: arch("temporal_unet", &[("dim_mults", vec![1, 4, 8])], Some(32)),
                diffusion_steps: 200_000,
                diffusion_batch: 32,
                reward_steps: 100_000,
                reward_batch: 256,
                reward_lr: 5e-5,
                reward_hidden: vec![128, 64, 32],
                num_chains: 1024,
                max_windows: 200_000,
            },
        }
    }

    /// Reads `--config`'s `[extract]` table over these sizes.
    pub fn apply_config(&mut self, path: &Path) -> Result<()> {
        let text = std::fs::read_to_string(path).with_context(|| format!("--config {}", path.display()))?;
        let mut doc: toml::Table = toml::from_str(&text).with_context(|| format!("--config {}", path.display()))?;
        if let Some(other) = doc.keys().find(|k| *k != "extract") {
            bail!(UsageError(format!("--config {}: unknown table '{other}' (sizes go in [extract])", path.display())));
        }
        let table = doc.remove("extract").unwrap_or(toml::Value::Table(toml::Table::new()));
        let o: SizeOverrides =
            table.try_into().map_err(|e| UsageError(format!("--config {}: [extract]: {e}", path.display())))?;
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = o.$f { self.$f = v; } )* };
        }
        set!(horizon, window, n_timesteps, diffusion_architecture, diffusion_steps, diffusion_batch);
        set!(reward_steps, reward_batch, reward_lr, reward_hidden, num_chains, max_windows);
        self.check().map_err(|m| UsageError(format!("--config {}: [extract]: {m}", path.display())).into())
    }

    /// The rules sizes obey, as a message naming the field at fault.
    pub fn check(&self) -> Result<(), String> {
        if self.horizon == 0 || self.window == 0 || !self.horizon.is_multiple_of(self.window) {
            return Err(format!("window = {} must divide horizon = {}", self.window, self.horizon));
        }
        if self.n_timesteps < 2 || self.diffusion_steps == 0 || self.reward_steps == 0 {
            return Err("n_timesteps must be >= 2 and the step counts >= 1".into());
        }
        Ok(())
    }

    /// A short fingerprint of every size (part of the rewards' names).
    pub fn fingerprint(&self) -> String {
        short_hash(&serde_json::to_string(self).unwrap_or_default())
    }

    /// A short fingerprint of the sizes that shape the diffusion models only (part of their
    /// names), so a run that changes only the reward's sizes reuses the diffusion models.
    pub fn diffusion_fingerprint(&self) -> String {
        let shaping = serde_json::json!([
            self.horizon,
            self.n_timesteps,
            self.diffusion_architecture,
            self.diffusion_steps,
            self.diffusion_batch
        ]);
        short_hash(&shaping.to_string())
    }
}

pub fn short_hash(text: &str) -> String {
    let mut h = DefaultHasher::new();
    text.hash(&mut h);
    format!("{:08x}", h.finish() as u32)
}

/// Where a run's sizes come from.
#[derive(Debug, Clone)]
pub enum Sizing {
    /// A preset's steps and networks, the horizon and window from the data, then `--config`.
    Derive { size: Size, config: Option<PathBuf> },
    /// Exactly these (the demo's plans).
    Fixed(Sizes),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_overrides_sizes_and_refuses_unknown_keys() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("c.toml");
        std::fs::write(&path, "[extract]\nhorizon = 32\nwindow = 8\nreward_hidden = [16]\n").expect("write");
        let mut s = Sizes::preset(Size::Tiny);
        s.apply_config(&path).expect("ok");
        assert_eq!((s.horizon, s.window, s.reward_hidden.clone()), (32, 8, vec![16]));
        std::fs::write(&path, "[extract]\nhorizn = 32\n").expect("write");
        let err = Sizes::preset(Size::Tiny).apply_config(&path).expect_err("typo").to_string();
        assert!(err.contains("horizn"), "{err}");
        std::fs::write(&path, "[extract]\nhorizon = 30\nwindow = 8\n").expect("write");
        let err = Sizes::preset(Size::Tiny).apply_config(&path).expect_err("window").to_string();
        assert!(err.contains("window = 8 must divide horizon = 30"), "{err}");
    }

    #[test]
    fn the_diffusion_models_name_depends_on_their_sizes_only() {
        let base = Sizes::preset(Size::Default);
        let mut reward_only = base.clone();
        (reward_only.reward_steps, reward_only.reward_lr, reward_only.window) = (600, 3e-4, 8);
        assert_eq!(base.diffusion_fingerprint(), reward_only.diffusion_fingerprint());
        assert_ne!(base.fingerprint(), reward_only.fingerprint());
        for change in [
            |s: &mut Sizes| s.horizon = 32,
            |s: &mut Sizes| s.n_timesteps = 50,
            |s: &mut Sizes| s.diffusion_steps += 1,
            |s: &mut Sizes| s.diffusion_batch = 7,
            |s: &mut Sizes| s.diffusion_architecture = toml::Value::String("other".into()),
        ] {
            let mut changed = base.clone();
            change(&mut changed);
            assert_ne!(base.diffusion_fingerprint(), changed.diffusion_fingerprint(), "{changed:?}");
        }
    }
}

//! Discriminability (paper section 5.1): a balanced, seeded subset of windows of a base and an
//! expert file scored at `t`, the pooled scores winsorized, each class split 80/20, a logistic
//! regression on the reward alone fitted on the training part and measured on the held-out
//! part ([`relreward_toolkit::eval::discriminate`]); optionally both classes' histograms.

use std::path::PathBuf;

use anyhow::{Result, anyhow};
use relreward_client::Client;
use relreward_toolkit::eval::discriminate::{self, Discrimination, Protocol};
use relreward_toolkit::eval::plot;
use relreward_toolkit::eval::stats::Rng;

use super::{HISTOGRAM_BINS, Scoring, file_name, load_items, score_subset};
use crate::ops::Progress;
use crate::ops::items::ItemsSource;
use crate::output::{check_out_file, fmt_p, percent};

/// Windows scored per class at most, unless asked otherwise.
pub const DEFAULT_MAX_WINDOWS: u64 = 20_000;
/// The paper's winsorization of the pooled scores: 1% per tail.
pub const DEFAULT_WINSORIZE: f64 = 0.01;

/// What to discriminate.
#[derive(Debug, Clone)]
pub struct DiscriminateInput {
    pub scoring: Scoring,
    /// Base (undirected) trajectories: a D4RL-style .npz, or an .npz holding x [B, H, D].
    pub base_data: PathBuf,
    /// Expert trajectories, in the same form.
    pub expert_data: PathBuf,
    /// Windows scored per class at most (both classes get min(this, base, expert windows)).
    pub max_windows: u64,
    /// Winsorize the pooled scores at the P and 1 - P quantiles.
    pub winsorize: f64,
    /// Where to draw both classes' reward histograms (winsorized scores), if anywhere.
    pub hist_out: Option<PathBuf>,
}

impl DiscriminateInput {
    /// The paper's protocol over these files, with default sizes.
    pub fn new(scoring: Scoring, base_data: PathBuf, expert_data: PathBuf) -> Self {
        Self {
            scoring,
            base_data,
            expert_data,
            max_windows: DEFAULT_MAX_WINDOWS,
            winsorize: DEFAULT_WINSORIZE,
            hist_out: None,
        }
    }

    /// The checks that need no server (a usage error before connecting).
    pub fn check(&self) -> Result<()> {
        if let Some(out) = &self.hist_out {
            check_out_file("--hist-out", out)?;
        }
        Ok(())
    }
}

/// One class's windows: how many the file had, and where they came from.
#[derive(Debug, Clone)]
pub struct ClassInput {
    pub available: usize,
    pub source: ItemsSource,
}

/// What [`discriminate`] measured.
#[derive(Debug, Clone)]
pub struct Discriminability {
    pub protocol: Protocol,
    pub base: ClassInput,
    pub expert: ClassInput,
    /// The fitted regression, accuracies, AUC and each class's summary.
    pub result: Discrimination,
}

impl Discriminability {
    /// Held-out balanced accuracy: the number the paper reports.
    pub fn balanced_accuracy(&self) -> f64 {
        self.result.test_balanced_accuracy
    }

    /// Whether the fitted weight is positive: the reward ranks expert windows above base ones.
    pub fn expert_scores_higher(&self) -> bool {
        self.result.model.weight > 0.0
    }
}

/// Scores both files' windows with the model and measures their discriminability.
pub async fn discriminate(
    progress: &dyn Progress,
    client: &Client,
    input: &DiscriminateInput,
) -> Result<Discriminability> {
    input.check()?;
    let s = &input.scoring;
    let base = load_items(client, &s.model, &input.base_data, "--base-data", s.stride).await?;
    let expert = load_items(client, &s.model, &input.expert_data, "--expert-data", s.stride).await?;
    let mut rng = Rng::new(s.seed);
    let (base_idx, expert_idx) =
        discriminate::balanced_subsets(base.len(), expert.len(), input.max_windows as usize, &mut rng);
    let (base_source, expert_source) = (base.source(), expert.source());
    let base = score_subset(progress, client, s, base, &base_idx, "--base-data", false).await?;
    let expert = score_subset(progress, client, s, expert, &expert_idx, "--expert-data", false).await?;
    let protocol = Protocol { winsorize: input.winsorize, ..Protocol::default() };
    let d = discriminate::discriminate(&base.rewards, &expert.rewards, protocol, &mut rng).map_err(|e| anyhow!(e))?;

    if let Some(out) = &input.hist_out {
        let groups = vec![
            (format!("base: {}", file_name(&input.base_data)), d.base_winsorized.clone()),
            (format!("expert: {}", file_name(&input.expert_data)), d.expert_winsorized.clone()),
        ];
        let title =
            format!("rho of {} at t = {}: test balanced accuracy {}", s.model, s.t, percent(d.test_balanced_accuracy));
        let x_label = format!("reward (winsorized at {}%)", fmt_p(input.winsorize));
        plot::histogram_png(out, &title, &x_label, &groups, HISTOGRAM_BINS)?;
    }
    Ok(Discriminability {
        protocol,
        base: ClassInput { available: base.available, source: base_source },
        expert: ClassInput { available: expert.available, source: expert_source },
        result: d,
    })
}

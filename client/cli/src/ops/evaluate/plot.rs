//! A job's loss curve (and held-out loss) from its recorded events, drawn as a PNG; optionally
//! a histogram of a reward over the windows of one or more datasets (pooled 1% winsorization).

use std::path::PathBuf;

use anyhow::{Result, bail};
use relreward_client::{Client, ClientError, pb};
use relreward_toolkit::eval::plot::{self, Series};
use relreward_toolkit::eval::stats::{Rng, winsorize};

use super::{HISTOGRAM_BINS, Scoring, file_name, load_items, score_subset};
use crate::UsageError;
use crate::ops::Progress;
use crate::ops::scoring::{Summary, summarize};
use crate::output::{check_out_file, state_name};

/// What to plot.
#[derive(Debug, Clone)]
pub struct JobPlotInput {
    pub id: String,
    /// Where to draw the loss curve (PNG).
    pub out: PathBuf,
    /// The reward histogram, if wanted.
    pub histogram: Option<HistogramInput>,
}

/// A histogram of a reward over the windows of datasets.
#[derive(Debug, Clone)]
pub struct HistogramInput {
    /// Where to draw it (PNG).
    pub out: PathBuf,
    /// The reward (`None`: the job's own model, for reward and discriminator jobs).
    pub model: Option<String>,
    /// Trajectories whose windows are scored, one overlaid histogram each.
    pub datasets: Vec<PathBuf>,
    pub t: u32,
    pub stride: Option<u64>,
    /// Windows scored per dataset at most (a seeded uniform subset).
    pub max_windows: u64,
    pub seed: u64,
}

impl JobPlotInput {
    /// The checks that need no server (a usage error before connecting).
    pub fn check(&self) -> Result<()> {
        check_out_file("--out", &self.out)?;
        if let Some(h) = &self.histogram {
            check_out_file("--hist-out", &h.out)?;
        }
        Ok(())
    }
}

/// What [`job_plot`] drew.
#[derive(Debug, Clone)]
pub struct JobPlot {
    /// `diffusion`, `reward`, `discriminator` (or `job` for a spec without a kind).
    pub kind: &'static str,
    /// The job's state when asked (`succeeded`, ...).
    pub state: &'static str,
    /// (step, loss) of each progress event, and of each held-out loss.
    pub loss: Vec<(f64, f64)>,
    pub eval_loss: Vec<(f64, f64)>,
    pub log_scale: bool,
    pub histogram: Option<RewardHistogram>,
}

/// The histogram [`job_plot`] drew.
#[derive(Debug, Clone)]
pub struct RewardHistogram {
    pub model: String,
    /// One per dataset, in order.
    pub datasets: Vec<DatasetRewards>,
}

/// A dataset's windows in the histogram.
#[derive(Debug, Clone)]
pub struct DatasetRewards {
    pub dataset: PathBuf,
    pub windows_available: usize,
    pub windows: usize,
    /// Of the raw (not winsorized) rewards.
    pub summary: Option<Summary>,
}

/// Draws the loss curve of job `input.id` (and the reward histogram, if asked).
pub async fn job_plot(progress: &dyn Progress, client: &Client, input: &JobPlotInput) -> Result<JobPlot> {
    input.check()?;
    let job = client.get_job(&input.id).await?;
    let spec = job.spec.clone().unwrap_or_default();
    let kind = match &spec.kind {
        Some(pb::job_spec::Kind::Diffusion(_)) => "diffusion",
        Some(pb::job_spec::Kind::Reward(_)) => "reward",
        Some(pb::job_spec::Kind::Discriminator(_)) => "discriminator",
        None => "job",
    };
    // Replay the recorded events up to the last one the job had when asked (a running job's
    // stream would go on).
    let (mut loss, mut eval) = (Vec::new(), Vec::new());
    if job.last_seq > 0 {
        let mut stream = client.watch_job(&input.id, 1).await?;
        while let Some(event) = stream.message().await.map_err(ClientError::Status)? {
            if let Some(pb::job_event::Event::Progress(p)) = &event.event {
                loss.push((p.step as f64, p.loss));
                if let Some(e) = p.eval_loss {
                    eval.push((p.step as f64, e));
                }
            }
            if event.seq >= job.last_seq {
                break;
            }
        }
    }
    if loss.is_empty() {
        bail!("job {} has no progress events yet: nothing to plot", input.id);
    }
    let mut series = vec![Series { name: "training loss".to_owned(), points: loss.clone() }];
    if !eval.is_empty() {
        series.push(Series { name: "held-out loss".to_owned(), points: eval.clone() });
    }
    let log = plot::wants_log_scale(&series);
    let state = state_name(job.state());
    let title = format!("job {} ({kind}, {state}): loss", input.id);
    plot::loss_png(&input.out, &title, "loss", &series, log)?;

    let histogram = match &input.histogram {
        None => None,
        Some(h) => {
            let model = match (&h.model, kind) {
                (Some(m), _) => m.clone(),
                (None, "reward" | "discriminator") => spec.output_model.clone(),
                (None, _) => {
                    return Err(UsageError(format!(
                        "--hist-out: job {} trains a {kind} model, not a reward; name the reward with --model",
                        input.id
                    ))
                    .into());
                }
            };
            Some(histogram(progress, client, h, model).await?)
        }
    };
    Ok(JobPlot { kind, state, loss, eval_loss: eval, log_scale: log, histogram })
}

async fn histogram(
    progress: &dyn Progress,
    client: &Client,
    h: &HistogramInput,
    model: String,
) -> Result<RewardHistogram> {
    let scoring = Scoring { t: h.t, stride: h.stride, seed: h.seed, ..Scoring::new(&model) };
    let mut rng = Rng::new(h.seed);
    let mut groups = Vec::new();
    let mut datasets = Vec::new();
    for path in &h.datasets {
        let items = load_items(client, &model, path, "--dataset", h.stride).await?;
        let idx = rng.subset(items.len(), h.max_windows as usize);
        let scored = score_subset(progress, client, &scoring, items, &idx, "--dataset", false).await?;
        datasets.push(DatasetRewards {
            dataset: path.clone(),
            windows_available: scored.available,
            windows: scored.rewards.len(),
            summary: summarize(scored.rewards.iter().copied()),
        });
        groups.push((file_name(path), scored.rewards));
    }
    // Pooled 1% winsorization, so that a few extreme windows do not squeeze the rest.
    let mut pooled: Vec<f64> = groups.iter().flat_map(|(_, v)| v.iter().copied()).collect();
    let limits = winsorize(&mut pooled, 0.01);
    for (_, values) in &mut groups {
        for v in values.iter_mut() {
            *v = v.clamp(limits.0, limits.1);
        }
    }
    let title = format!("rho of {model} at t = {}", h.t);
    plot::histogram_png(&h.out, &title, "reward (winsorized at 1%)", &groups, HISTOGRAM_BINS)?;
    Ok(RewardHistogram { model, datasets })
}

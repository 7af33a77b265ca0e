//! `relreward relabel`: a trajectory archive's rewards replaced by a reward model's (see
//! `ops::relabel` for the rule and what is kept).

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use relreward_cli::ops::relabel::{RelabelQuery, relabel as run};

use super::{Ctx, Report};

#[derive(Debug, Clone, Args)]
pub struct RelabelArgs {
    /// The reward (or discriminator) model whose values become the rewards.
    #[arg(long, value_name = "MODEL")]
    pub model: String,
    /// Trajectories (.npz: observations, actions, terminals, timeouts; rewards if any).
    #[arg(long, value_name = "FILE.npz")]
    pub input: PathBuf,
    /// Where the relabelled archive goes (its own rewards kept as rewards_original).
    #[arg(long, value_name = "FILE.npz")]
    pub output: PathBuf,
    /// Diffusion time the windows are scored at (0: clean data).
    #[arg(long, value_name = "T", default_value_t = 0)]
    pub t: u32,
    /// Windows per Score request.
    #[arg(long, default_value_t = 1024)]
    pub batch: usize,
    /// Replace an existing --output.
    #[arg(long)]
    pub overwrite: bool,
}

pub async fn relabel(ctx: &Ctx, args: RelabelArgs) -> Result<Report> {
    let client = ctx.connect().await?;
    let query = RelabelQuery {
        model: args.model,
        input: args.input,
        output: args.output,
        t: args.t,
        batch: args.batch,
        overwrite: args.overwrite,
    };
    let done = run(&client, ctx, &query).await?;
    let kept = done.original.as_deref().map_or(String::new(), |o| format!("; the file's own rewards kept as {o}"));
    let text = format!(
        "{}: {} rows in {} episodes relabelled with '{}' at t = {} (mean {:.4}, min {:.4}, max {:.4}){kept}",
        done.output.display(),
        done.rows,
        done.episodes,
        query.model,
        query.t,
        done.mean,
        done.min,
        done.max
    );
    Ok(Report::ok(text, serde_json::to_value(&done)?))
}

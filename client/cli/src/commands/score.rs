//! `relreward score`: rho of every item of `--input` (Score requests in batches).

use anyhow::{Result, bail};
use clap::Args;
use relreward_client::pb;
use serde_json::json;

use relreward_cli::ops::items::{batches, read_items, request_batch};
use relreward_cli::ops::scoring::floats;

use super::rewards::{InputArgs, check_out, query_batches, query_fields, query_report};
use super::{Ctx, Report};

#[derive(Debug, Clone, Args)]
pub struct ScoreArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Diffusion time of every item (0: clean data).
    #[arg(long, value_name = "T", default_value_t = 0, allow_negative_numbers = true)]
    pub t: u32,
    /// Also rho per window ([B, H / h]; windowed rewards).
    #[arg(long)]
    pub per_window: bool,
    /// Also rho per step ([B, H]; windowed rewards).
    #[arg(long)]
    pub per_step: bool,
}

pub async fn score(ctx: &Ctx, args: ScoreArgs) -> Result<Report> {
    let ScoreArgs { input, t, per_window, per_step } = args;
    check_out(input.out.as_deref())?;
    let client = ctx.connect().await?;
    let items = read_items(&client, &input.query()).await?;
    let n = items.len();
    let batch = request_batch(input.batch, items.item_len() as u64 * 4, ctx.json);
    let ranges = batches(n, batch);

    let mut fields = query_fields(&input, t);
    fields.push(("per_window", "--per-window".to_owned()));
    fields.push(("per_step", "--per-step".to_owned()));
    let mut rewards = Vec::with_capacity(n);
    let mut windows: Option<(u64, Vec<f32>)> = None;
    let mut steps: Option<(u64, Vec<f32>)> = None;
    let send = |_, range| {
        let request = pb::ScoreRequest {
            model: input.model.clone(),
            x: Some(items.batch(range)),
            t: vec![t],
            input_units: input.units.to_proto() as i32,
            per_window,
            per_step,
        };
        let client = client.clone();
        async move { client.score(request).await }
    };
    query_batches(ctx, &ranges, &fields, send, |b, answer: pb::ScoreResponse| {
        rewards.extend(floats(answer.rewards.as_ref(), "rewards", &[b])?);
        for (wanted, field, tensor, acc) in [
            (per_window, "per_window", answer.per_window.as_ref(), &mut windows),
            (per_step, "per_step", answer.per_step.as_ref(), &mut steps),
        ] {
            if !wanted {
                continue;
            }
            let width = match (acc.as_ref(), tensor) {
                (Some((w, _)), _) => *w,
                (None, Some(t)) if t.shape.len() == 2 => t.shape[1],
                (None, Some(t)) => bail!("the server's answer has {field} of shape {:?}; expected [{b}, K]", t.shape),
                (None, None) => bail!("the server's answer has no {field}"),
            };
            let values = floats(tensor, field, &[b, width])?;
            acc.get_or_insert_with(|| (width, Vec::new())).1.extend(values);
        }
        Ok(())
    })
    .await?;

    let mut more = Vec::new();
    if let Some((w, values)) = windows {
        more.push(("per_window", vec![n as u64, w], values));
    }
    if let Some((w, values)) = steps {
        more.push(("per_step", vec![n as u64, w], values));
    }
    query_report(&input, &items, t, rewards, more, Vec::new(), json!({})).await
}

//! `relreward grad`: grad_x rho of every item of `--input` (Gradient requests in batches).

use anyhow::Result;
use clap::Args;
use relreward_client::pb;
use serde_json::json;

use relreward_cli::ops::items::{batches, read_items, request_batch};
use relreward_cli::ops::scoring::{floats, summarize};

use super::rewards::{
    InputArgs, UnitsArg, check_out, query_batches, query_fields, query_report, summary_json, summary_text,
};
use super::{Ctx, Report, UsageError};

#[derive(Debug, Clone, Args)]
pub struct GradArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Diffusion time of every item.
    #[arg(long, value_name = "T", allow_negative_numbers = true)]
    pub t: u32,
    /// Units of the returned gradient (raw: through the normalizer's chain rule).
    #[arg(long, value_enum, value_name = "UNITS", default_value_t = UnitsArg::Raw)]
    pub gradient_units: UnitsArg,
    /// Multiply the gradient by W [default: 1].
    #[arg(long, value_name = "W", allow_negative_numbers = true)]
    pub omega: Option<f64>,
    /// Multiply the gradient by this diffusion model's posterior variance at t (Diffuser's
    /// scale_grad_by_std).
    #[arg(long, value_name = "BASE")]
    pub scale_by_posterior_variance_of: Option<String>,
}

pub async fn grad(ctx: &Ctx, args: GradArgs) -> Result<Report> {
    let GradArgs { input, t, gradient_units, omega, scale_by_posterior_variance_of } = args;
    if let Some(w) = omega.filter(|w| !w.is_finite()) {
        return Err(UsageError(format!("--omega {w}: must be a finite number")).into());
    }
    if scale_by_posterior_variance_of.as_deref() == Some("") {
        return Err(UsageError("--scale-by-posterior-variance-of: needs a diffusion model name".into()).into());
    }
    check_out(input.out.as_deref())?;
    let client = ctx.connect().await?;
    let items = read_items(&client, &input.query()).await?;
    let n = items.len();
    let item_shape = items.item_shape();
    let item_len = items.item_len();
    // The answer carries a gradient as large as the request: keep both under the limit.
    let batch = request_batch(input.batch, item_len as u64 * 4, ctx.json);
    let ranges = batches(n, batch);

    let mut fields = query_fields(&input, t);
    fields.push(("gradient_units", "--gradient-units".to_owned()));
    if let Some(w) = omega {
        fields.push(("omega", format!("--omega {w}")));
    }
    if let Some(base) = &scale_by_posterior_variance_of {
        fields.push(("scale_by_posterior_variance_of", format!("--scale-by-posterior-variance-of {base}")));
    }
    let mut rewards = Vec::with_capacity(n);
    let mut gradients = Vec::with_capacity(n * item_len);
    let send = |i: usize, range| {
        let request = pb::GradientRequest {
            request_id: i as u64,
            model: input.model.clone(),
            x: Some(items.batch(range)),
            t: vec![t],
            input_units: input.units.to_proto() as i32,
            gradient_units: gradient_units.to_proto() as i32,
            omega,
            scale_by_posterior_variance_of: scale_by_posterior_variance_of.clone().unwrap_or_default(),
        };
        let client = client.clone();
        async move { client.gradient(request).await }
    };
    query_batches(ctx, &ranges, &fields, send, |b, answer: pb::GradientResponse| {
        rewards.extend(floats(answer.rewards.as_ref(), "rewards", &[b])?);
        let mut shape = vec![b];
        shape.extend(&item_shape);
        gradients.extend(floats(answer.gradient.as_ref(), "gradient", &shape)?);
        Ok(())
    })
    .await?;

    let norms = summarize(
        gradients.chunks(item_len.max(1)).map(|g| g.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>().sqrt()),
    );
    let mut grad_shape = vec![n as u64];
    grad_shape.extend(&item_shape);
    let more = vec![("grad_x", grad_shape, gradients)];
    let text = vec![("|grad_x|", summary_text(norms))];
    let json = json!({
        "gradient_units": gradient_units.name(),
        "omega": omega.unwrap_or(1.0),
        "scale_by_posterior_variance_of": scale_by_posterior_variance_of,
        "gradient_norm": summary_json(norms),
    });
    query_report(&input, &items, t, rewards, more, text, json).await
}

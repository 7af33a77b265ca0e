//! `relreward encode` and `relreward decode`: an `.npz` of images into an `.npz` of latents
//! through an autoencoder model, and back (see `ops::latents` for the batching and what the
//! output holds).

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use relreward_cli::ops::latents::{Conversion, Direction, convert};
use relreward_cli::output::{check_out_file, item_bar};

use super::{Ctx, Report};

/// The flags of both commands.
#[derive(Debug, Clone, Args)]
pub struct LatentArgs {
    /// The autoencoder model (`relreward model upload --autoencoder`).
    #[arg(long, value_name = "AE")]
    pub model: String,
    /// .npz (or .npy) holding the items: images [B, *image_shape] to encode, latents
    /// [B, *latent_shape] to decode; float32 or float64.
    #[arg(long, value_name = "FILE.npz")]
    pub input: PathBuf,
    /// The array of --input holding the items.
    #[arg(long, value_name = "KEY", default_value = "x")]
    pub key: String,
    /// Where the result goes: an .npz with the result under --out-key and every other array of
    /// --input copied unchanged (e.g. labels).
    #[arg(long, value_name = "FILE.npz")]
    pub out: PathBuf,
    /// The result's array name in --out (`x`: a file of latents uploads as a samples dataset
    /// as it is).
    #[arg(long, value_name = "KEY", default_value = "x")]
    pub out_key: String,
    /// Items per request (lowered so that a request and its answer stay under 8 MiB each).
    #[arg(long, value_name = "N", default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub batch: u64,
}

pub async fn encode(ctx: &Ctx, args: LatentArgs) -> Result<Report> {
    run(ctx, args, Direction::Encode).await
}

pub async fn decode(ctx: &Ctx, args: LatentArgs) -> Result<Report> {
    run(ctx, args, Direction::Decode).await
}

async fn run(ctx: &Ctx, args: LatentArgs, direction: Direction) -> Result<Report> {
    check_out_file("--out", &args.out)?;
    let client = ctx.connect().await?;
    let conversion = Conversion {
        model: args.model,
        direction,
        input: args.input,
        key: args.key,
        out: args.out,
        out_key: args.out_key,
        batch: args.batch,
    };
    let what = match direction {
        Direction::Encode => "images",
        Direction::Decode => "latents",
    };
    let bar = item_bar(ctx.json, 0, what);
    let done = convert(&client, &conversion, |n, total| {
        bar.set_length(total);
        bar.set_position(n);
    })
    .await;
    bar.finish_and_clear();
    let done = done?;
    let verb = match direction {
        Direction::Encode => "encoded",
        Direction::Decode => "decoded",
    };
    let copied = if done.copied.is_empty() { String::new() } else { format!("; copied {}", done.copied.join(", ")) };
    let text = format!(
        "{verb} {} {what} {:?} with '{}' into {} '{}' {:?} ({} requests){copied}\n",
        done.items,
        done.input_shape,
        done.model,
        done.out.display(),
        done.out_key,
        done.output_shape,
        done.requests
    );
    Ok(Report::ok(text, serde_json::to_value(&done)?))
}

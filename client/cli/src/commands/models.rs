//! `relreward model upload|import|list|show|download|delete`.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use relreward_cli::ops::scoring::flag_of;
use relreward_client::client::UploadProgress;
use relreward_client::pb;
use serde_json::{Value, json};
use tokio::sync::oneshot;

use relreward_toolkit::diffuser_import::{NamedTensor, write_safetensors};

use super::manifest::{self, architecture_text, manifest_json, parametrization_name, schedule_text, space_text};
use super::output::{
    byte_progress_bar, drive_progress, eprint_line, fmt_short, human_bytes, key_values, normalizer_json,
    normalizer_text, or_dash, rfc3339, table, time_or_dash,
};
use super::{Ctx, Report, UsageError};

#[derive(Debug, Subcommand)]
pub enum ModelCommand {
    /// Register a diffusion model with its manifest: a TorchScript module, or native safetensors
    /// weights when the manifest names an `architecture`; with --reward, a bring-your-own
    /// TorchScript reward (rho(x, t) -> [B], or Diffuser's value function forward(x, cond, t)
    /// -> [B, 1]) served like trained rewards; with --autoencoder, a TorchScript module exporting
    /// encode(x) and decode(z) (`relreward encode` / `decode`).
    Upload(ModelUploadArgs),
    /// Convert a model into native weights (safetensors), checking every tensor: a Diffuser
    /// TemporalUnet state_dict exported to .npz, or a folder written by diffusers'
    /// save_pretrained (UNet1DModel, UNet2DModel), by path or by repository id in the local
    /// Hugging Face cache; runs locally (nothing is downloaded) unless --name.
    // Boxed: its many flags would make every other variant as large.
    Import(Box<ModelImportArgs>),
    /// List models (every kind unless --kind).
    List {
        #[arg(long, value_enum)]
        kind: Option<ModelKindArg>,
    },
    /// Show a model: kind, format, digest, provenance and manifest.
    Show { name: String },
    /// Download a model's files (TorchScript module or safetensors weights, and any that
    /// belong with them) and its manifest as manifest.json, each checked against its sha256.
    Download(ModelDownloadArgs),
    /// Download plus module.pt, the model traced as TorchScript by the server: a reward's
    /// forward(x in raw units, t) -> rho (Score's values; autograd gives Gradient's), a native
    /// diffusion model's denoiser over normalized inputs. Loads with torch.jit.load.
    Export(ModelDownloadArgs),
    /// Delete a model (refused while a job uses it, or a recipe samples it).
    Delete { name: String },
    /// Register a named sampling recipe: a conditional diffusion model sampled under a prompt
    /// set (--labels), a classifier-free guidance scale and optional safety guidance. It stands
    /// for a diffusion model in `sample --base` (sample i under label i mod k) and as a reward
    /// job's base_model / expert_model (Algorithm 2: each chain draws a label).
    Recipe(ModelRecipeArgs),
}

#[derive(Debug, Args)]
pub struct ModelRecipeArgs {
    /// Recipe name: [a-z0-9][a-z0-9._-]{0,63}.
    name: String,
    /// The conditional diffusion model it samples.
    #[arg(long, value_name = "M")]
    model: String,
    #[command(flatten)]
    recipe: super::sample::RecipeFlags,
    #[arg(long, default_value = "")]
    description: String,
}

#[derive(Debug, Args)]
pub struct ModelUploadArgs {
    /// The TorchScript module (.pt), called as forward(x, t); or native weights
    /// (.safetensors) when the manifest names an `architecture`.
    file: PathBuf,
    /// Model name: [a-z0-9][a-z0-9._-]{0,63}.
    #[arg(long)]
    name: String,
    /// The model's manifest, TOML or JSON (parametrization, schedule, n_timesteps, space,
    /// normalizer, clip_denoised; architecture for native weights). With --reward, a reward
    /// manifest: signature ("rho" | "value_function"), n_timesteps, space, normalizer, and
    /// optionally base_model. With --autoencoder, an autoencoder manifest: image_shape,
    /// latent_shape, and optionally scaling_factor (default 1) and shift_factor (default 0).
    #[arg(long, value_name = "MANIFEST.toml|json")]
    manifest: PathBuf,
    #[arg(long, default_value = "")]
    description: String,
    /// The file is a bring-your-own TorchScript reward over normalized x (needs a server with
    /// models.allow_torchscript_upload); --manifest is its reward manifest.
    #[arg(long, conflicts_with = "autoencoder")]
    reward: bool,
    /// The file is an autoencoder: a TorchScript module exporting encode(x) (images [B, *image_shape]
    /// -> latents [B, *latent_shape]) and decode(z) (needs a server with
    /// models.allow_torchscript_upload); --manifest is its autoencoder manifest.
    #[arg(long)]
    autoencoder: bool,
}

/// `model import`: the source decides the form. A file is a `.npz` state_dict (the flags under
/// "Diffuser .npz"); a directory, or a repository id found in the local Hugging Face cache, is a
/// diffusers folder (the flags under "diffusers folder"), whose config.json and
/// scheduler_config.json give the architecture and the manifest.
#[derive(Debug, Args)]
pub struct ModelImportArgs {
    /// A Diffuser state_dict as .npz (`np.savez(path, **{k: v.cpu().numpy() for k, v in
    /// model.state_dict().items()})`); or a folder written by diffusers' save_pretrained
    /// (config.json, diffusion_pytorch_model.safetensors, scheduler/scheduler_config.json; or a
    /// pipeline's unet/ and scheduler/); or the repository id of such a folder in the local
    /// Hugging Face cache ($HF_HOME/hub; nothing is downloaded).
    #[arg(value_name = "FILE.npz|DIR|ORG/NAME")]
    source: String,
    /// Where to write the native weights (safetensors, relreward's tensor names).
    #[arg(long, value_name = "WEIGHTS.safetensors")]
    out: PathBuf,
    /// Also register the weights on the server under this name (a native upload: accepted
    /// without models.allow_torchscript_upload); without it the command runs offline.
    #[arg(long)]
    name: Option<String>,
    /// The registered model's description (with --name).
    #[arg(long, default_value = "", requires = "name")]
    description: String,

    /// The model's manifest (TOML or JSON); its trajectory space gives the horizon and the
    /// transition dim (action_dim + obs_dim). An `architecture` in it must agree with the flags.
    #[arg(long, value_name = "MANIFEST.toml|json", help_heading = "Diffuser .npz")]
    manifest: Option<PathBuf>,
    /// TemporalUnet `dim` (Diffuser's `model.dim`).
    #[arg(long, help_heading = "Diffuser .npz")]
    dim: Option<u64>,
    /// TemporalUnet `dim_mults`, comma separated (Diffuser's `model.dim_mults`).
    #[arg(long, value_delimiter = ',', help_heading = "Diffuser .npz")]
    dim_mults: Vec<u64>,
    /// Keep only tensors under this prefix and strip it: `model.` for a GaussianDiffusion
    /// state_dict (Diffuser's checkpoints hold `model` and `ema`, each one of these) [default: none].
    #[arg(long, help_heading = "Diffuser .npz")]
    prefix: Option<String>,

    /// Where to write the manifest derived from the folder (TOML, or JSON for a .json name)
    /// [default: OUT with the extension .manifest.toml].
    #[arg(long, value_name = "MANIFEST.toml|json", help_heading = "diffusers folder")]
    manifest_out: Option<PathBuf>,
    /// UNet1DModel: the trajectory length (a multiple of 2^(levels - 1)); required.
    #[arg(long, help_heading = "diffusers folder")]
    horizon: Option<usize>,
    /// UNet1DModel: how many of the channels are the action (rows are [action | observation],
    /// Diffuser's layout); required.
    #[arg(long, help_heading = "diffusers folder")]
    action_dim: Option<usize>,
    /// UNet2DModel: the image's height and width [default: the config's sample_size].
    #[arg(long, value_name = "H[,W]", value_delimiter = ',', help_heading = "diffusers folder")]
    image_size: Vec<usize>,
    /// The normalizer the model was trained under, a TOML or JSON table (e.g. kind =
    /// "gaussian", mean = [..], std = [..]) [default: identity: a folder holds none].
    #[arg(long, value_name = "NORMALIZER.toml|json", help_heading = "diffusers folder")]
    normalizer: Option<PathBuf>,
    /// Class-conditional UNet2DModel (num_class_embeds): the label meaning "no class", which
    /// classifier-free guidance needs [default: none].
    #[arg(long, value_name = "L", help_heading = "diffusers folder")]
    null_class: Option<usize>,
    /// The model's subfolder [default: the folder itself when it holds config.json, else unet].
    #[arg(long, value_name = "NAME", help_heading = "diffusers folder")]
    subfolder: Option<String>,
    /// The DDPMScheduler's config [default: scheduler/scheduler_config.json, found as
    /// save_pretrained lays it out].
    #[arg(long, value_name = "FILE", help_heading = "diffusers folder")]
    scheduler_config: Option<PathBuf>,
    /// For a repository id: the cached revision (a branch or tag under refs/, or a commit)
    /// [default: main].
    #[arg(long, value_name = "REV", help_heading = "diffusers folder")]
    revision: Option<String>,
}

#[derive(Debug, Args)]
pub struct ModelDownloadArgs {
    name: String,
    /// The directory to write into (created if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Replace files of the same names already in DIR.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModelKindArg {
    Diffusion,
    Reward,
    Discriminator,
    Autoencoder,
    Recipe,
}

impl ModelKindArg {
    fn to_proto(self) -> pb::ModelKind {
        match self {
            Self::Diffusion => pb::ModelKind::Diffusion,
            Self::Reward => pb::ModelKind::Reward,
            Self::Discriminator => pb::ModelKind::Discriminator,
            Self::Autoencoder => pb::ModelKind::Autoencoder,
            Self::Recipe => pb::ModelKind::Recipe,
        }
    }
}

pub async fn run(ctx: &Ctx, command: ModelCommand) -> Result<Report> {
    match command {
        ModelCommand::Upload(args) => upload(ctx, args).await,
        ModelCommand::Import(args) => import(ctx, *args).await,
        ModelCommand::List { kind } => list(ctx, kind).await,
        ModelCommand::Show { name } => show(ctx, &name).await,
        ModelCommand::Download(args) => download(ctx, args, false).await,
        ModelCommand::Export(args) => download(ctx, args, true).await,
        ModelCommand::Delete { name } => delete(ctx, &name).await,
        ModelCommand::Recipe(args) => recipe(ctx, args).await,
    }
}

// ---------------------------------------------------------------------------------------------
// Commands

async fn upload(ctx: &Ctx, args: ModelUploadArgs) -> Result<Report> {
    let ModelUploadArgs { file, name, manifest, description, reward, autoencoder } = args;
    if autoencoder {
        // A bad manifest is reported before anything is sent.
        let man = manifest::load_autoencoder(&manifest)?;
        let model = send_model(ctx, &file, name, Upload::Autoencoder(man), description).await?;
        return Ok(Report::ok(format_model(&model), model_json(&model)));
    }
    if reward {
        // A bad manifest is reported before anything is sent.
        let man = manifest::load_reward(&manifest)?;
        let model = send_model(ctx, &file, name, Upload::Reward(man), description).await?;
        return Ok(Report::ok(format_model(&model), model_json(&model)));
    }
    // A bad manifest is reported before anything is sent.
    let man = manifest::load(&manifest)?;
    let is_safetensors = file.extension().is_some_and(|e| e.eq_ignore_ascii_case("safetensors"));
    if is_safetensors && man.architecture.is_none() {
        bail!(
            "{}: architecture: missing; {} is safetensors weights, which need the built-in architecture they \
             belong to (e.g. architecture = {{ kind = \"temporal_unet\", dim = 32, dim_mults = [1, 4, 8] }})",
            manifest.display(),
            file.display()
        );
    }
    let model = send_model(ctx, &file, name, Upload::Diffusion(man), description).await?;
    Ok(Report::ok(format_model(&model), model_json(&model)))
}

/// What `send_model` registers.
enum Upload {
    Diffusion(pb::DiffusionManifest),
    /// A bring-your-own TorchScript reward.
    Reward(pb::RewardUploadManifest),
    /// An autoencoder (TorchScript).
    Autoencoder(pb::AutoencoderUploadManifest),
}

/// Streams a model file with its manifest, with a progress bar; the format follows the
/// manifest (native weights when a diffusion manifest names an architecture, see `manifest`;
/// a reward and an autoencoder are always TorchScript).
async fn send_model(
    ctx: &Ctx,
    file: &std::path::Path,
    name: String,
    upload: Upload,
    description: String,
) -> Result<pb::Model> {
    let (manifest, reward, autoencoder) = match upload {
        Upload::Diffusion(m) => (Some(m), None, None),
        Upload::Reward(r) => (None, Some(r), None),
        Upload::Autoencoder(a) => (None, None, Some(a)),
    };
    let native = manifest.as_ref().is_some_and(|m| m.architecture.is_some());
    let format = if native { pb::ModelFormat::Native } else { pb::ModelFormat::Torchscript };
    let size = std::fs::metadata(file).with_context(|| format!("{}", file.display()))?.len();
    let client = ctx.connect().await?;
    let progress = Arc::new(UploadProgress::default());
    progress.total_bytes.store(size, Ordering::Relaxed);
    let bar = byte_progress_bar(ctx.json);
    let (done_tx, done_rx) = oneshot::channel();
    let ticker = tokio::spawn(drive_progress(bar.clone(), Arc::clone(&progress), done_rx));
    let started = Instant::now();
    let header = pb::UploadModelHeader { name, manifest, description, format: format as i32, reward, autoencoder };
    let result = client.upload_model(header, file, Arc::clone(&progress)).await;
    let _ = done_tx.send(());
    let _ = ticker.await;
    bar.finish_and_clear();
    let model = result?;
    if !bar.is_hidden() {
        let secs = started.elapsed().as_secs_f64();
        let sent = progress.sent_bytes.load(Ordering::Relaxed);
        eprint_line(&format!("uploaded {} in {secs:.1} s", human_bytes(sent)));
    }
    Ok(model)
}

/// What `model import` reads: decided by the source (see [`ModelImportArgs`]).
enum ImportSource {
    Npz(PathBuf),
    /// A diffusers folder: a directory given, or a cache snapshot found by repository id.
    Folder {
        root: PathBuf,
        repo: Option<String>,
    },
}

impl ImportSource {
    /// A directory is a folder, a file a state_dict; a path that does not exist but has the form
    /// of a repository id is looked up in the Hugging Face cache (`revision`, default main).
    fn find(source: &str, revision: Option<&str>) -> Result<Self> {
        use relreward_toolkit::diffusers_import::{hub_cache, hub_snapshot, is_repo_id};
        let path = PathBuf::from(source);
        if path.is_dir() {
            return Ok(Self::Folder { root: path, repo: None });
        }
        if path.is_file() {
            return Ok(Self::Npz(path));
        }
        if !is_repo_id(source) {
            bail!("{source}: no such file or directory (nor a repository id, ORG/NAME)");
        }
        let Some(cache) = hub_cache(&|k| std::env::var(k).ok()) else {
            bail!("{source}: no Hugging Face cache to look in (set HF_HOME or HF_HUB_CACHE)");
        };
        let root = hub_snapshot(&cache, source, revision.unwrap_or("main"))?;
        Ok(Self::Folder { root, repo: Some(source.to_owned()) })
    }
}

/// A converted model, before anything is written.
struct Converted {
    tensors: Vec<NamedTensor>,
    manifest: pb::DiffusionManifest,
    /// The manifest file to write beside the weights (a diffusers folder's): path and text.
    manifest_file: Option<(PathBuf, String)>,
    text: String,
    json: Value,
}

async fn import(ctx: &Ctx, args: ModelImportArgs) -> Result<Report> {
    // Every check before the first byte is written: a refused --name leaves no --out behind.
    if let Some(name) = &args.name {
        check_model_name("--name", name)?;
    }
    let source = ImportSource::find(&args.source, args.revision.as_deref())?;
    let converted = match &source {
        ImportSource::Npz(file) => convert_npz(file, &args)?,
        ImportSource::Folder { root, repo } => convert_folder(root, repo.as_deref(), &args)?,
    };
    let Converted { tensors, manifest, manifest_file, mut text, mut json } = converted;
    let ModelImportArgs { out, name, description, .. } = args;
    // Written beside their targets and renamed onto them only once everything succeeded (the
    // upload too, with --name): a failure at any step leaves --out (and the manifest) as they
    // were, never a partial file nor weights the command reported as failed.
    let staged = Staged::new(&out);
    write_safetensors(staged.path(), &tensors).with_context(|| format!("{}", out.display()))?;
    let staged_manifest = match &manifest_file {
        Some((path, body)) => {
            let staged = Staged::new(path);
            std::fs::write(staged.path(), body).with_context(|| format!("{}", path.display()))?;
            Some(staged)
        }
        None => None,
    };
    let model = match name {
        Some(name) => Some(
            send_model(ctx, staged.path(), name, Upload::Diffusion(manifest), description)
                .await
                .with_context(|| format!("{} was not written", out.display()))?,
        ),
        None => None,
    };
    staged.commit().with_context(|| format!("{}", out.display()))?;
    if let (Some(staged), Some((path, _))) = (staged_manifest, &manifest_file) {
        staged.commit().with_context(|| format!("{}", path.display()))?;
    }
    if let Some(model) = model {
        text.push_str(&format!("registered as model '{}' (native)\n", model.name));
        json["model"] = model_json(&model);
    }
    Ok(Report::ok(text, json))
}

/// Refuses the flags of the other form, naming each.
fn refuse_flags(given: &[(&str, bool)], form: &str) -> Result<()> {
    let named: Vec<&str> = given.iter().filter(|(_, set)| *set).map(|(flag, _)| *flag).collect();
    if named.is_empty() {
        return Ok(());
    }
    Err(UsageError(format!("{}: {form}", named.join(", "))).into())
}

/// A Diffuser state_dict (.npz). The architecture's limits are the engine's
/// (`TemporalUnet::validate`); checked here too so that a bad flag is named before the file is
/// read.
fn convert_npz(file: &std::path::Path, args: &ModelImportArgs) -> Result<Converted> {
    use relreward_toolkit::diffuser_import::{import_npz, temporal_unet_shapes};
    refuse_flags(
        &[
            ("--manifest-out", args.manifest_out.is_some()),
            ("--horizon", args.horizon.is_some()),
            ("--action-dim", args.action_dim.is_some()),
            ("--image-size", !args.image_size.is_empty()),
            ("--normalizer", args.normalizer.is_some()),
            ("--null-class", args.null_class.is_some()),
            ("--subfolder", args.subfolder.is_some()),
            ("--scheduler-config", args.scheduler_config.is_some()),
            ("--revision", args.revision.is_some()),
        ],
        "only for a diffusers folder (a directory or a repository id), not for a .npz state_dict",
    )?;
    let (Some(manifest), Some(dim), false) = (&args.manifest, args.dim, args.dim_mults.is_empty()) else {
        let missing: Vec<&str> = [
            ("--manifest", args.manifest.is_none()),
            ("--dim", args.dim.is_none()),
            ("--dim-mults", args.dim_mults.is_empty()),
        ]
        .iter()
        .filter(|(_, m)| *m)
        .map(|(f, _)| *f)
        .collect();
        return Err(UsageError(format!(
            "{}: required for a .npz state_dict ({} is a file; a diffusers folder is a directory)",
            missing.join(", "),
            file.display()
        ))
        .into());
    };
    let dim_mults = &args.dim_mults;
    let mut man = manifest::load(manifest)?;
    let Some(pb::diffusion_manifest::Space::Trajectory(space)) = man.space else {
        bail!("{}: space: a TemporalUnet needs a trajectory space", manifest.display());
    };
    let transition_dim = u64::from(space.action_dim) + u64::from(space.obs_dim);
    if dim == 0 || dim % 8 != 0 || dim > 1 << 20 {
        bail!("--dim: {dim} must be a positive multiple of 8 (GroupNorm with 8 groups), at most 2^20");
    }
    if dim_mults.len() > 16 || dim_mults.iter().any(|&m| m == 0 || dim * m > 1 << 20) {
        bail!("--dim-mults: {dim_mults:?} must hold 1 to 16 positive multipliers, each times --dim at most 2^20");
    }
    let factor = 1u64 << (dim_mults.len() - 1);
    if u64::from(space.horizon) % factor != 0 {
        bail!(
            "{}: space.horizon {} must be a multiple of 2^(levels - 1) = {factor} for --dim-mults {dim_mults:?}",
            manifest.display(),
            space.horizon
        );
    }
    // The flags are the architecture; one already in the manifest must say the same.
    let architecture = pb::diffusion_manifest::Architecture::TemporalUnet(pb::TemporalUnet {
        dim: Some(dim as u32),
        dim_mults: dim_mults.iter().map(|&m| m as u32).collect(),
    });
    if let Some(given) = &man.architecture
        && *given != architecture
    {
        bail!(
            "{}: architecture: {} disagrees with --dim {dim} --dim-mults {dim_mults:?}; remove it or make them agree",
            manifest.display(),
            architecture_text(Some(given))
        );
    }
    man.architecture = Some(architecture);
    let expected = temporal_unet_shapes(transition_dim, dim, dim_mults);
    let tensors = import_npz(file, args.prefix.as_deref().unwrap_or(""), &expected)?;
    let parameters: usize = tensors.iter().map(|(_, _, v)| v.len()).sum();
    let text = format!(
        "imported {} tensors ({parameters} parameters) from {} into {}\narchitecture = {{ kind = \"temporal_unet\", dim = {dim}, dim_mults = {dim_mults:?} }}\n",
        tensors.len(),
        file.display(),
        args.out.display()
    );
    let json = json!({
        "tensors": tensors.len(),
        "parameters": parameters,
        "weights": args.out.display().to_string(),
        "architecture": { "kind": "temporal_unet", "dim": dim, "dim_mults": dim_mults },
    });
    Ok(Converted { tensors, manifest: man, manifest_file: None, text, json })
}

/// A diffusers folder: the toolkit's `diffusers_import` reads both configs and the weights; the
/// manifest it derives is written beside the weights.
fn convert_folder(root: &std::path::Path, repo: Option<&str>, args: &ModelImportArgs) -> Result<Converted> {
    use relreward_toolkit::diffusers_import::{Hints, import_folder, locate};
    refuse_flags(
        &[
            ("--manifest", args.manifest.is_some()),
            ("--dim", args.dim.is_some()),
            ("--dim-mults", !args.dim_mults.is_empty()),
            ("--prefix", args.prefix.is_some()),
        ],
        "only for a .npz state_dict, not for a diffusers folder (its config.json gives the architecture and its \
         scheduler_config.json the manifest, written to --manifest-out)",
    )?;
    if repo.is_none() && args.revision.is_some() {
        return Err(UsageError(format!("--revision: for a repository id; {} is a directory", root.display())).into());
    }
    let image_size = match args.image_size.as_slice() {
        [] => None,
        [s] => Some((*s, *s)),
        [h, w] => Some((*h, *w)),
        more => return Err(UsageError(format!("--image-size: {more:?}; give H or H,W")).into()),
    };
    let normalizer = args.normalizer.as_deref().map(manifest::read_file).transpose()?;
    let hints = Hints {
        horizon: args.horizon,
        action_dim: args.action_dim,
        image_size,
        normalizer,
        null_class: args.null_class,
    };
    let folder = locate(root, args.subfolder.as_deref(), args.scheduler_config.as_deref())?;
    let imported = import_folder(&folder, &hints)?;
    let manifest_path = args.manifest_out.clone().unwrap_or_else(|| default_manifest_path(&args.out));
    let from = repo
        .map_or_else(|| folder.model_dir.display().to_string(), |r| format!("{r} ({})", folder.model_dir.display()));
    let body =
        manifest_text(&imported.manifest, &manifest_path, &from, imported.class.name(), &imported.schedule_source)?;
    let man = imported.manifest.to_proto();
    let tensors = imported.tensors;
    let parameters: usize = tensors.iter().map(|(_, _, v)| v.len()).sum();
    let text = format!(
        "imported {} from {from} ({} tensors, {parameters} parameters) into {}\n\
         manifest {}: {} parametrization, T = {} ({} betas), clip_denoised {}, space {}, normalizer {}\n\
         architecture {}\n",
        imported.class.name(),
        tensors.len(),
        args.out.display(),
        manifest_path.display(),
        parametrization_name(man.parametrization()).unwrap_or("-"),
        man.n_timesteps,
        imported.schedule_source,
        man.clip_denoised,
        space_text(man.space.as_ref()),
        normalizer_text(man.normalizer.as_ref()),
        architecture_text(man.architecture.as_ref()),
    );
    let json = json!({
        "source": from,
        "class": imported.class.name(),
        "tensors": tensors.len(),
        "parameters": parameters,
        "weights": args.out.display().to_string(),
        "manifest_file": manifest_path.display().to_string(),
        "manifest": manifest_json(&man),
    });
    Ok(Converted { tensors, manifest: man, manifest_file: Some((manifest_path, body)), text, json })
}

/// `weights.safetensors` -> `weights.manifest.toml`, beside it.
fn default_manifest_path(out: &std::path::Path) -> PathBuf {
    out.with_extension("manifest.toml")
}

/// The derived manifest as a file: JSON for a `.json` name, TOML otherwise, with a comment
/// saying where it came from (TOML only).
fn manifest_text(
    man: &relreward_proto::schema::manifest::DiffusionManifest,
    path: &std::path::Path,
    from: &str,
    class: &str,
    schedule: &str,
) -> Result<String> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) {
        return Ok(serde_json::to_string_pretty(man)? + "\n");
    }
    let normalizer = if man.normalizer == relreward_proto::schema::manifest::Normalizer::Identity {
        "# A diffusers folder holds no normalizer: set the one the model was trained under.\n"
    } else {
        ""
    };
    Ok(format!(
        "# Derived by `relreward model import` from {from}\n# ({class}; DDPMScheduler, {schedule} betas as diffusers \
         computes them).\n{normalizer}{}",
        toml::to_string(man)?
    ))
}

/// The server's naming rule (`[a-z0-9][a-z0-9._-]{0,63}`), checked before any work so that a
/// name the server would refuse is named first and costs nothing.
fn check_model_name(flag: &str, name: &str) -> Result<()> {
    let mut chars = name.chars();
    let first = chars.next().is_some_and(|c| c.is_ascii_lowercase() || c.is_ascii_digit());
    let rest = chars.all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || matches!(c, '.' | '_' | '-'));
    if first && rest && name.len() <= 64 {
        return Ok(());
    }
    let shown: String = name.chars().take(64).collect();
    Err(UsageError(format!(
        "{flag}: {shown:?}{} is not a valid model name (1 to 64 characters, [a-z0-9] then [a-z0-9._-])",
        if shown.len() < name.len() { "..." } else { "" }
    ))
    .into())
}

/// A file written beside its target and renamed onto it by [`Staged::commit`]; removed when
/// dropped uncommitted.
struct Staged {
    target: PathBuf,
    path: PathBuf,
    committed: bool,
}

impl Staged {
    fn new(target: &std::path::Path) -> Self {
        let mut file_name = target.file_name().map(std::ffi::OsString::from).unwrap_or_else(|| "weights".into());
        file_name.push(format!(".partial-{}", std::process::id()));
        Self { target: target.to_owned(), path: target.with_file_name(file_name), committed: false }
    }

    fn path(&self) -> &std::path::Path {
        &self.path
    }

    fn commit(mut self) -> std::io::Result<()> {
        std::fs::rename(&self.path, &self.target)?;
        self.committed = true;
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

async fn list(ctx: &Ctx, kind: Option<ModelKindArg>) -> Result<Report> {
    let kind = kind.map_or(pb::ModelKind::Unspecified, ModelKindArg::to_proto);
    let models = ctx.connect().await?.list_models(kind).await?;
    Ok(Report::ok(format_model_table(&models), Value::Array(models.iter().map(model_json).collect())))
}

async fn show(ctx: &Ctx, name: &str) -> Result<Report> {
    let model = ctx.connect().await?.get_model(name).await?;
    Ok(Report::ok(format_model(&model), model_json(&model)))
}

/// `model download`, or with `export` `model export` (the same files plus the traced module.pt).
async fn download(ctx: &Ctx, args: ModelDownloadArgs, export: bool) -> Result<Report> {
    let ModelDownloadArgs { name, out, force } = args;
    let client = ctx.connect().await?;
    let got = if export {
        client.export_model(&name, &out, force).await?
    } else {
        client.download_model(&name, &out, force).await?
    };
    let paths: Vec<String> = got.files.iter().chain([&got.manifest_path]).map(|p| p.display().to_string()).collect();
    let text = format!(
        "downloaded {} ({}, sha256 {}) into {}\n{}\n",
        got.model.name,
        human_bytes(got.model.size_bytes),
        got.model.sha256,
        out.display(),
        paths.iter().map(|p| format!("  {p}")).collect::<Vec<_>>().join("\n")
    );
    let json = json!({
        "model": model_json(&got.model),
        "weights": got.weights().display().to_string(),
        "manifest": got.manifest_path.display().to_string(),
        "files": paths,
    });
    Ok(Report::ok(text, json))
}

async fn recipe(ctx: &Ctx, args: ModelRecipeArgs) -> Result<Report> {
    check_model_name("NAME", &args.name)?;
    check_model_name("--model", &args.model)?;
    let Some(prompts) = args.recipe.prompts() else {
        return Err(UsageError("--labels: missing; a recipe needs the prompt set it samples under".into()).into());
    };
    let req = pb::CreateRecipeRequest {
        name: args.name.clone(),
        model: args.model.clone(),
        recipe: Some(pb::SamplingRecipe {
            prompts: Some(prompts),
            guidance_scale: args.recipe.guidance_scale,
            safety: args.recipe.safety(),
        }),
        description: args.description,
    };
    let fields: Vec<(&str, String)> = [
        ("name", "NAME".to_owned()),
        ("model", format!("--model {}", args.model)),
        ("recipe", "the recipe flags".into()),
    ]
    .into_iter()
    .collect();
    let model = ctx.connect().await?.create_recipe(req).await.map_err(|e| match flag_of(&e, &fields) {
        Some(flag) => anyhow::Error::new(e).context(flag),
        None => anyhow::Error::new(e),
    })?;
    Ok(Report::ok(format_model(&model), model_json(&model)))
}

async fn delete(ctx: &Ctx, name: &str) -> Result<Report> {
    ctx.connect().await?.delete_model(name).await?;
    Ok(Report::ok(format!("deleted {name}\n"), json!({ "deleted": name })))
}

// ---------------------------------------------------------------------------------------------
// Output: JSON

pub fn kind_name(kind: pb::ModelKind) -> &'static str {
    match kind {
        pb::ModelKind::Diffusion => "diffusion",
        pb::ModelKind::Reward => "reward",
        pb::ModelKind::Discriminator => "discriminator",
        pb::ModelKind::Autoencoder => "autoencoder",
        pb::ModelKind::Recipe => "recipe",
        pb::ModelKind::Unspecified => "unspecified",
    }
}

fn format_name(format: pb::ModelFormat) -> &'static str {
    match format {
        pb::ModelFormat::Torchscript => "torchscript",
        pb::ModelFormat::Native => "native",
        pb::ModelFormat::Recipe => "recipe",
        pb::ModelFormat::Unspecified => "unspecified",
    }
}

/// A model as JSON:
///
/// ```json
/// {"name": "..", "kind": "diffusion" | "reward" | "discriminator" | "autoencoder" | "recipe",
///  "format": "torchscript" | "native" | "recipe", "parameter_count": N, "sha256": "..",
///  "size_bytes": N, "created_at": "RFC3339" | null, "description": "..",
///  "provenance": {"source": "uploaded" | "trained", "job_id": ".." | null,
///                 "datasets": [..], "models": [..], "final_loss": X | null} | null,
///  "manifest": {see manifest::manifest_json} | null,
///  "reward": {"base_model": "..", "expert_model": "..", "architecture": "..", "window": N,
///             "input_shape": [..], "n_timesteps": T, "normalizer": {..},
///             "base_recipe": {recipe} | null, "expert_recipe": {recipe} | null} | null,
///  "recipe": {see recipe_json} | null,
///  "autoencoder": {"image_shape": [..], "latent_shape": [..], "scaling_factor": X,
///                  "shift_factor": X} | null}
/// ```
///
/// Non-finite numbers are written as `null`.
pub fn model_json(m: &pb::Model) -> Value {
    json!({
        "name": m.name,
        "kind": kind_name(m.kind()),
        "format": format_name(m.format()),
        "parameter_count": m.parameter_count,
        "sha256": m.sha256,
        "size_bytes": m.size_bytes,
        "created_at": m.created_at.as_ref().map(rfc3339),
        "description": m.description,
        "provenance": m.provenance.as_ref().and_then(provenance_json),
        "manifest": m.manifest.as_ref().map(manifest_json),
        "reward": m.reward.as_ref().map(|r| json!({
            "base_model": r.base_model,
            "expert_model": r.expert_model,
            "architecture": r.architecture,
            "window": r.window,
            "input_shape": r.input_shape,
            "n_timesteps": r.n_timesteps,
            "normalizer": normalizer_json(r.normalizer.as_ref()),
            "base_recipe": r.base_recipe.as_ref().map(recipe_json),
            "expert_recipe": r.expert_recipe.as_ref().map(recipe_json),
        })),
        "recipe": m.recipe.as_ref().map(recipe_json),
        "autoencoder": m.autoencoder.as_ref().map(|a| json!({
            "image_shape": a.image_shape,
            "latent_shape": a.latent_shape,
            "scaling_factor": a.scaling_factor,
            "shift_factor": a.shift_factor,
        })),
    })
}

/// A recipe as JSON (the Python client's `RecipeInfo.as_dict()`): {"model", "model_sha256",
/// "recipe": {"prompts": [labels] | [[embedding], ..], "guidance_scale": X | null,
/// "safety": {"concept": (as prompts), "scale", "warmup_steps", "threshold", "momentum_scale",
/// "momentum_beta"} | null}, "prompt_dataset": ".." | null}.
fn recipe_json(r: &pb::RecipeInfo) -> Value {
    let prompts = |p: Option<&pb::Prompts>| -> Value {
        match p {
            Some(pb::Prompts { embeddings: Some(e), .. }) => {
                let values = relreward_client::tensor::decode_finite_f32(e).unwrap_or_default();
                let dim = e.shape.last().copied().unwrap_or(1).max(1) as usize;
                if e.shape.len() == 1 {
                    json!(values)
                } else {
                    Value::Array(values.chunks(dim).map(|row| json!(row)).collect())
                }
            }
            Some(p) => json!(p.labels),
            None => Value::Null,
        }
    };
    let spec = r.recipe.clone().unwrap_or_default();
    json!({
        "model": r.model,
        "model_sha256": r.model_sha256,
        "recipe": {
            "prompts": prompts(spec.prompts.as_ref()),
            "guidance_scale": spec.guidance_scale,
            "safety": spec.safety.as_ref().map(|s| json!({
                "concept": prompts(s.concept.as_ref()),
                "scale": s.scale,
                "warmup_steps": s.warmup_steps,
                "threshold": s.threshold,
                "momentum_scale": s.momentum_scale,
                "momentum_beta": s.momentum_beta,
            })),
        },
        "prompt_dataset": (!r.prompt_dataset.is_empty()).then_some(&r.prompt_dataset),
    })
}

/// A recipe in one line: "model m, labels [..], guidance 3, safety from [..] (scale .., ..)".
fn recipe_text(r: &pb::RecipeInfo) -> String {
    let prompts = |p: Option<&pb::Prompts>| match p {
        Some(p) if !p.labels.is_empty() => format!("labels {:?}", p.labels),
        Some(p) => format!("embeddings {:?}", p.embeddings.as_ref().map(|e| e.shape.clone()).unwrap_or_default()),
        None => "-".to_owned(),
    };
    let spec = r.recipe.clone().unwrap_or_default();
    let mut text = format!(
        "model {}, {}, guidance {}",
        r.model,
        prompts(spec.prompts.as_ref()),
        spec.guidance_scale.unwrap_or(1.0)
    );
    if let Some(s) = &spec.safety {
        text.push_str(&format!(
            ", safety from {} (scale {}, warm-up {}, threshold {}, momentum {} / {})",
            prompts(s.concept.as_ref()),
            fmt_short(s.scale),
            s.warmup_steps,
            fmt_short(s.threshold),
            fmt_short(s.momentum_scale),
            fmt_short(s.momentum_beta)
        ));
    }
    text
}

fn provenance_json(p: &pb::Provenance) -> Option<Value> {
    use pb::provenance::Source;
    Some(match p.source.as_ref()? {
        Source::Uploaded(_) => {
            json!({ "source": "uploaded", "job_id": null, "datasets": [], "models": [], "final_loss": null })
        }
        Source::Trained(t) => json!({
            "source": "trained",
            "job_id": t.job_id,
            "datasets": t.datasets,
            "models": t.models,
            "final_loss": t.final_loss,
        }),
    })
}

// ---------------------------------------------------------------------------------------------
// Output: text

fn provenance_text(p: Option<&pb::Provenance>) -> String {
    use pb::provenance::Source;
    match p.and_then(|p| p.source.as_ref()) {
        Some(Source::Uploaded(_)) => "uploaded".to_owned(),
        Some(Source::Trained(t)) => {
            let mut inputs = Vec::new();
            if !t.datasets.is_empty() {
                inputs.push(format!("datasets {}", t.datasets.join(", ")));
            }
            if !t.models.is_empty() {
                inputs.push(format!("models {}", t.models.join(", ")));
            }
            inputs.push(format!("final loss {}", fmt_short(t.final_loss)));
            format!("trained by job {} ({})", t.job_id, inputs.join("; "))
        }
        None => "-".to_owned(),
    }
}

/// `model show`: a key/value block, then the manifest or the reward details.
fn format_model(m: &pb::Model) -> String {
    let fields = [
        ("name", m.name.clone()),
        ("kind", kind_name(m.kind()).to_owned()),
        ("format", format_name(m.format()).to_owned()),
        ("parameters", m.parameter_count.to_string()),
        ("size", format!("{} ({} bytes)", human_bytes(m.size_bytes), m.size_bytes)),
        ("sha256", m.sha256.clone()),
        ("created", time_or_dash(m.created_at.as_ref())),
        ("description", or_dash(&m.description)),
        ("source", provenance_text(m.provenance.as_ref())),
    ];
    let mut out = key_values(&fields, 0);
    if let Some(man) = &m.manifest {
        out.push_str("\nmanifest\n");
        let fields = [
            ("parametrization", parametrization_name(man.parametrization()).unwrap_or("-").to_owned()),
            ("schedule", schedule_text(man.schedule.as_ref())),
            ("n_timesteps", man.n_timesteps.to_string()),
            ("clip_denoised", man.clip_denoised.to_string()),
            ("space", space_text(man.space.as_ref())),
            ("normalizer", normalizer_text(man.normalizer.as_ref())),
            ("architecture", architecture_text(man.architecture.as_ref())),
        ];
        out.push_str(&key_values(&fields, 2));
    }
    if let Some(r) = &m.reward {
        out.push_str("\nreward\n");
        let fields = [
            ("base model", or_dash(&r.base_model)),
            ("expert model", or_dash(&r.expert_model)),
            ("architecture", or_dash(&r.architecture)),
            ("window", if r.window == 0 { "-".to_owned() } else { r.window.to_string() }),
            ("input shape", format!("{:?}", r.input_shape)),
            ("diffusion steps", r.n_timesteps.to_string()),
            ("normalizer", normalizer_text(r.normalizer.as_ref())),
            ("base recipe", r.base_recipe.as_ref().map_or_else(|| "-".to_owned(), recipe_text)),
            ("expert recipe", r.expert_recipe.as_ref().map_or_else(|| "-".to_owned(), recipe_text)),
        ];
        out.push_str(&key_values(&fields, 2));
    }
    if let Some(r) = &m.recipe {
        out.push_str("\nrecipe\n");
        let fields = [("samples", recipe_text(r)), ("model sha256", r.model_sha256.clone())];
        out.push_str(&key_values(&fields, 2));
    }
    if let Some(a) = &m.autoencoder {
        out.push_str("\nautoencoder\n");
        let fields = [
            ("image shape", format!("{:?}", a.image_shape)),
            ("latent shape", format!("{:?}", a.latent_shape)),
            ("scaling factor", fmt_short(a.scaling_factor)),
            ("shift factor", fmt_short(a.shift_factor)),
        ];
        out.push_str(&key_values(&fields, 2));
    }
    out
}

/// `model list`: one model per row.
fn format_model_table(models: &[pb::Model]) -> String {
    if models.is_empty() {
        return "no models\n".to_owned();
    }
    let rows = models
        .iter()
        .map(|m| {
            vec![
                m.name.clone(),
                kind_name(m.kind()).to_owned(),
                format_name(m.format()).to_owned(),
                m.parameter_count.to_string(),
                human_bytes(m.size_bytes),
                time_or_dash(m.created_at.as_ref()),
            ]
        })
        .collect();
    table(&["NAME", "KIND", "FORMAT", "PARAMS", "SIZE", "CREATED"], &[false, false, false, true, true, false], rows, 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uploaded() -> pb::Model {
        use pb::diffusion_manifest::{Space, Trajectory};
        pb::Model {
            name: "maze-base".into(),
            kind: pb::ModelKind::Diffusion as i32,
            format: pb::ModelFormat::Torchscript as i32,
            manifest: Some(pb::DiffusionManifest {
                parametrization: pb::Parametrization::Epsilon as i32,
                schedule: Some(pb::Schedule { kind: Some(pb::schedule::Kind::Linear(pb::schedule::Linear {})) }),
                n_timesteps: 20,
                clip_denoised: false,
                space: Some(Space::Trajectory(Trajectory { horizon: 8, action_dim: 2, obs_dim: 4 })),
                normalizer: None,
                architecture: None,
                conditioning: None,
            }),
            reward: None,
            parameter_count: 1234,
            sha256: "cd".repeat(32),
            size_bytes: 4096,
            provenance: Some(pb::Provenance { source: Some(pb::provenance::Source::Uploaded(Default::default())) }),
            created_at: Some(prost_types::Timestamp { seconds: 1_714_564_800, nanos: 0 }),
            description: String::new(),
            autoencoder: None,
            recipe: None,
        }
    }

    fn trained_reward() -> pb::Model {
        pb::Model {
            name: "maze-reward".into(),
            kind: pb::ModelKind::Reward as i32,
            format: pb::ModelFormat::Native as i32,
            manifest: None,
            reward: Some(pb::RewardInfo {
                base_model: "base".into(),
                expert_model: "expert".into(),
                architecture: "windowed_mlp(h=4)".into(),
                window: 4,
                input_shape: vec![8, 6],
                normalizer: None,
                n_timesteps: 20,
                ..Default::default()
            }),
            provenance: Some(pb::Provenance {
                source: Some(pb::provenance::Source::Trained(pb::provenance::Trained {
                    job_id: "j1".into(),
                    datasets: vec!["maze".into()],
                    models: vec!["base".into(), "expert".into()],
                    final_loss: 0.5,
                })),
            }),
            ..uploaded()
        }
    }

    /// The manifest `model import` writes for a diffusers folder reads back as the same
    /// manifest, in both forms, through the loader `model upload` uses.
    #[test]
    fn a_derived_manifest_file_reads_back() {
        use relreward_proto::schema::manifest::{
            Architecture, DiffusionManifest, Normalizer, Parametrization, ScheduleSpec, Space,
        };
        let man = DiffusionManifest {
            parametrization: Parametrization::X0,
            schedule: ScheduleSpec::Betas { betas: vec![f64::from(1e-4f32), 0.5, 0.999] },
            n_timesteps: 3,
            clip_denoised: true,
            space: Space::Trajectory { horizon: 8, action_dim: 2, obs_dim: 3 },
            normalizer: Normalizer::Identity,
            conditioning: None,
            architecture: Some(Architecture::TemporalUnet { dim: 8, dim_mults: vec![1, 2] }),
        };
        for name in ["w.manifest.toml", "m.json"] {
            let path = std::path::Path::new(name);
            let text = manifest_text(&man, path, "DIR", "UNet1DModel", "squaredcos_cap_v2").unwrap();
            let back = manifest::load_text(&text, path).unwrap_or_else(|e| panic!("{name}: {e:#}\n{text}"));
            assert_eq!(back, man.to_proto(), "{name}:\n{text}");
        }
        assert_eq!(
            default_manifest_path(std::path::Path::new("out/w.safetensors")),
            PathBuf::from("out/w.manifest.toml")
        );
    }

    #[test]
    fn model_json_has_the_documented_shape() {
        let v = model_json(&uploaded());
        let keys: Vec<&str> = v.as_object().expect("object").keys().map(String::as_str).collect();
        let mut expected = [
            "name",
            "kind",
            "format",
            "parameter_count",
            "sha256",
            "size_bytes",
            "created_at",
            "description",
            "provenance",
            "manifest",
            "reward",
            "autoencoder",
            "recipe",
        ];
        expected.sort_unstable();
        assert_eq!(keys, expected);
        assert_eq!(v["kind"], "diffusion");
        assert_eq!(v["format"], "torchscript");
        assert_eq!(v["parameter_count"], 1234);
        assert_eq!(v["created_at"], "2024-05-01T12:00:00Z");
        assert_eq!(
            v["provenance"],
            json!({"source": "uploaded", "job_id": null, "datasets": [], "models": [], "final_loss": null})
        );
        assert_eq!(v["manifest"]["parametrization"], "epsilon");
        assert_eq!(v["manifest"]["schedule"], json!({"kind": "linear"}));
        assert_eq!(v["manifest"]["space"], json!({"kind": "trajectory", "horizon": 8, "action_dim": 2, "obs_dim": 4}));
        assert!(v["reward"].is_null());

        let v = model_json(&trained_reward());
        assert_eq!(v["kind"], "reward");
        assert_eq!(v["format"], "native");
        assert!(v["manifest"].is_null());
        assert_eq!(
            v["provenance"],
            json!({"source": "trained", "job_id": "j1", "datasets": ["maze"], "models": ["base", "expert"], "final_loss": 0.5})
        );
        assert_eq!(v["reward"]["window"], 4);
        assert_eq!(v["reward"]["input_shape"], json!([8, 6]));
        assert_eq!(v["reward"]["normalizer"], json!({"kind": "identity"}));
        assert!(v["autoencoder"].is_null());

        let v = model_json(&autoencoder());
        assert_eq!((v["kind"].as_str(), v["format"].as_str()), (Some("autoencoder"), Some("torchscript")));
        assert!(v["manifest"].is_null() && v["reward"].is_null());
        assert_eq!(
            v["autoencoder"],
            json!({"image_shape": [3, 16, 16], "latent_shape": [4, 8, 8], "scaling_factor": 0.18215, "shift_factor": 0.0})
        );
        let text = format_model(&autoencoder());
        for needle in ["kind         autoencoder", "image shape     [3, 16, 16]", "latent shape    [4, 8, 8]"] {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
    }

    fn autoencoder() -> pb::Model {
        pb::Model {
            name: "vae".into(),
            kind: pb::ModelKind::Autoencoder as i32,
            manifest: None,
            autoencoder: Some(pb::AutoencoderInfo {
                image_shape: vec![3, 16, 16],
                latent_shape: vec![4, 8, 8],
                scaling_factor: 0.18215,
                shift_factor: 0.0,
            }),
            ..uploaded()
        }
    }

    #[test]
    fn text_output_shows_every_field() {
        let text = format_model(&uploaded());
        for needle in [
            "maze-base",
            "torchscript",
            "parameters   1234",
            "4.0 KiB (4096 bytes)",
            "source       uploaded",
            "parametrization  epsilon",
            "trajectory (horizon 8, action_dim 2, obs_dim 4)",
            "normalizer       identity",
        ] {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
        let text = format_model(&trained_reward());
        for needle in ["trained by job j1 (datasets maze; models base, expert; final loss 0.5000)", "windowed_mlp(h=4)"]
        {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
        let list = format_model_table(&[uploaded(), trained_reward()]);
        assert!(list.starts_with("NAME"), "{list}");
        assert!(list.contains("maze-reward  reward     native"), "{list}");
        assert_eq!(format_model_table(&[]), "no models\n");
    }
}

//! `relreward.v1.ModelService`: register diffusion models (TorchScript modules or native
//! safetensors weights), bring-your-own rewards and autoencoders (TorchScript modules), and
//! named sampling recipes (`CreateRecipe`: JSON over a stored conditional model, its sha256
//! pinned; the model cannot be deleted while a recipe samples it); get, list, delete, download.
//!
//! Upload protocol (one client stream): a `header` (name, manifest, description, format), the
//! file's bytes in `chunk`s, then a `commit` with the file's sha256. The order of checks is
//! cheapest first, and nothing is visible until the last step:
//!
//! 1. the header: format (a TorchScript upload also needs `models.allow_torchscript_upload`,
//!    off by default: a TorchScript file is a program; native weights are data), name, no
//!    existing model of that name, the manifest converted and validated: a diffusion
//!    manifest's architecture present exactly when the format is native; a reward's
//!    (`header.reward`) TorchScript only, its base model, if named, agreeing with it; an
//!    autoencoder's (`header.autoencoder`) TorchScript only, alone in the header;
//! 2. the bytes, streamed into a staging file, hashed, bounded by `models.max_upload_bytes`;
//! 3. the commit digest;
//! 4. the file itself, on a blocking thread: a module loaded and run once on zeros of the
//!    declared shape (`engine::torchscript`; a reward's also differentiated once with respect
//!    to x; an autoencoder's encode and decode each once, `engine::autoencoder`); native
//!    weights loaded strictly into the
//!    architecture (every tensor named, float32, of its shape, nothing extra) and run once the
//!    same way (`ModelRegistry::validate_native`);
//! 5. `manifest.json` written next to the file, the staging directory published and the record
//!    inserted (`Store::commit_model`).
//!
//! Any error, or a stream that ends early, drops the `Staging` guard, which removes the files.
//!
//! Download (`DownloadModel`, server streaming, the mirror of upload): the record, its blob's
//! files checked against their digests on a blocking thread (a corrupt model is `DataLoss`
//! before a byte leaves), then one `header` (the record, the stored manifest as JSON, each
//! file's name, size and sha256) and the files' bytes in chunks bounded by
//! `server.max_response_bytes`. The files are opened before the header is sent, so a model
//! deleted meanwhile still streams whole (its blob is immutable until removed). With
//! `torchscript` (the export), the stored native network is traced into a module on a blocking
//! thread (`registry::export_torchscript`, `engine::export`) and sent as a last file.

use std::path::Path;
use std::pin::Pin;

use futures::Stream;
use relreward_proto::v1::{self as pb, model_service_server::ModelService, upload_model_request::Message};
use sha2::{Digest, Sha256};
use tokio::io::AsyncReadExt;
use tonic::{Request, Response, Status, Streaming};

use super::convert::{diffusion_manifest_from_proto, model_kind_filter_from_proto, model_to_proto};
use super::{next_upload, page_limit};
use crate::config::ModelsConfig;
use crate::engine::autoencoder::AutoencoderManifest;
use crate::engine::manifest::{DiffusionManifest, RewardUploadManifest};
use crate::engine::relative_reward::RewardManifest;
use crate::error::{Error, Result};
use crate::fields::{self, validate_name};
use crate::jobs::JobManager;
use crate::limits::DiskBudget;
use crate::registry::ModelRegistry;
use crate::store::digests::{self, DIGEST_FILE, Verified};
use crate::store::ingest::now_ms;
use crate::store::{ModelFormat, ModelKind, ModelRecord, Provenance, Store};
use relreward_proto::schema::recipe::{RecipeManifest, RecipeSpec};

/// File names inside an uploaded model's blob (native weights keep the name training jobs give
/// them, `weights.safetensors`).
pub const MODULE_FILE: &str = "module.pt";
pub const WEIGHTS_FILE: &str = "weights.safetensors";
pub const MANIFEST_FILE: &str = "manifest.json";
/// A recipe's one file: its manifest (JSON).
pub const RECIPE_FILE: &str = "recipe.json";

/// Model records read per page when looking for the recipes that sample a model.
const RECIPE_SCAN_PAGE: usize = 256;

/// An upload of unknown size reserves disk budget in steps of this many bytes as it grows.
const BUDGET_STEP: u64 = 64 << 20;

/// Largest file chunk of a download (the clients' upload chunk too).
const DOWNLOAD_CHUNK_BYTES: usize = 1 << 20;
/// What a chunk message adds to its bytes (oneof tag and length), with room to spare.
const CHUNK_FRAMING_BYTES: usize = 64;

type DownloadStream = Pin<Box<dyn Stream<Item = Result<pb::DownloadModelResponse, Status>> + Send + 'static>>;

pub struct Models {
    store: Store,
    registry: ModelRegistry,
    jobs: JobManager,
    config: ModelsConfig,
    budget: DiskBudget,
    /// Bytes per download chunk: [`DOWNLOAD_CHUNK_BYTES`], less where `server.max_response_bytes`
    /// would not fit it.
    chunk_bytes: usize,
}

impl Models {
    /// `max_response_bytes`: the server's `server.max_response_bytes`, which every streamed
    /// download chunk must fit.
    pub fn new(
        store: Store,
        registry: ModelRegistry,
        jobs: JobManager,
        config: ModelsConfig,
        budget: DiskBudget,
        max_response_bytes: usize,
    ) -> Self {
        let chunk_bytes = DOWNLOAD_CHUNK_BYTES.min(max_response_bytes.saturating_sub(CHUNK_FRAMING_BYTES)).max(1);
        Self { store, registry, jobs, config, budget, chunk_bytes }
    }

    async fn upload(&self, mut stream: Streaming<pb::UploadModelRequest>) -> Result<pb::Model> {
        let header = match next_upload(&mut stream, |m: pb::UploadModelRequest| m.message).await? {
            Some(Message::Header(h)) => h,
            Some(_) => return Err(Error::invalid("message 1: the first message of an upload must be a header")),
            None => return Err(Error::invalid("upload stream was empty: expected a header, chunks and a commit")),
        };
        let format = match fields::known::<pb::ModelFormat>(
            "header.format",
            header.format,
            "MODEL_FORMAT_TORCHSCRIPT (the default) or MODEL_FORMAT_NATIVE",
        )? {
            pb::ModelFormat::Unspecified | pb::ModelFormat::Torchscript => ModelFormat::Torchscript,
            pb::ModelFormat::Native => ModelFormat::Native,
            pb::ModelFormat::Recipe => {
                return Err(Error::invalid(
                    "header.format: MODEL_FORMAT_RECIPE is not uploaded; register a recipe with \
                     ModelService.CreateRecipe",
                ));
            }
        };
        if format == ModelFormat::Torchscript && !self.config.allow_torchscript_upload {
            return Err(Error::FailedPrecondition(
                "ModelService.UploadModel of TorchScript is disabled on this server: a TorchScript file is a program \
                 that would run inside the server, so such uploads are refused unless the operator sets \
                 models.allow_torchscript_upload = true (environment variable \
                 RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD=true); native safetensors weights of a built-in \
                 architecture (header.format = MODEL_FORMAT_NATIVE, e.g. from `relreward model import`) are accepted"
                    .into(),
            ));
        }
        validate_name("header.name", &header.name)?;
        fields::check_description("header.description", &header.description)?;
        if self.store.meta.get_model(&header.name).await?.is_some() {
            return Err(Error::AlreadyExists(format!("header.name: model '{}' already exists", header.name)));
        }
        let (manifest, file_name) = match (header.reward, header.autoencoder) {
            (Some(_), Some(_)) => {
                return Err(Error::invalid(
                    "header.autoencoder: set together with header.reward; one upload registers one model",
                ));
            }
            (Some(reward), None) => {
                (Manifest::Reward(self.reward_manifest(reward, header.manifest, format).await?), MODULE_FILE)
            }
            (None, Some(autoencoder)) => {
                (Manifest::Autoencoder(autoencoder_manifest(autoencoder, header.manifest, format)?), MODULE_FILE)
            }
            (None, None) => {
                let manifest = diffusion_manifest_from_proto(header.manifest, "header.manifest")?;
                let file_name = diffusion_file_name(format, &manifest)?;
                (Manifest::Diffusion(manifest), file_name)
            }
        };

        let staging = self.store.blobs.staging()?;
        let file_path = staging.path().join(file_name);
        let mut file = std::fs::File::create(&file_path)?;
        let mut hasher = Sha256::new();
        let mut size = 0u64;
        let max = self.config.max_upload_bytes;
        // The header declares no size: the disk budget (storage.max_bytes) is reserved step by
        // step as chunks arrive, and given back when the upload ends either way.
        let mut reservations = Vec::new();
        let mut reserved = 0u64;
        let digest = loop {
            match next_upload(&mut stream, |m: pb::UploadModelRequest| m.message).await? {
                Some(Message::Chunk(bytes)) => {
                    size = size.saturating_add(bytes.len() as u64);
                    if size > max {
                        return Err(Error::ResourceExhausted(format!(
                            "chunk: the file exceeds models.max_upload_bytes ({max} bytes)"
                        )));
                    }
                    if size > reserved {
                        let step = BUDGET_STEP.min(max - reserved).max(size - reserved);
                        let what = format!("chunk: model '{}'", header.name);
                        reservations.push(tokio::task::block_in_place(|| self.budget.reserve(step, &what))?);
                        reserved += step;
                    }
                    tokio::task::block_in_place(|| -> Result<()> {
                        use std::io::Write;
                        hasher.update(&bytes);
                        file.write_all(&bytes)?;
                        Ok(())
                    })?;
                }
                Some(Message::Commit(c)) => break c.sha256,
                Some(Message::Header(_)) => {
                    return Err(Error::invalid("header: sent twice; one upload has one header"));
                }
                None => return Err(Error::invalid("upload ended without a commit message; nothing was stored")),
            }
        };
        if next_upload(&mut stream, |m: pb::UploadModelRequest| m.message).await?.is_some() {
            return Err(Error::invalid("commit: must be the last message of the upload"));
        }
        drop(file);
        if size == 0 {
            return Err(Error::invalid("chunk: no bytes of the file were uploaded"));
        }
        let sha256 = hex::encode(hasher.finalize());
        if !digest.eq_ignore_ascii_case(&sha256) {
            return Err(Error::invalid(format!(
                "commit.sha256: {} does not match the uploaded bytes (sha256 {sha256}); nothing was stored",
                crate::error::quote(&digest)
            )));
        }

        let (kind, parameter_count, manifest_json) = match manifest {
            Manifest::Diffusion(manifest) => {
                let parameter_count = match format {
                    ModelFormat::Torchscript => self.registry.validate_torchscript(file_path, manifest.clone()).await?,
                    ModelFormat::Native => self.registry.validate_native(file_path, manifest.clone()).await?,
                    // Refused with the header above.
                    ModelFormat::Recipe => return Err(Error::internal("UploadModel", "a recipe format upload")),
                };
                (ModelKind::Diffusion, parameter_count, serde_json::to_value(&manifest))
            }
            Manifest::Reward(manifest) => {
                let parameter_count = self.registry.validate_torchscript_reward(file_path, manifest.clone()).await?;
                (ModelKind::Reward, parameter_count, serde_json::to_value(RewardManifest::uploaded(&manifest)))
            }
            Manifest::Autoencoder(manifest) => {
                let parameter_count =
                    self.registry.validate_torchscript_autoencoder(file_path, manifest.clone()).await?;
                (ModelKind::Autoencoder, parameter_count, serde_json::to_value(&manifest))
            }
        };
        let manifest_json = manifest_json.map_err(|e| Error::internal("encoding manifest", e))?;
        let text = serde_json::to_vec_pretty(&manifest_json).map_err(|e| Error::internal("encoding manifest", e))?;
        tokio::task::block_in_place(|| std::fs::write(staging.path().join(MANIFEST_FILE), text))?;

        let record = ModelRecord {
            name: header.name,
            kind,
            format,
            manifest: manifest_json,
            parameter_count,
            sha256,
            size_bytes: size,
            file: file_name.into(),
            provenance: Provenance::Uploaded,
            created_at_ms: now_ms(),
            description: header.description,
            blob_key: String::new(),
        };
        let record = self.store.commit_model(staging, record).await?;
        // Nothing of this name can be cached, but a stale entry must never survive a new upload.
        self.registry.invalidate(&record.name);
        tracing::info!(
            model = record.name,
            bytes = record.size_bytes,
            parameters = parameter_count,
            format = ?format,
            kind = ?kind,
            "model registered"
        );
        model_to_proto(&record)
    }

    /// A bring-your-own reward's header checked and converted: TorchScript only, no diffusion
    /// manifest beside it, the manifest valid, and its base model (when named) an existing
    /// diffusion model with the same item shape, T and normalizer.
    async fn reward_manifest(
        &self,
        reward: pb::RewardUploadManifest,
        diffusion: Option<pb::DiffusionManifest>,
        format: ModelFormat,
    ) -> Result<RewardUploadManifest> {
        if diffusion.is_some() {
            return Err(Error::invalid(
                "header.manifest: set together with header.reward; a reward upload sends its RewardUploadManifest \
                 alone (header.manifest is a diffusion model's)",
            ));
        }
        if format != ModelFormat::Torchscript {
            return Err(Error::invalid(
                "header.format: MODEL_FORMAT_NATIVE with header.reward; a bring-your-own reward is a TorchScript \
                 module (native reward weights come from training jobs)",
            ));
        }
        let manifest = RewardUploadManifest::from_proto(reward, "header.reward")?;
        if manifest.base_model.is_empty() {
            return Ok(manifest);
        }
        let field = "header.reward.base_model";
        validate_name(field, &manifest.base_model)?;
        let base = self
            .store
            .meta
            .get_model(&manifest.base_model)
            .await?
            .ok_or_else(|| Error::NotFound(format!("{field}: model '{}' not found", manifest.base_model)))?;
        if base.kind != ModelKind::Diffusion {
            return Err(Error::invalid(format!("{field}: model '{}' is not a diffusion model", base.name)));
        }
        let base_manifest: DiffusionManifest = serde_json::from_value(base.manifest)
            .map_err(|e| Error::DataLoss(format!("model '{}': its stored manifest is unreadable: {e}", base.name)))?;
        let (ours, theirs) = (manifest.space.item_shape(), base_manifest.space.item_shape());
        if ours != theirs {
            return Err(Error::invalid(format!(
                "header.reward.space: items of shape {ours:?}, but base model '{}' has {theirs:?}",
                base.name
            )));
        }
        if manifest.n_timesteps != base_manifest.n_timesteps {
            return Err(Error::invalid(format!(
                "header.reward.n_timesteps: {}, but base model '{}' has T = {}",
                manifest.n_timesteps, base.name, base_manifest.n_timesteps
            )));
        }
        if manifest.normalizer != base_manifest.normalizer {
            return Err(Error::invalid(format!(
                "header.reward.normalizer: differs from base model '{}''s; a reward takes its base model's \
                 normalized units",
                base.name
            )));
        }
        Ok(manifest)
    }

    async fn list(&self, req: pb::ListModelsRequest) -> Result<pb::ListModelsResponse> {
        let page = req.page.unwrap_or_default();
        let limit = page_limit(page.page_size);
        let kind = model_kind_filter_from_proto(req.kind, "kind")?;
        // Read in pages of limit + 1 until limit + 1 matches are found (one extra tells whether
        // another page exists) or the listing ends.
        let mut after = fields::name_page_token(&page.page_token, "ListModels")?.to_owned();
        let mut matched: Vec<ModelRecord> = Vec::new();
        loop {
            let batch = self.store.meta.list_models(&after, limit + 1).await?;
            let exhausted = batch.len() <= limit;
            if let Some(last) = batch.last() {
                after = last.name.clone();
            }
            matched.extend(batch.into_iter().filter(|r| kind.is_none_or(|k| r.kind == k)));
            if matched.len() > limit || exhausted {
                break;
            }
        }
        let next_page_token = if matched.len() > limit {
            matched.truncate(limit);
            matched.last().map(|r| fields::next_name_token(&r.name)).unwrap_or_default()
        } else {
            String::new()
        };
        let models = matched.iter().map(model_to_proto).collect::<Result<_>>()?;
        Ok(pb::ListModelsResponse { models, next_page_token })
    }

    /// The header of a download and its files, opened (see the module doc); with
    /// `torchscript`, the traced module last.
    async fn download(
        &self,
        name: &str,
        torchscript: bool,
    ) -> Result<(pb::DownloadModelHeader, Vec<(std::fs::File, u64)>)> {
        validate_name("name", name)?;
        let not_found = || Error::NotFound(format!("name: model '{name}' not found"));
        let record = self.store.meta.get_model(name).await?.ok_or_else(not_found)?;
        let dir = self.store.blobs.local_dir(&record.blob_key).await?;
        let mut files = tokio::task::block_in_place(|| stored_files(&record, &dir))?;
        let mut opened = Vec::with_capacity(files.len() + 1);
        for file in &files {
            match std::fs::File::open(dir.join(&file.name)) {
                Ok(f) => opened.push((f, file.size_bytes)),
                // Deleted between the check and here: as if a moment later.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(not_found()),
                Err(e) => return Err(e.into()),
            }
        }
        if torchscript {
            // Traced into a staging directory that is removed on return: the open file stays
            // readable until the stream has sent it, and nothing is left on disk.
            let staging = self.store.blobs.staging()?;
            let path = staging.path().join(MODULE_FILE);
            let (sha256, size_bytes) = tokio::task::block_in_place(|| -> Result<_> {
                crate::registry::export_torchscript(&record, &dir, &path)?;
                Ok(digests::sha256_file(&path)?)
            })?;
            opened.push((std::fs::File::open(&path)?, size_bytes));
            files.push(pb::ModelFile { name: MODULE_FILE.into(), size_bytes, sha256 });
        }
        let manifest_json = serde_json::to_string_pretty(&record.manifest)
            .map_err(|e| Error::internal("encoding the stored manifest", e))?;
        let header = pb::DownloadModelHeader { model: Some(model_to_proto(&record)?), manifest_json, files };
        Ok((header, opened))
    }

    /// `CreateRecipe` (models.proto): checked cheapest first (name, description, the name free,
    /// the prompt dataset read, the recipe's own fields, the model a conditional diffusion model
    /// the recipe fits), then
    /// stored as `recipe.json`, the record's manifest, with its model's sha256 pinned.
    async fn create_recipe(&self, req: pb::CreateRecipeRequest) -> Result<pb::Model> {
        validate_name("name", &req.name)?;
        fields::check_description("description", &req.description)?;
        validate_name("model", &req.model)?;
        let mut recipe = req
            .recipe
            .ok_or_else(|| Error::invalid("recipe: missing; give its prompts (and guidance_scale, safety)"))?;
        if self.store.meta.get_model(&req.name).await?.is_some() {
            return Err(Error::AlreadyExists(format!("name: model '{}' already exists", req.name)));
        }
        let prompt_dataset = match recipe.prompts.as_mut() {
            Some(p) => crate::jobs::datasets::resolve_prompt_dataset(&self.store, p, "recipe.prompts").await?,
            None => None,
        };
        let recipe = RecipeSpec::from_proto(&recipe, "recipe")?;
        // From the model's lookup to the recipe's record: DeleteModel waits, then sees the recipe.
        let _references = self.store.references().await;
        let model = self
            .store
            .meta
            .get_model(&req.model)
            .await?
            .ok_or_else(|| Error::NotFound(format!("model: model '{}' not found", req.model)))?;
        if model.kind != ModelKind::Diffusion {
            return Err(Error::FailedPrecondition(format!(
                "model: '{}' is {}; a recipe samples a conditional diffusion model",
                req.model,
                crate::registry::kind_name(model.kind)
            )));
        }
        let manifest: DiffusionManifest = serde_json::from_value(model.manifest.clone())
            .map_err(|e| Error::DataLoss(format!("model '{}': its stored manifest is unreadable: {e}", req.model)))?;
        recipe.check_against(manifest.conditioning.as_ref(), "recipe", &req.model)?;
        let stored =
            RecipeManifest { model: req.model.clone(), model_sha256: model.sha256.clone(), recipe, prompt_dataset };
        let manifest_json = serde_json::to_value(&stored).map_err(|e| Error::internal("encoding a recipe", e))?;
        let text = serde_json::to_vec_pretty(&manifest_json).map_err(|e| Error::internal("encoding a recipe", e))?;
        let _reserved =
            tokio::task::block_in_place(|| self.budget.reserve(text.len() as u64, &format!("recipe '{}'", req.name)))?;
        let staging = self.store.blobs.staging()?;
        tokio::task::block_in_place(|| std::fs::write(staging.path().join(RECIPE_FILE), &text))?;
        let record = ModelRecord {
            name: req.name,
            kind: ModelKind::Recipe,
            format: ModelFormat::Recipe,
            manifest: manifest_json,
            parameter_count: 0,
            sha256: hex::encode(Sha256::digest(&text)),
            size_bytes: text.len() as u64,
            file: RECIPE_FILE.into(),
            provenance: Provenance::Uploaded,
            created_at_ms: now_ms(),
            description: req.description,
            blob_key: String::new(),
        };
        let record = self.store.commit_model(staging, record).await?;
        self.registry.invalidate(&record.name);
        tracing::info!(recipe = record.name, model = stored.model, "recipe registered");
        model_to_proto(&record)
    }

    /// A recipe that samples model `name`, if any (a scan of the model records: deletions are
    /// rare, recipes few).
    async fn recipe_using(&self, name: &str) -> Result<Option<String>> {
        let mut after = String::new();
        loop {
            let page = self.store.meta.list_models(&after, RECIPE_SCAN_PAGE).await?;
            for r in &page {
                if r.kind == ModelKind::Recipe && r.manifest.get("model").and_then(|m| m.as_str()) == Some(name) {
                    return Ok(Some(r.name.clone()));
                }
            }
            match page.last() {
                Some(last) if page.len() == RECIPE_SCAN_PAGE => after.clone_from(&last.name),
                _ => return Ok(None),
            }
        }
    }

    async fn delete(&self, name: &str) -> Result<()> {
        validate_name("name", name)?;
        let _references = self.store.references().await;
        if self.store.meta.get_model(name).await?.is_none() {
            return Err(Error::NotFound(format!("name: model '{name}' not found")));
        }
        if let Some(job) = self.jobs.job_using(name).await? {
            return Err(Error::FailedPrecondition(format!(
                "name: model '{name}' is in use by job '{job}'; cancel the job or wait for it to finish, then delete"
            )));
        }
        if let Some(recipe) = self.recipe_using(name).await? {
            return Err(Error::FailedPrecondition(format!(
                "name: model '{name}' is sampled by recipe '{recipe}'; delete the recipe first"
            )));
        }
        self.store.delete_model(name).await?;
        self.registry.invalidate(name);
        tracing::info!(model = name, "model deleted");
        Ok(())
    }
}

/// What an upload registers.
enum Manifest {
    Diffusion(DiffusionManifest),
    Reward(RewardUploadManifest),
    Autoencoder(AutoencoderManifest),
}

/// An autoencoder's header checked and converted: TorchScript only, no diffusion manifest
/// beside it, the manifest valid (messages name `header.autoencoder.*`).
fn autoencoder_manifest(
    autoencoder: pb::AutoencoderUploadManifest,
    diffusion: Option<pb::DiffusionManifest>,
    format: ModelFormat,
) -> Result<AutoencoderManifest> {
    if diffusion.is_some() {
        return Err(Error::invalid(
            "header.manifest: set together with header.autoencoder; an autoencoder upload sends its \
             AutoencoderUploadManifest alone (header.manifest is a diffusion model's)",
        ));
    }
    if format != ModelFormat::Torchscript {
        return Err(Error::invalid(
            "header.format: MODEL_FORMAT_NATIVE with header.autoencoder; an autoencoder is a TorchScript module \
             exporting encode and decode",
        ));
    }
    Ok(AutoencoderManifest::from_proto(autoencoder, "header.autoencoder")?)
}

/// A diffusion model's file name for its format: native weights need the manifest to name
/// their architecture, a TorchScript module must not (it is its own).
fn diffusion_file_name(format: ModelFormat, manifest: &DiffusionManifest) -> Result<&'static str> {
    match (format, &manifest.architecture) {
        // Refused with the header's format.
        (ModelFormat::Recipe, _) => Err(Error::internal("UploadModel", "a recipe format upload")),
        (ModelFormat::Torchscript, None) => Ok(MODULE_FILE),
        (ModelFormat::Native, Some(_)) => Ok(WEIGHTS_FILE),
        (ModelFormat::Torchscript, Some(_)) => Err(Error::invalid(
            "header.manifest.architecture: set, but header.format is TorchScript, whose module is its own \
             architecture; send safetensors weights with header.format = MODEL_FORMAT_NATIVE, or leave the \
             architecture unset",
        )),
        (ModelFormat::Native, None) => Err(Error::invalid(
            "header.manifest.architecture: missing; native weights (header.format = MODEL_FORMAT_NATIVE) \
             need the built-in architecture they belong to: temporal_unet, mlp or unet2d",
        )),
    }
}

/// The files of a stored model, checked, in download order: the record's file first, then
/// the others of its blob by name (e.g. a reward's step tables), without the digest list and
/// `manifest.json` (the header carries the manifest). Blocking: hashes every file once. A
/// blob with a digest list is checked against it; one from before digest lists existed is
/// hashed here, and its model file checked against the record. `DataLoss` naming the model
/// when anything disagrees.
fn stored_files(record: &ModelRecord, dir: &Path) -> Result<Vec<pb::ModelFile>> {
    let what = format!("model '{}'", record.name);
    let sums = match digests::verify_dir(dir, &what)? {
        Verified::Intact(sums) => sums,
        Verified::NoList => {
            let mut sums = std::collections::BTreeMap::new();
            for entry in std::fs::read_dir(dir)? {
                let entry = entry?;
                if entry.file_type()?.is_file() {
                    let name = entry.file_name().to_string_lossy().into_owned();
                    sums.insert(name, digests::sha256_file(&entry.path())?.0);
                }
            }
            sums
        }
    };
    match sums.get(&record.file) {
        Some(sum) if *sum == record.sha256 => {}
        Some(sum) => {
            return Err(Error::DataLoss(format!(
                "{what} is corrupt: stored file {} fails its integrity check (sha256 {sum}, recorded {})",
                record.file, record.sha256
            )));
        }
        None => return Err(Error::DataLoss(format!("{what} is corrupt: stored file {} is missing", record.file))),
    }
    let others = sums.keys().filter(|n| **n != record.file && *n != DIGEST_FILE && *n != MANIFEST_FILE);
    std::iter::once(&record.file)
        .chain(others)
        .map(|name| {
            let size_bytes = std::fs::metadata(dir.join(name))?.len();
            Ok(pb::ModelFile { name: name.clone(), size_bytes, sha256: sums[name].clone() })
        })
        .collect()
}

/// The header, then each file's bytes in chunks of at most `chunk_bytes`, read as the client
/// takes them (the stream is polled by tonic, so a slow client holds no more than a chunk).
fn download_stream(
    header: pb::DownloadModelHeader,
    files: Vec<(std::fs::File, u64)>,
    chunk_bytes: usize,
) -> DownloadStream {
    use pb::download_model_response::Message as Out;
    struct State {
        files: std::vec::IntoIter<(std::fs::File, u64)>,
        current: Option<(tokio::fs::File, u64)>,
        failed: bool,
    }
    let first =
        futures::stream::once(async move { Ok(pb::DownloadModelResponse { message: Some(Out::Header(header)) }) });
    let state = State { files: files.into_iter(), current: None, failed: false };
    let chunks = futures::stream::unfold(state, move |mut st| async move {
        if st.failed {
            return None;
        }
        // Skip to the next file with bytes left (an empty file sends no chunk).
        let (file, left) = loop {
            match st.current.take() {
                Some((file, left)) if left > 0 => break (file, left),
                _ => {
                    let (file, size) = st.files.next()?;
                    st.current = Some((tokio::fs::File::from_std(file), size));
                }
            }
        };
        let n = (chunk_bytes as u64).min(left) as usize;
        let mut buf = vec![0u8; n];
        let mut file = file;
        match file.read_exact(&mut buf).await {
            Ok(_) => {
                st.current = Some((file, left - n as u64));
                Some((Ok(pb::DownloadModelResponse { message: Some(Out::Chunk(buf)) }), st))
            }
            Err(e) => {
                st.failed = true;
                Some((Err(Status::from(Error::internal("reading a stored model file", e))), st))
            }
        }
    });
    Box::pin(futures::StreamExt::chain(first, chunks))
}

#[tonic::async_trait]
impl ModelService for Models {
    type DownloadModelStream = DownloadStream;

    async fn upload_model(
        &self,
        request: Request<Streaming<pb::UploadModelRequest>>,
    ) -> Result<Response<pb::Model>, Status> {
        Ok(Response::new(self.upload(request.into_inner()).await?))
    }

    async fn get_model(&self, request: Request<pb::GetModelRequest>) -> Result<Response<pb::Model>, Status> {
        let req = request.into_inner();
        validate_name("name", &req.name)?;
        let record = self
            .store
            .meta
            .get_model(&req.name)
            .await?
            .ok_or_else(|| Error::NotFound(format!("name: model '{}' not found", req.name)))?;
        Ok(Response::new(model_to_proto(&record)?))
    }

    async fn list_models(
        &self,
        request: Request<pb::ListModelsRequest>,
    ) -> Result<Response<pb::ListModelsResponse>, Status> {
        Ok(Response::new(self.list(request.into_inner()).await?))
    }

    async fn delete_model(
        &self,
        request: Request<pb::DeleteModelRequest>,
    ) -> Result<Response<pb::DeleteModelResponse>, Status> {
        self.delete(&request.into_inner().name).await?;
        Ok(Response::new(pb::DeleteModelResponse {}))
    }

    async fn create_recipe(&self, request: Request<pb::CreateRecipeRequest>) -> Result<Response<pb::Model>, Status> {
        Ok(Response::new(self.create_recipe(request.into_inner()).await?))
    }

    async fn download_model(
        &self,
        request: Request<pb::DownloadModelRequest>,
    ) -> Result<Response<Self::DownloadModelStream>, Status> {
        let req = request.into_inner();
        let (header, files) = self.download(&req.name, req.torchscript).await?;
        Ok(Response::new(download_stream(header, files, self.chunk_bytes)))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;
    use crate::config::{Config, Overrides};
    use crate::store::{JobRecord, JobState};
    use crate::tasks::Tasks;

    #[tokio::test(flavor = "multi_thread")]
    async fn delete_is_refused_while_a_job_uses_the_model() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let overrides = Overrides { data_dir: Some(tmp.path().join("data")), ..Overrides::default() };
        let env = config::Environment::with_prefix("RELREWARD").source(Some(HashMap::new()));
        let config = Config::load_with_env(None, &overrides, env).expect("config");
        let store = Store::open(&config).await.expect("store");
        let jobs = JobManager::start(store.clone(), config.jobs.clone(), true, Tasks::detached_for_tests("jobs"))
            .await
            .expect("jobs");
        let registry = ModelRegistry::new(store.clone(), &config.models, tch::Device::Cpu);
        let models = Models::new(
            store.clone(),
            registry,
            jobs,
            config.models.clone(),
            DiskBudget::new(&config.storage.data_dir, 0),
            config.server.max_response_bytes,
        );

        let staging = store.blobs.staging().expect("staging");
        std::fs::write(staging.path().join(MODULE_FILE), b"weights").expect("write");
        let record = ModelRecord {
            name: "base".into(),
            kind: ModelKind::Diffusion,
            format: ModelFormat::Torchscript,
            manifest: serde_json::json!({}),
            parameter_count: 0,
            sha256: String::new(),
            size_bytes: 7,
            file: MODULE_FILE.into(),
            provenance: Provenance::Uploaded,
            created_at_ms: 0,
            description: String::new(),
            blob_key: String::new(),
        };
        store.commit_model(staging, record).await.expect("commit");
        // A job that reads the model, recorded directly (the manager never runs it).
        let mut job = JobRecord {
            id: "job-uses-base".into(),
            kind: "reward".into(),
            spec: serde_json::json!({}),
            state: JobState::Pending,
            step: 0,
            total_steps: 1,
            loss: None,
            error: String::new(),
            created_at_ms: 0,
            started_at_ms: None,
            finished_at_ms: None,
            last_seq: 0,
            checkpoint: None,
            inputs: vec!["some-dataset".into(), "base".into()],
            output_model: "reward-out".into(),
        };
        store.meta.insert_job(&job, &[]).await.expect("job");

        match models.delete("base").await {
            Err(Error::FailedPrecondition(m)) => {
                assert!(m.contains("'job-uses-base'") && m.starts_with("name:"), "{m}")
            }
            other => panic!("expected FailedPrecondition, got {other:?}"),
        }
        assert!(store.meta.get_model("base").await.expect("get").is_some(), "still registered");

        job.state = JobState::Cancelled;
        store.meta.record_job(&job, &[], None).await.expect("cancel");
        models.delete("base").await.expect("delete once no job uses it");
        assert!(matches!(models.delete("base").await, Err(Error::NotFound(_))));
        assert!(matches!(models.delete("Bad Name").await, Err(Error::InvalidArgument(_))));
    }
}

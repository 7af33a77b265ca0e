//! [`ModelRegistry`]: stored models loaded on demand and kept in memory: diffusion models
//! ([`DiffusionModel`]), reward or discriminator models ([`RewardModel`]) and autoencoders
//! ([`TorchScriptAutoencoder`]).
//!
//! Where it sits: between the doors and workers above it (`api`, `serving`, `sampling`, `jobs`)
//! and [`crate::engine`] below. It is the one place where the store's records and files meet
//! engine types, which is why it lives outside `engine/`: the engine knows neither the store
//! nor the configuration, and could leave as a crate of its own.
//!
//! - Loading: the record's manifest (JSON) becomes an engine manifest. A diffusion model's
//!   file is a native architecture's safetensors weights ([`NativeDenoiser`]) or a TorchScript
//!   module ([`TorchScriptDenoiser`], validated again with one forward pass); a reward model's
//!   is its network's safetensors weights (plus Algorithm 2's step tables beside them), or a
//!   bring-your-own TorchScript module ([`TorchScriptReward`], validated again as at upload);
//!   an autoencoder's is its TorchScript module ([`TorchScriptAutoencoder`], likewise).
//! - Integrity: the stored file's sha256 is recomputed on every load and compared with the
//!   record's; a mismatch (or a missing file, or an unreadable manifest) is `DataLoss` and the
//!   model is never served.
//! - Cache: models stay loaded up to `models.cache_bytes`, counted as the larger of their
//!   parameter bytes and their file's size (a TorchScript file holds its buffers, which
//!   libtorch's C API does not list); beyond it the least recently used are dropped. A model
//!   larger than the whole budget is served but not kept. Dropping only removes the registry's
//!   reference: a request still holding the model finishes with it.
//! - Identity: an entry is keyed by name and remembers its blob key; a lookup reads the record
//!   first unless no model record changed since the entry was last checked (the store's
//!   models generation), so a model deleted and registered again under the same name is never
//!   served from a stale entry, and the serving hot path costs no metadata read.
//!   [`ModelRegistry::invalidate`] frees an entry at once.
//! - Kind: asking for a diffusion model by the name of a reward model, or the reverse (or for
//!   an autoencoder by another kind's name), is `FailedPrecondition` (the name is well formed
//!   and the model exists; it is the wrong kind of model for the request in the system's
//!   current state).
//! - Recipes: a named sampling recipe is a record without a network. [`resolve_sampled`] is the
//!   one place that follows a name to the diffusion model it samples (a recipe's model, checked
//!   against the sha256 the recipe pinned); [`ModelRegistry::get_sampled`] loads that model.
//!
//! tch modules are `Send` but not `Sync`, so each model is shared behind a `std::sync::Mutex`
//! (lock it on a blocking thread, where tensor work belongs anyway).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use tch::Device;

use crate::config::ModelsConfig;
use crate::engine::autoencoder::{AutoencoderManifest, TorchScriptAutoencoder};
use crate::engine::denoiser::{Denoiser, ValidationProbe};
use crate::engine::diffusion::DiffusionModel;
use crate::engine::export;
use crate::engine::manifest::{DiffusionManifest, RewardUploadManifest};
use crate::engine::nets::NativeDenoiser;
use crate::engine::relative_reward::{RewardManifest, RewardSource};
use crate::engine::reward_model::RewardModel;
use crate::engine::torchscript::{TorchScriptDenoiser, TorchScriptReward};
use crate::error::{Error, Result};
use crate::store::digests::{self, Verified, sha256_file};
use crate::store::{ModelFormat, ModelKind, ModelRecord, Store};
use relreward_proto::schema::recipe::RecipeManifest;

/// A loaded diffusion model, shared between requests.
pub type SharedDiffusion = Arc<ServedDiffusion>;

/// A loaded reward or discriminator model, shared between requests.
pub type SharedReward = Arc<ServedReward>;

/// A loaded autoencoder, shared between requests.
pub type SharedAutoencoder = Arc<ServedAutoencoder>;

/// An autoencoder with its manifest (shapes, scaling) readable without its lock, so Encode and
/// Decode are validated on the async side.
#[derive(Debug)]
pub struct ServedAutoencoder {
    pub name: String,
    pub manifest: AutoencoderManifest,
    model: Mutex<TorchScriptAutoencoder>,
}

impl ServedAutoencoder {
    /// The module, for tensor work (blocking threads only).
    pub fn lock(&self) -> MutexGuard<'_, TorchScriptAutoencoder> {
        // Encoding and decoding never write the weights.
        lock(&self.model)
    }
}

/// A reward model with what requests validate against readable without its lock.
#[derive(Debug)]
pub struct ServedReward {
    pub name: String,
    /// The stored version: a model registered again under the same name has another key.
    pub blob_key: String,
    pub manifest: RewardManifest,
    pub item_shape: Vec<i64>,
    pub window: Option<usize>,
    model: Mutex<RewardModel>,
}

#[cfg(test)]
impl ServedReward {
    /// A loaded model served under the name "test", for tests of what uses one.
    pub(crate) fn for_tests(model: RewardModel) -> Self {
        Self {
            name: "test".into(),
            blob_key: "test".into(),
            manifest: model.manifest.clone(),
            item_shape: model.item_shape().to_vec(),
            window: model.window(),
            model: Mutex::new(model),
        }
    }
}

impl ServedReward {
    /// The model, for tensor work (blocking threads only).
    pub fn lock(&self) -> MutexGuard<'_, RewardModel> {
        // A panic inside libtorch cannot leave the weights half-written (inference never
        // writes them), so a poisoned lock is still usable.
        lock(&self.model)
    }
}

/// A diffusion model with its manifest readable without its lock: a request is validated
/// against the manifest on the async side while a sampling run may hold the model for long.
#[derive(Debug)]
pub struct ServedDiffusion {
    pub name: String,
    pub manifest: DiffusionManifest,
    model: Mutex<DiffusionModel>,
}

impl ServedDiffusion {
    /// The model, for tensor work (blocking threads only).
    pub fn lock(&self) -> MutexGuard<'_, DiffusionModel> {
        // As for rewards: sampling never writes the weights.
        lock(&self.model)
    }
}

#[derive(Clone)]
pub struct ModelRegistry {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    device: Device,
    cache_bytes: u64,
    cache: Mutex<Cache>,
    /// One async gate per name, so concurrent first requests load a model once.
    loading: Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
    /// Models found corrupt: name -> (blob key, the DataLoss message). Blobs are immutable,
    /// so a corrupt one stays corrupt: later requests get the same answer without hashing
    /// the file again. Keyed by blob key, so a model registered again is loaded afresh.
    corrupt: Mutex<HashMap<String, (String, String)>>,
}

#[derive(Default)]
struct Cache {
    entries: HashMap<String, Entry>,
    clock: u64,
    bytes: u64,
}

/// A loaded model of either family.
#[derive(Clone)]
enum Served {
    Diffusion(SharedDiffusion),
    Reward(SharedReward),
    Autoencoder(SharedAutoencoder),
}

/// Which family a request needs.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Family {
    Diffusion,
    Reward,
    Autoencoder,
}

struct Entry {
    blob_key: String,
    model: Served,
    bytes: u64,
    last_used: u64,
    /// The store's models generation when the record was last read: while it is unchanged the
    /// record is too, and lookups skip the metadata read.
    checked_at: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Every critical section below is a few map operations that cannot leave the map
    // inconsistent, so a poisoned lock is still usable.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What the loader produced.
struct Loaded {
    model: Served,
    bytes: u64,
}

impl ModelRegistry {
    /// A registry over `store` that loads models onto `device`.
    pub fn new(store: Store, config: &ModelsConfig, device: Device) -> Self {
        Self {
            inner: Arc::new(Inner {
                store,
                device,
                cache_bytes: config.cache_bytes,
                cache: Mutex::new(Cache::default()),
                loading: Mutex::new(HashMap::new()),
                corrupt: Mutex::new(HashMap::new()),
            }),
        }
    }

    pub fn device(&self) -> Device {
        self.inner.device
    }

    /// The diffusion model `name`, from the cache or loaded from the store.
    ///
    /// Errors: `NotFound` (no such model), `FailedPrecondition` (a reward or discriminator
    /// model), `DataLoss` (the stored file or manifest fails its integrity check).
    pub async fn get_diffusion(&self, name: &str) -> Result<SharedDiffusion> {
        match self.get(name, Family::Diffusion).await? {
            Served::Diffusion(m) => Ok(m),
            Served::Reward(_) | Served::Autoencoder(_) => {
                Err(Error::internal("model registry", "another kind of model was cached as a diffusion model"))
            }
        }
    }

    /// What `name` samples: a diffusion model (no recipe), or a named recipe's model with the
    /// recipe ([`resolve_sampled`]), the model from the cache or loaded from the store.
    ///
    /// Errors: those of [`resolve_sampled`] and [`Self::get_diffusion`].
    pub async fn get_sampled(&self, name: &str) -> Result<(SharedDiffusion, Option<RecipeManifest>)> {
        let (record, recipe) = resolve_sampled(&self.inner.store, name).await?;
        Ok((self.get_diffusion(&record.name).await?, recipe))
    }

    /// The reward or discriminator model `name`, from the cache or loaded from the store.
    ///
    /// Errors: `NotFound`, `FailedPrecondition` (a diffusion model), `DataLoss`.
    pub async fn get_reward(&self, name: &str) -> Result<SharedReward> {
        match self.get(name, Family::Reward).await? {
            Served::Reward(m) => Ok(m),
            Served::Diffusion(_) | Served::Autoencoder(_) => {
                Err(Error::internal("model registry", "another kind of model was cached as a reward model"))
            }
        }
    }

    /// The autoencoder `name`, from the cache or loaded from the store.
    ///
    /// Errors: `NotFound`, `FailedPrecondition` (another kind of model), `DataLoss`.
    pub async fn get_autoencoder(&self, name: &str) -> Result<SharedAutoencoder> {
        match self.get(name, Family::Autoencoder).await? {
            Served::Autoencoder(m) => Ok(m),
            Served::Diffusion(_) | Served::Reward(_) => {
                Err(Error::internal("model registry", "another kind of model was cached as an autoencoder"))
            }
        }
    }

    /// The store's models generation (see [`Store::models_generation`]): unchanged means no
    /// model record was inserted or deleted since it was read.
    pub fn models_generation(&self) -> u64 {
        self.inner.store.models_generation()
    }

    /// Stored model records with names strictly after `after`, in name order, at most `limit`
    /// (the store's listing: nothing is loaded).
    pub async fn list_records(&self, after: &str, limit: usize) -> Result<Vec<ModelRecord>> {
        self.inner.store.meta.list_models(after, limit).await
    }

    /// The stored record of diffusion model `name` (for what its manifest alone answers, such
    /// as its schedule), without loading it.
    pub async fn diffusion_record(&self, name: &str) -> Result<ModelRecord> {
        self.record(name, Family::Diffusion).await
    }

    async fn get(&self, name: &str, family: Family) -> Result<Served> {
        // Read before the record, so a change racing with this lookup bumps it past what the
        // entry remembers and the next lookup reads the record again.
        let generation = self.inner.store.models_generation();
        if let Some(model) = self.lookup_unchanged(name, family, generation) {
            return Ok(model);
        }
        let record = self.record(name, family).await?;
        if let Some(model) = self.lookup(name, &record.blob_key, generation) {
            return Ok(model);
        }
        if let Some((key, message)) = lock(&self.inner.corrupt).get(name)
            && *key == record.blob_key
        {
            return Err(Error::DataLoss(message.clone()));
        }
        let gate = Arc::clone(lock(&self.inner.loading).entry(name.to_owned()).or_default());
        let _loading = gate.lock().await;
        // Whoever held the gate before may have loaded it.
        if let Some(model) = self.lookup(name, &record.blob_key, generation) {
            return Ok(model);
        }
        let dir = self.inner.store.blobs.local_dir(&record.blob_key).await?;
        let device = self.inner.device;
        let blob_key = record.blob_key.clone();
        let loaded = tokio::task::spawn_blocking(move || match family {
            Family::Diffusion => load_diffusion(&record, &dir, device),
            Family::Reward => load_reward(&record, &dir, device),
            Family::Autoencoder => load_autoencoder(&record, &dir, device),
        })
        .await
        .map_err(|e| Error::internal("model loading task", e))?;
        let loaded = match loaded {
            Ok(l) => l,
            Err(e) => {
                // Deleted (or replaced) while loading: say so rather than report lost data.
                match self.inner.store.meta.get_model(name).await? {
                    Some(current) if current.blob_key == blob_key => {
                        if let Error::DataLoss(message) = &e {
                            tracing::error!(model = name, blob = blob_key, "{message}");
                            lock(&self.inner.corrupt).insert(name.to_owned(), (blob_key, message.clone()));
                        }
                        return Err(e);
                    }
                    _ => return Err(Error::NotFound(format!("model '{name}' not found (deleted while loading)"))),
                }
            }
        };
        Ok(self.insert(name, blob_key, loaded, generation))
    }

    /// The stored record of a model of `family`.
    async fn record(&self, name: &str, family: Family) -> Result<ModelRecord> {
        let record = self
            .inner
            .store
            .meta
            .get_model(name)
            .await?
            .ok_or_else(|| Error::NotFound(format!("model '{name}' not found")))?;
        match (record.kind, family) {
            (ModelKind::Diffusion, Family::Diffusion)
            | (ModelKind::Reward | ModelKind::Discriminator, Family::Reward)
            | (ModelKind::Autoencoder, Family::Autoencoder) => Ok(record),
            (kind, Family::Diffusion) => {
                Err(Error::FailedPrecondition(format!("model '{name}' is {}, not a diffusion model", kind_name(kind))))
            }
            (kind, Family::Reward) => Err(Error::FailedPrecondition(format!(
                "model '{name}' is {}, not a reward or discriminator model",
                kind_name(kind)
            ))),
            (kind, Family::Autoencoder) => Err(Error::FailedPrecondition(format!(
                "model '{name}' is {}, not an autoencoder (Encode and Decode take a model uploaded with \
                 header.autoencoder)",
                kind_name(kind)
            ))),
        }
    }

    /// The cached model of `family` if no model record changed since the entry was checked.
    fn lookup_unchanged(&self, name: &str, family: Family, generation: u64) -> Option<Served> {
        let mut cache = lock(&self.inner.cache);
        cache.clock += 1;
        let clock = cache.clock;
        let entry = cache.entries.get_mut(name).filter(|e| e.checked_at == generation)?;
        let same_family = match &entry.model {
            Served::Diffusion(_) => family == Family::Diffusion,
            Served::Reward(_) => family == Family::Reward,
            Served::Autoencoder(_) => family == Family::Autoencoder,
        };
        if !same_family {
            return None;
        }
        entry.last_used = clock;
        Some(entry.model.clone())
    }

    fn lookup(&self, name: &str, blob_key: &str, generation: u64) -> Option<Served> {
        let mut cache = lock(&self.inner.cache);
        cache.clock += 1;
        let clock = cache.clock;
        let entry = cache.entries.get_mut(name).filter(|e| e.blob_key == blob_key)?;
        entry.last_used = clock;
        entry.checked_at = generation;
        Some(entry.model.clone())
    }

    fn insert(&self, name: &str, blob_key: String, loaded: Loaded, generation: u64) -> Served {
        let model = loaded.model;
        let mut cache = lock(&self.inner.cache);
        if let Some(old) = cache.entries.remove(name) {
            cache.bytes = cache.bytes.saturating_sub(old.bytes);
        }
        if loaded.bytes > self.inner.cache_bytes {
            tracing::info!(
                model = name,
                bytes = loaded.bytes,
                cache_bytes = self.inner.cache_bytes,
                "model is larger than models.cache_bytes: served without caching"
            );
            return model;
        }
        while cache.bytes.saturating_add(loaded.bytes) > self.inner.cache_bytes {
            let Some(victim) = cache.entries.iter().min_by_key(|(_, e)| e.last_used).map(|(n, _)| n.clone()) else {
                break;
            };
            if let Some(old) = cache.entries.remove(&victim) {
                cache.bytes = cache.bytes.saturating_sub(old.bytes);
                tracing::debug!(model = victim, bytes = old.bytes, "evicted from the model cache");
            }
        }
        cache.clock += 1;
        let last_used = cache.clock;
        cache.bytes = cache.bytes.saturating_add(loaded.bytes);
        cache.entries.insert(
            name.to_owned(),
            Entry { blob_key, model: model.clone(), bytes: loaded.bytes, last_used, checked_at: generation },
        );
        tracing::debug!(model = name, bytes = loaded.bytes, cached_bytes = cache.bytes, "model loaded");
        model
    }

    /// Drops the cached entry of `name` (after a delete). Requests holding it finish with it.
    pub fn invalidate(&self, name: &str) {
        {
            let mut cache = lock(&self.inner.cache);
            if let Some(old) = cache.entries.remove(name) {
                cache.bytes = cache.bytes.saturating_sub(old.bytes);
            }
        }
        lock(&self.inner.loading).remove(name);
        lock(&self.inner.corrupt).remove(name);
    }

    /// Names of the models in memory, sorted (for tests and diagnostics).
    pub fn cached_names(&self) -> Vec<String> {
        let mut names: Vec<String> = lock(&self.inner.cache).entries.keys().cloned().collect();
        names.sort();
        names
    }

    /// Bytes the cache accounts for.
    pub fn cached_bytes(&self) -> u64 {
        lock(&self.inner.cache).bytes
    }

    /// Loads the TorchScript module at `path` on the registry's device and validates it against
    /// `manifest` (see [`TorchScriptDenoiser::load_and_validate`]) on a blocking thread. Returns
    /// its parameter count.
    pub async fn validate_torchscript(&self, path: PathBuf, manifest: DiffusionManifest) -> Result<u64> {
        let device = self.inner.device;
        tokio::task::spawn_blocking(move || {
            TorchScriptDenoiser::load_and_validate(&path, &manifest, device).map(|d| d.parameter_count())
        })
        .await
        .map_err(|e| Error::internal("module validation task", e))?
    }
}

impl ModelRegistry {
    /// Loads a bring-your-own reward's module at `path` on the registry's device and validates
    /// it against `manifest` (see [`TorchScriptReward::load_and_validate`]: a forward and a
    /// backward to x on zeros of the declared shape) on a blocking thread. Returns its
    /// parameter count.
    pub async fn validate_torchscript_reward(&self, path: PathBuf, manifest: RewardUploadManifest) -> Result<u64> {
        let device = self.inner.device;
        tokio::task::spawn_blocking(move || {
            TorchScriptReward::load_and_validate(&path, &manifest, device).map(|r| r.parameter_count())
        })
        .await
        .map_err(|e| Error::internal("module validation task", e))?
    }

    /// Loads an autoencoder's module at `path` on the registry's device and validates it against
    /// `manifest` (see [`TorchScriptAutoencoder::load_and_validate`]: encode and decode once each
    /// on zeros of the declared shapes) on a blocking thread. Returns its parameter count.
    pub async fn validate_torchscript_autoencoder(&self, path: PathBuf, manifest: AutoencoderManifest) -> Result<u64> {
        let device = self.inner.device;
        tokio::task::spawn_blocking(move || {
            TorchScriptAutoencoder::load_and_validate(&path, &manifest, device).map(|a| a.parameter_count())
        })
        .await
        .map_err(|e| Error::internal("module validation task", e))?
    }

    /// Checks uploaded native weights against their manifest before registration (blocking
    /// work on a worker thread): the strict load names every missing, unexpected or mis-shaped
    /// tensor; every weight must be finite (the error names the first tensor holding a NaN or
    /// an infinity, and where); then one forward on zeros `[2, *item]` with `t = [0, T - 1]`
    /// must be finite too. Returns the parameter count.
    pub async fn validate_native(&self, path: PathBuf, manifest: DiffusionManifest) -> Result<u64> {
        let device = self.inner.device;
        tokio::task::spawn_blocking(move || -> Result<u64> {
            let Some(architecture) = manifest.architecture.as_ref() else {
                return Err(Error::invalid("header.manifest.architecture: missing; native weights need one"));
            };
            let net =
                NativeDenoiser::load(architecture, &manifest.space, &path, manifest.conditioning.as_ref(), device)
                    .map_err(|e| match e {
                        Error::InvalidArgument(m) | Error::DataLoss(m) => Error::invalid(format!(
                            "chunk: the uploaded weights do not fit header.manifest.architecture: {m}"
                        )),
                        other => other,
                    })?;
            net.weights().check_finite().map_err(|e| match e {
                Error::InvalidArgument(m) => Error::invalid(format!("chunk: the uploaded {m}")),
                other => other,
            })?;
            let probe =
                ValidationProbe::new(net.item_shape(), manifest.n_timesteps, manifest.conditioning.as_ref(), device)?;
            let out = tch::no_grad(|| net.forward(&probe.x, &probe.t, probe.cond.as_ref()))?;
            probe.check_finite(&out, "chunk: the uploaded weights' forward")?;
            Ok(net.parameter_count())
        })
        .await
        .map_err(|e| Error::internal("weights validation task", e))?
    }
}

/// A kind of model with its article, for messages ("a reward model", "an autoencoder").
pub fn kind_name(kind: ModelKind) -> &'static str {
    match kind {
        ModelKind::Diffusion => "a diffusion model",
        ModelKind::Reward => "a reward model",
        ModelKind::Discriminator => "a discriminator model",
        ModelKind::Autoencoder => "an autoencoder",
        ModelKind::Recipe => "a sampling recipe",
    }
}

/// Follows `name` to the diffusion model it samples (the stored record): a diffusion model
/// itself (no recipe), or a named recipe's model with the recipe. A recipe's model must still be
/// the one it was made for (same sha256): deleting it is refused while the recipe exists, but a
/// recipe must never quietly sample a different model.
///
/// Errors: `NotFound` (no such model), `FailedPrecondition` (another kind of model, or a recipe
/// whose model is gone or changed), `DataLoss` (an unreadable recipe manifest).
pub async fn resolve_sampled(store: &Store, name: &str) -> Result<(ModelRecord, Option<RecipeManifest>)> {
    let record =
        store.meta.get_model(name).await?.ok_or_else(|| Error::NotFound(format!("model '{name}' not found")))?;
    match record.kind {
        ModelKind::Diffusion => Ok((record, None)),
        ModelKind::Recipe => {
            let recipe: RecipeManifest = serde_json::from_value(record.manifest)
                .map_err(|e| Error::DataLoss(format!("recipe '{name}': its stored manifest is unreadable: {e}")))?;
            match store.meta.get_model(&recipe.model).await? {
                Some(m) if m.kind == ModelKind::Diffusion && m.sha256 == recipe.model_sha256 => Ok((m, Some(recipe))),
                Some(m) => Err(Error::FailedPrecondition(format!(
                    "recipe '{name}' was made for model '{}' (sha256 {}), which has been replaced since by {} (sha256 \
                     {}); create the recipe again",
                    recipe.model,
                    recipe.model_sha256,
                    kind_name(m.kind),
                    m.sha256
                ))),
                None => Err(Error::FailedPrecondition(format!(
                    "recipe '{name}': its model '{}' no longer exists",
                    recipe.model
                ))),
            }
        }
        kind => Err(Error::FailedPrecondition(format!(
            "model '{name}' is {}, not a diffusion model or a sampling recipe",
            kind_name(kind)
        ))),
    }
}

/// A private, uncached copy of a stored diffusion model (blocking), for a training job that
/// must not hold the shared copy's lock for its whole run.
pub fn load_diffusion_copy(record: &ModelRecord, dir: &Path, device: Device) -> Result<DiffusionModel> {
    let (model, _) = build_diffusion(record, dir, device)?;
    Ok(model)
}

/// A stored native model traced into a TorchScript module at `out` (blocking; on the CPU,
/// from a private copy: nothing served is locked meanwhile). See [`crate::engine::export`] for
/// what the module computes. A TorchScript diffusion model is refused: its stored file is
/// already the module. The caller has checked the blob's files against their digests (the
/// download does, `stored_files`), so they are not hashed a second time here.
pub fn export_torchscript(record: &ModelRecord, dir: &Path, out: &Path) -> Result<()> {
    let path = dir.join(&record.file);
    match (record.kind, record.format) {
        (ModelKind::Recipe, _) | (_, ModelFormat::Recipe) => Err(Error::FailedPrecondition(format!(
            "torchscript: model '{}' is a sampling recipe (data, no network); export the model it samples",
            record.name
        ))),
        (ModelKind::Autoencoder, _) => Err(Error::FailedPrecondition(format!(
            "torchscript: model '{}' is an autoencoder, an uploaded TorchScript module; its module.pt, as uploaded, \
             is the module",
            record.name
        ))),
        (ModelKind::Diffusion, ModelFormat::Torchscript) => Err(Error::FailedPrecondition(format!(
            "torchscript: model '{}' is stored as TorchScript already; its module.pt is the export",
            record.name
        ))),
        (_, ModelFormat::Torchscript) => Err(Error::FailedPrecondition(format!(
            "torchscript: model '{}' is a bring-your-own TorchScript reward; its module.pt, as uploaded, is the \
             module (over normalized x, as its manifest's signature says)",
            record.name
        ))),
        (ModelKind::Reward | ModelKind::Discriminator, ModelFormat::Native) => {
            let manifest: RewardManifest = serde_json::from_value(record.manifest.clone())
                .map_err(|e| lost(record, format!("its stored manifest is unreadable: {e}")))?;
            let mut model = RewardModel::load(manifest, &path, dir, Device::Cpu)?;
            model.freeze();
            export::trace_reward(&model, out)
        }
        (ModelKind::Diffusion, ModelFormat::Native) => {
            let manifest: DiffusionManifest = serde_json::from_value(record.manifest.clone())
                .map_err(|e| lost(record, format!("its stored manifest is unreadable: {e}")))?;
            let arch = manifest.architecture.as_ref().ok_or_else(|| {
                lost(record, "its stored manifest names no architecture (native models need one)".into())
            })?;
            let mut net =
                NativeDenoiser::load(arch, &manifest.space, &path, manifest.conditioning.as_ref(), Device::Cpu)?;
            net.freeze();
            let item_shape = net.item_shape().to_vec();
            export::trace_denoiser(&net, &item_shape, manifest.n_timesteps, manifest.conditioning.as_ref(), out)
        }
    }
}

/// The stored file of `record`, checked against its recorded sha256; returns its path and size.
/// Every file of the blob is checked against the blob's digest list (a reward model's step
/// tables too), and the list's entry for the model file must be the record's sha256, so each
/// file is hashed once. A blob without a list (published before lists existed) is checked
/// by the record's sha256 of the model file alone.
fn verified_file(record: &ModelRecord, dir: &Path) -> Result<(PathBuf, u64)> {
    let path = dir.join(&record.file);
    let sha256 = match digests::verify_dir(dir, &format!("model '{}'", record.name)) {
        Ok(Verified::Intact(sums)) => match sums.get(&record.file) {
            Some(sum) => sum.clone(),
            None => return Err(lost(record, "its stored file is not in its digest list".into())),
        },
        Ok(Verified::NoList) => match sha256_file(&path) {
            Ok((sum, _)) => sum,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(lost(record, "its stored file is missing".into()));
            }
            Err(e) => return Err(e.into()),
        },
        Err(Error::DataLoss(m)) => return Err(Error::DataLoss(format!("{m}; it will not be served"))),
        Err(e) => return Err(e),
    };
    if sha256 != record.sha256 {
        return Err(lost(
            record,
            format!("the stored file fails its integrity check (sha256 {sha256}, recorded {})", record.sha256),
        ));
    }
    let size = std::fs::metadata(&path)?.len();
    Ok((path, size))
}

fn lost(record: &ModelRecord, what: String) -> Error {
    Error::DataLoss(format!("model '{}': {what}; it will not be served", record.name))
}

fn load_diffusion(record: &ModelRecord, dir: &Path, device: Device) -> Result<Loaded> {
    let (model, bytes) = build_diffusion(record, dir, device)?;
    let served =
        ServedDiffusion { name: record.name.clone(), manifest: model.manifest.clone(), model: Mutex::new(model) };
    Ok(Loaded { model: Served::Diffusion(Arc::new(served)), bytes })
}

/// Builds the diffusion model of a stored record (blocking: hashing and libtorch); returns it
/// with its cache size.
fn build_diffusion(record: &ModelRecord, dir: &Path, device: Device) -> Result<(DiffusionModel, u64)> {
    let (path, size) = verified_file(record, dir)?;
    let manifest: DiffusionManifest = serde_json::from_value(record.manifest.clone())
        .map_err(|e| lost(record, format!("its stored manifest is unreadable: {e}")))?;
    manifest.validate().map_err(|e| lost(record, format!("its stored manifest is invalid: {e}")))?;
    let (net, parameter_bytes): (Box<dyn Denoiser>, u64) = match record.format {
        ModelFormat::Recipe => return Err(lost(record, "a diffusion model stored as a recipe".into())),
        ModelFormat::Native => {
            let arch = manifest.architecture.as_ref().ok_or_else(|| {
                lost(record, "its stored manifest names no architecture (native models need one)".into())
            })?;
            let net = NativeDenoiser::load(arch, &manifest.space, &path, manifest.conditioning.as_ref(), device)?;
            let bytes = net.parameter_count().saturating_mul(4);
            (Box::new(net), bytes)
        }
        ModelFormat::Torchscript => {
            let net = TorchScriptDenoiser::load_and_validate(&path, &manifest, device)?;
            let bytes = net.parameter_bytes();
            (Box::new(net), bytes)
        }
    };
    let model = DiffusionModel::new(manifest, net)?;
    Ok((model, parameter_bytes.max(size)))
}

/// Builds the autoencoder of a stored record (blocking): its module validated again as at
/// upload, so a module that no longer honours its manifest is never served.
fn load_autoencoder(record: &ModelRecord, dir: &Path, device: Device) -> Result<Loaded> {
    let (path, size) = verified_file(record, dir)?;
    let manifest: AutoencoderManifest = serde_json::from_value(record.manifest.clone())
        .map_err(|e| lost(record, format!("its stored manifest is unreadable: {e}")))?;
    if record.format != ModelFormat::Torchscript {
        return Err(lost(
            record,
            format!("an autoencoder's format is TorchScript, its record says {:?}", record.format),
        ));
    }
    let model = TorchScriptAutoencoder::load_and_validate(&path, &manifest, device).map_err(|e| match e {
        Error::InvalidArgument(m) => lost(record, m),
        other => other,
    })?;
    let bytes = model.parameter_bytes().max(size);
    let served = ServedAutoencoder { name: record.name.clone(), manifest, model: Mutex::new(model) };
    Ok(Loaded { model: Served::Autoencoder(Arc::new(served)), bytes })
}

/// Builds the reward model of a stored record (blocking).
fn load_reward(record: &ModelRecord, dir: &Path, device: Device) -> Result<Loaded> {
    let (path, size) = verified_file(record, dir)?;
    let manifest: RewardManifest = serde_json::from_value(record.manifest.clone())
        .map_err(|e| lost(record, format!("its stored manifest is unreadable: {e}")))?;
    match (record.format, &manifest.architecture) {
        (ModelFormat::Native, RewardSource::Native(_)) | (ModelFormat::Torchscript, RewardSource::Uploaded(_)) => {}
        (format, architecture) => {
            return Err(lost(
                record,
                format!("its record's format {format:?} does not fit its manifest's {architecture}"),
            ));
        }
    }
    let model = RewardModel::load(manifest.clone(), &path, dir, device).map_err(|e| match e {
        Error::DataLoss(m) | Error::InvalidArgument(m) => lost(record, m),
        other => other,
    })?;
    let bytes = model.parameter_bytes().max(size);
    let served = ServedReward {
        name: record.name.clone(),
        blob_key: record.blob_key.clone(),
        item_shape: model.item_shape().to_vec(),
        window: model.window(),
        manifest,
        model: Mutex::new(model),
    };
    Ok(Loaded { model: Served::Reward(Arc::new(served)), bytes })
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use tch::{Kind, Tensor};

    use super::*;
    use crate::config::{Config, Overrides};
    use crate::engine::manifest::{Architecture, Space};
    use crate::engine::schedule::Table;
    use crate::engine::torchscript::tests::export_fixtures;
    use crate::store::Provenance;

    async fn open_store(dir: &Path) -> (Store, Config) {
        let overrides = Overrides { data_dir: Some(dir.join("data")), ..Overrides::default() };
        let env = config::Environment::with_prefix("RELREWARD").source(Some(HashMap::new()));
        let config = Config::load_with_env(None, &overrides, env).expect("config");
        (Store::open(&config).await.expect("store"), config)
    }

    /// Registers `file` (copied into a staging directory) under `name`.
    async fn register(store: &Store, name: &str, file: &Path, format: ModelFormat, kind: ModelKind, manifest: &str) {
        let staging = store.blobs.staging().expect("staging");
        let target = staging.path().join("model.bin");
        std::fs::copy(file, &target).expect("copy");
        let (sha256, size_bytes) = sha256_file(&target).expect("hash");
        let record = ModelRecord {
            name: name.into(),
            kind,
            format,
            manifest: serde_json::from_str(manifest).expect("manifest json"),
            parameter_count: 0,
            sha256,
            size_bytes,
            file: "model.bin".into(),
            provenance: Provenance::Uploaded,
            created_at_ms: 0,
            description: String::new(),
            blob_key: String::new(),
        };
        store.commit_model(staging, record).await.expect("commit");
    }

    fn registry(store: &Store, cache_bytes: u64) -> ModelRegistry {
        let config = ModelsConfig { allow_torchscript_upload: false, max_upload_bytes: 1 << 30, cache_bytes };
        ModelRegistry::new(store.clone(), &config, Device::Cpu)
    }

    const MEAN: [f64; 3] = [1.0, -2.0, 0.5];

    #[tokio::test(flavor = "multi_thread")]
    async fn registry_serves_the_analytic_torchscript_model_exactly() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let fixtures = export_fixtures();
        let (store, _) = open_store(tmp.path()).await;
        let manifest = std::fs::read_to_string(fixtures.path().join("gaussian.json")).expect("manifest");
        register(
            &store,
            "gauss",
            &fixtures.path().join("gaussian.pt"),
            ModelFormat::Torchscript,
            ModelKind::Diffusion,
            &manifest,
        )
        .await;
        let reg = registry(&store, 1 << 30);
        let shared = reg.get_diffusion("gauss").await.expect("load");
        assert!(Arc::ptr_eq(&shared, &reg.get_diffusion("gauss").await.expect("cached")), "second get is a cache hit");
        assert_eq!(reg.cached_names(), ["gauss"]);

        let model = shared.lock();
        let abar = model.schedule.values(Table::AlphasCumprod).to_vec();
        let ts = [0i64, 1, 17, 48, 49];
        let x: Vec<f64> = (0..15).map(|i| (i as f64 * 0.37).sin() * 2.0).collect();
        let xt = Tensor::from_slice(&x).reshape([5, 3]).to_kind(Kind::Float);
        let eps = tch::no_grad(|| model.eps_hat(&xt, &Tensor::from_slice(&ts))).expect("eps_hat");
        for (b, &t) in ts.iter().enumerate() {
            let a = abar[t as usize];
            for (d, m) in MEAN.iter().enumerate() {
                let want = (1.0 - a).sqrt() * (x[b * 3 + d] - a.sqrt() * m);
                let got = eps.double_value(&[b as i64, d as i64]);
                assert!((got - want).abs() < 1e-5, "t = {t}, d = {d}: {got} vs {want}");
            }
        }
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn registry_loads_native_models_evicts_lru_and_invalidates() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let (store, _) = open_store(tmp.path()).await;
        let arch = Architecture::Mlp { hidden: vec![16] };
        let space = Space::Sample { shape: vec![3] };
        let net = NativeDenoiser::new(&arch, &space, None, 0, Device::Cpu).expect("net");
        let weights = tmp.path().join("weights.safetensors");
        net.save(&weights).expect("save");
        let manifest = serde_json::json!({
            "parametrization": "x0",
            "schedule": {"kind": "linear"},
            "n_timesteps": 100,
            "space": {"kind": "sample", "shape": [3]},
            "normalizer": {"kind": "gaussian", "mean": [0, 0, 0], "std": [1, 2, 3]},
            "architecture": {"kind": "mlp", "hidden": [16]},
        })
        .to_string();
        for name in ["a", "b", "c"] {
            register(&store, name, &weights, ModelFormat::Native, ModelKind::Diffusion, &manifest).await;
        }
        let bytes = net.parameter_count() * 4;
        // Room for two models.
        let reg = registry(&store, bytes * 2 + bytes / 2);
        let a = reg.get_diffusion("a").await.expect("a");
        let x = Tensor::zeros([2, 3], (Kind::Float, Device::Cpu));
        let t = Tensor::from_slice(&[0i64, 99]);
        let want = tch::no_grad(|| net.forward(&x, &t, None)).expect("forward");
        let got = tch::no_grad(|| a.lock().predict(&x, &t)).expect("predict");
        assert_eq!((&got - &want).abs().max().double_value(&[]), 0.0, "weights loaded exactly");

        reg.get_diffusion("b").await.expect("b");
        reg.get_diffusion("a").await.expect("a again"); // a is now more recent than b
        reg.get_diffusion("c").await.expect("c");
        assert_eq!(reg.cached_names(), ["a", "c"], "b was least recently used");
        assert_eq!(reg.cached_bytes(), 2 * bytes.max(std::fs::metadata(&weights).expect("meta").len()));
        assert!(Arc::ptr_eq(&a, &reg.get_diffusion("a").await.expect("a cached")));

        reg.invalidate("a");
        assert_eq!(reg.cached_names(), ["c"]);
        assert!(!Arc::ptr_eq(&a, &reg.get_diffusion("a").await.expect("a reloaded")));

        // A budget below one model: served, not kept.
        let tiny = registry(&store, 1);
        tiny.get_diffusion("a").await.expect("served");
        assert!(tiny.cached_names().is_empty());
        assert_eq!(tiny.cached_bytes(), 0);
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn registry_refuses_corrupt_files_wrong_kinds_and_unknown_names() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let fixtures = export_fixtures();
        let (store, _) = open_store(tmp.path()).await;
        let manifest = std::fs::read_to_string(fixtures.path().join("gaussian.json")).expect("manifest");
        let file = fixtures.path().join("gaussian.pt");
        register(&store, "good", &file, ModelFormat::Torchscript, ModelKind::Diffusion, &manifest).await;
        register(&store, "corrupt", &file, ModelFormat::Torchscript, ModelKind::Diffusion, &manifest).await;
        register(&store, "reward", &file, ModelFormat::Torchscript, ModelKind::Reward, "{}").await;
        register(&store, "bad-manifest", &file, ModelFormat::Torchscript, ModelKind::Diffusion, "{\"n_timesteps\": 3}")
            .await;

        let record = store.meta.get_model("corrupt").await.expect("get").expect("exists");
        let stored = store.blobs.local_dir(&record.blob_key).await.expect("dir").join(&record.file);
        let mut bytes = std::fs::read(&stored).expect("read");
        let last = bytes.len() - 1;
        bytes[last] ^= 1;
        std::fs::write(&stored, &bytes).expect("write");

        let reg = registry(&store, 1 << 30);
        match reg.get_diffusion("corrupt").await {
            Err(Error::DataLoss(m)) => assert!(m.contains("integrity") && m.contains("'corrupt'"), "{m}"),
            other => panic!("expected DataLoss, got {other:?}"),
        }
        match reg.get_diffusion("bad-manifest").await {
            Err(Error::DataLoss(m)) => assert!(m.contains("manifest"), "{m}"),
            other => panic!("expected DataLoss, got {other:?}"),
        }
        match reg.get_diffusion("reward").await {
            Err(Error::FailedPrecondition(m)) => assert!(m.contains("reward model, not a diffusion model"), "{m}"),
            other => panic!("expected FailedPrecondition, got {other:?}"),
        }
        assert!(matches!(reg.get_diffusion("absent").await, Err(Error::NotFound(_))));
        reg.get_diffusion("good").await.expect("the intact copy still loads");
        assert_eq!(reg.cached_names(), ["good"], "nothing corrupt was cached");

        // Deleted and registered again under the same name: the stale entry is not served.
        let old = reg.get_diffusion("good").await.expect("good");
        store.delete_model("good").await.expect("delete");
        assert!(matches!(reg.get_diffusion("good").await, Err(Error::NotFound(_))));
        register(&store, "good", &file, ModelFormat::Torchscript, ModelKind::Diffusion, &manifest).await;
        assert!(!Arc::ptr_eq(&old, &reg.get_diffusion("good").await.expect("re-registered")));
    }
}

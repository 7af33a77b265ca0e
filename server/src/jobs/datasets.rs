//! Reading stored datasets back for training: rows in raw units and, for trajectories, the
//! windows that lie inside episodes; and a samples dataset read as a recipe's prompt set
//! ([`resolve_prompt_dataset`]).

use std::path::Path;

use tch::Tensor;

use crate::engine::data::window_starts;
use crate::error::{Error, Result};
use crate::store::{DatasetKind, DatasetRecord, npy};

pub(crate) fn array<'a>(ds: &'a DatasetRecord, name: &str) -> Option<&'a crate::store::ArrayRecord> {
    ds.arrays.iter().find(|a| a.name == name)
}

/// Loads the dataset's rows in raw units and, for trajectories, the window starts.
/// Checks the files' digests first (once per load), so a corrupt dataset fails the job with
/// `DataLoss` naming it instead of training on damaged rows.
pub(crate) fn load_rows(store_dir: &Path, ds: &DatasetRecord, horizon: usize) -> Result<(Tensor, Option<Vec<i64>>)> {
    crate::store::Store::verify_dataset(store_dir, ds)?;
    let read = |name: &str| -> Result<Option<npy::Array>> {
        let Some(a) = array(ds, name) else { return Ok(None) };
        let dtype = relreward_proto::tensor::parse_dtype(&a.dtype)
            .ok_or_else(|| Error::DataLoss(format!("dataset '{}': unknown stored dtype {}", ds.name, a.dtype)))?;
        npy::read(&store_dir.join(&a.file), dtype, &a.shape).map(Some)
    };
    let floats = |a: &npy::Array| -> Result<Tensor> {
        let v = a.to_f32().ok_or_else(|| Error::DataLoss(format!("dataset '{}': non-float values", ds.name)))?;
        let shape: Vec<i64> = a.shape.iter().map(|&d| d as i64).collect();
        Ok(Tensor::from_slice(&v).reshape(&shape))
    };
    let n = ds.num_rows as usize;
    match ds.kind {
        DatasetKind::Samples => {
            let samples =
                read("samples")?.ok_or_else(|| Error::DataLoss(format!("dataset '{}' lacks samples", ds.name)))?;
            Ok((floats(&samples)?, None))
        }
        DatasetKind::Trajectories => {
            let missing = |what: &str| Error::DataLoss(format!("dataset '{}' lacks {what}", ds.name));
            let obs = floats(&read("observations")?.ok_or_else(|| missing("observations"))?)?;
            let act = floats(&read("actions")?.ok_or_else(|| missing("actions"))?)?;
            let mut ends = vec![false; n];
            for name in ["terminals", "timeouts"] {
                if let Some(flags) = read(name)?.and_then(|a| a.to_flags()) {
                    ends.iter_mut().zip(flags).for_each(|(e, f)| *e |= f);
                }
            }
            let starts_at = read("episode_starts")?.and_then(|a| a.to_flags()).unwrap_or_default();
            let rows = Tensor::cat(&[act, obs], 1);
            Ok((rows, Some(window_starts(n, horizon, &ends, &starts_at))))
        }
    }
}

/// A sample dataset's class labels as int64 `[N]`, or None when it has none. Reads the file
/// [`load_rows`] verified (call it after that).
pub(crate) fn load_labels(store_dir: &Path, ds: &DatasetRecord) -> Result<Option<Tensor>> {
    let Some(a) = array(ds, "labels") else { return Ok(None) };
    let dtype = relreward_proto::tensor::parse_dtype(&a.dtype)
        .ok_or_else(|| Error::DataLoss(format!("dataset '{}': unknown stored dtype {}", ds.name, a.dtype)))?;
    let labels = npy::read(&store_dir.join(&a.file), dtype, &a.shape)?
        .to_i64()
        .ok_or_else(|| Error::DataLoss(format!("dataset '{}': labels stored as {}", ds.name, a.dtype)))?;
    Ok(Some(Tensor::from_slice(&labels)))
}

/// Most labels, and most embedding values, a prompt dataset may give a recipe.
const MAX_PROMPT_LABELS: usize = 1_000_000;
const MAX_PROMPT_VALUES: usize = 1 << 24;

/// A `Prompts` message naming a stored dataset (`dataset`) made into the conditions it holds:
/// its `labels` array, or without one its `samples` rows flattened to embeddings `[k, dim]`.
/// Returns the dataset's name (None when `p` names none, and `p` is left as it is). Errors name
/// `field` (e.g. "recipe.prompts"): labels or embeddings beside the dataset, an unknown dataset
/// (NotFound), a trajectory dataset, one too large.
pub(crate) async fn resolve_prompt_dataset(
    store: &crate::store::Store,
    p: &mut relreward_proto::v1::Prompts,
    field: &str,
) -> Result<Option<String>> {
    if p.dataset.is_empty() {
        return Ok(None);
    }
    crate::fields::validate_name(&format!("{field}.dataset"), &p.dataset)?;
    if !p.labels.is_empty() || p.embeddings.is_some() {
        return Err(Error::invalid(format!(
            "{field}.dataset: set together with labels or embeddings; give one of them"
        )));
    }
    let name = std::mem::take(&mut p.dataset);
    let ds = store
        .meta
        .get_dataset(&name)
        .await?
        .ok_or_else(|| Error::NotFound(format!("{field}.dataset: dataset '{name}' not found")))?;
    if ds.kind != DatasetKind::Samples {
        return Err(Error::invalid(format!(
            "{field}.dataset: dataset '{name}' holds trajectories; a prompt set is a samples dataset (its labels, or \
             its samples as embeddings)"
        )));
    }
    let labelled = array(&ds, "labels").is_some();
    let (k, width) = match array(&ds, "samples") {
        Some(a) => (a.shape.first().copied().unwrap_or(0) as usize, a.shape[1..].iter().product::<u64>() as usize),
        None => (0, 0),
    };
    if labelled && k > MAX_PROMPT_LABELS || !labelled && k.saturating_mul(width) > MAX_PROMPT_VALUES {
        return Err(Error::invalid(format!(
            "{field}.dataset: dataset '{name}' is too large for a prompt set (at most {MAX_PROMPT_LABELS} labels or \
             {MAX_PROMPT_VALUES} embedding values)"
        )));
    }
    let dir = store.blobs.local_dir(&ds.blob_key).await?;
    tokio::task::block_in_place(|| -> Result<()> {
        if labelled {
            // The labels alone: the samples beside them are not read (only their digests checked).
            crate::store::Store::verify_dataset(&dir, &ds)?;
            let labels = load_labels(&dir, &ds)?.ok_or_else(|| Error::internal("prompt dataset", "labels vanished"))?;
            p.labels = Vec::<i64>::try_from(&labels).map_err(|e| Error::internal("reading prompt labels", e))?;
        } else {
            let (rows, _) = load_rows(&dir, &ds, 1)?;
            let flat = rows.reshape([k as i64, width as i64]).to_kind(tch::Kind::Float).contiguous();
            let values =
                Vec::<f32>::try_from(&flat.view([-1])).map_err(|e| Error::internal("reading prompt embeddings", e))?;
            p.embeddings = Some(relreward_proto::tensor::encode_f32(&[k as u64, width as u64], &values));
        }
        Ok(())
    })?;
    Ok(Some(name))
}

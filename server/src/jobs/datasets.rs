//! Reading stored datasets back for training: rows in raw units and, for trajectories, the
//! windows that lie inside episodes.

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

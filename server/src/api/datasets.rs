//! `relreward.v1.DatasetService`: upload, get, list, delete.
//!
//! Thin by design: the stream protocol (header, chunks, commit) is enforced here; validation
//! of the data itself is `store::ingest`, durability is `store`.

use relreward_proto::v1::{self as pb, dataset_service_server::DatasetService, upload_dataset_request::Message};
use tonic::{Request, Response, Status, Streaming};

use super::{next_upload, page_limit, timestamp};
use crate::error::Error;
use crate::fields::{self, validate_name};
use crate::jobs::JobManager;
use crate::limits::{DiskBudget, is_disk_full};
use crate::store::ingest::DatasetIngest;

const DATASET_VIEW: &str = "view";
const DATASET_VIEWS: &str = "DATASET_VIEW_UNSPECIFIED, DATASET_VIEW_BASIC or DATASET_VIEW_FULL";
use crate::store::{DatasetKind, DatasetRecord, Store};

pub struct Datasets {
    store: Store,
    jobs: JobManager,
    max_upload_bytes: u64,
    /// `storage.max_bytes`, shared by every upload.
    budget: DiskBudget,
}

impl Datasets {
    pub fn new(store: Store, jobs: JobManager, max_upload_bytes: u64, budget: DiskBudget) -> Self {
        Self { store, jobs, max_upload_bytes, budget }
    }

    /// An upload, with a full disk (ENOSPC, a filesystem quota) reported as what it is: the
    /// client can free space and retry, which INTERNAL would not tell it. Whatever failed, the
    /// staging directory is gone by now (dropped with the ingest), so nothing half-written stays.
    async fn upload(&self, stream: Streaming<pb::UploadDatasetRequest>) -> Result<pb::Dataset, Error> {
        self.upload_inner(stream).await.map_err(|e| {
            if is_disk_full(&e) {
                tracing::warn!(error = %e, "dataset upload refused: disk full");
                Error::ResourceExhausted(
                    "the disk holding storage.data_dir is full (or its filesystem quota is reached); the upload was \
                     discarded"
                        .into(),
                )
            } else {
                e
            }
        })
    }

    async fn upload_inner(&self, mut stream: Streaming<pb::UploadDatasetRequest>) -> Result<pb::Dataset, Error> {
        let header = match next_upload(&mut stream, |m: pb::UploadDatasetRequest| m.message).await? {
            Some(Message::Header(h)) => h,
            Some(_) => return Err(Error::invalid("message 1: the first message of an upload must be a header")),
            None => return Err(Error::invalid("upload stream was empty: expected a header, chunks and a commit")),
        };
        validate_name("header.name", &header.name)?;
        fields::check_description("header.description", &header.description)?;
        if self.store.meta.get_dataset(&header.name).await?.is_some() {
            return Err(Error::AlreadyExists(format!("dataset '{}' already exists", header.name)));
        }
        let name = header.name.clone();
        let needs = disk_bytes(&header);
        let staging = self.store.blobs.staging()?;
        let mut ingest = DatasetIngest::begin(header, self.max_upload_bytes, staging).map_err(|e| match e {
            // The ingest names the header field; the operator also needs the key to raise.
            Error::ResourceExhausted(m) => Error::ResourceExhausted(format!("{m} (datasets.max_upload_bytes)")),
            other => other,
        })?;
        // After the header is known valid (its sizes are then trustworthy), before any payload
        // is written; held until the files are published and counted on disk.
        let _reservation =
            tokio::task::block_in_place(|| self.budget.reserve(needs, &format!("header: dataset '{name}'")))?;
        let sha256 = loop {
            match next_upload(&mut stream, |m: pb::UploadDatasetRequest| m.message).await? {
                // Hashing, statistics and file writes are CPU and disk work: keep them off the
                // async worker's poll loop.
                Some(Message::Chunk(c)) => {
                    tokio::task::block_in_place(|| ingest.accept(c))?;
                    crate::fault::point("upload.chunk");
                }
                Some(Message::Commit(c)) => break c.sha256,
                Some(Message::Header(_)) => {
                    return Err(Error::invalid("header: sent twice; one upload has one header"));
                }
                None => return Err(Error::invalid("upload ended without a commit message; nothing was stored")),
            }
        };
        if next_upload(&mut stream, |m: pb::UploadDatasetRequest| m.message).await?.is_some() {
            return Err(Error::invalid("commit: must be the last message of the upload"));
        }
        let (staging, record) = tokio::task::block_in_place(|| ingest.finish(&sha256))?;
        let record = self.store.commit_dataset(staging, record).await?;
        tracing::info!(dataset = record.name, rows = record.num_rows, bytes = record.size_bytes, "dataset stored");
        Ok(to_proto(&record, pb::DatasetView::Full))
    }
}

#[tonic::async_trait]
impl DatasetService for Datasets {
    async fn upload_dataset(
        &self,
        request: Request<Streaming<pb::UploadDatasetRequest>>,
    ) -> Result<Response<pb::Dataset>, Status> {
        Ok(Response::new(self.upload(request.into_inner()).await?))
    }

    async fn get_dataset(&self, request: Request<pb::GetDatasetRequest>) -> Result<Response<pb::Dataset>, Status> {
        let req = request.into_inner();
        validate_name("name", &req.name)?;
        // Unspecified: the full view for a single dataset.
        let view = match fields::known(DATASET_VIEW, req.view, DATASET_VIEWS)? {
            pb::DatasetView::Basic => pb::DatasetView::Basic,
            pb::DatasetView::Unspecified | pb::DatasetView::Full => pb::DatasetView::Full,
        };
        let record = self
            .store
            .meta
            .get_dataset(&req.name)
            .await?
            .ok_or_else(|| Error::NotFound(format!("dataset '{}' not found", req.name)))?;
        Ok(Response::new(to_proto(&record, view)))
    }

    async fn list_datasets(
        &self,
        request: Request<pb::ListDatasetsRequest>,
    ) -> Result<Response<pb::ListDatasetsResponse>, Status> {
        let req = request.into_inner();
        let page = req.page.unwrap_or_default();
        let limit = page_limit(page.page_size);
        // Unspecified: the basic view for a listing.
        let view = match fields::known(DATASET_VIEW, req.view, DATASET_VIEWS)? {
            pb::DatasetView::Full => pb::DatasetView::Full,
            pb::DatasetView::Unspecified | pb::DatasetView::Basic => pb::DatasetView::Basic,
        };
        let after = fields::name_page_token(&page.page_token, "ListDatasets")?;
        // One extra row tells whether another page exists.
        let mut records = self.store.meta.list_datasets(after, limit + 1).await?;
        let next_page_token = if records.len() > limit {
            records.truncate(limit);
            records.last().map(|r| fields::next_name_token(&r.name)).unwrap_or_default()
        } else {
            String::new()
        };
        let datasets = records.iter().map(|r| to_proto(r, view)).collect();
        Ok(Response::new(pb::ListDatasetsResponse { datasets, next_page_token }))
    }

    async fn delete_dataset(
        &self,
        request: Request<pb::DeleteDatasetRequest>,
    ) -> Result<Response<pb::DeleteDatasetResponse>, Status> {
        let req = request.into_inner();
        validate_name("name", &req.name)?;
        let _references = self.store.references().await;
        // A job re-reads its datasets when it resumes after a restart: keep them until it ends.
        if self.store.meta.get_dataset(&req.name).await?.is_some()
            && let Some(job) = self.jobs.job_using(&req.name).await?
        {
            return Err(Error::FailedPrecondition(format!(
                "name: dataset '{}' is in use by job '{job}'; cancel the job or wait for it to finish, then delete",
                req.name
            ))
            .into());
        }
        self.store.delete_dataset(&req.name).await?;
        tracing::info!(dataset = req.name, "dataset deleted");
        Ok(Response::new(pb::DeleteDatasetResponse {}))
    }
}

/// Bytes the upload described by `header` takes on disk: its payload plus one `.npy` header
/// per array (at most a few hundred bytes; 4 KiB each leaves room for the filesystem's blocks).
/// An array with an invalid dtype or shape counts 0: `DatasetIngest::begin` refuses those.
fn disk_bytes(header: &pb::UploadHeader) -> u64 {
    header.arrays.iter().fold(0u64, |total, spec| {
        let payload = relreward_proto::tensor::known_dtype(spec.dtype)
            .and_then(|dtype| relreward_proto::tensor::byte_len(&spec.shape, dtype))
            .unwrap_or(0);
        total.saturating_add(payload).saturating_add(4096)
    })
}

fn to_proto(r: &DatasetRecord, view: pb::DatasetView) -> pb::Dataset {
    let full = view == pb::DatasetView::Full;
    pb::Dataset {
        name: r.name.clone(),
        kind: match r.kind {
            DatasetKind::Trajectories => pb::DatasetKind::Trajectories,
            DatasetKind::Samples => pb::DatasetKind::Samples,
        } as i32,
        num_rows: r.num_rows,
        arrays: r
            .arrays
            .iter()
            .map(|a| pb::ArrayInfo {
                spec: Some(pb::ArraySpec {
                    name: a.name.clone(),
                    dtype: relreward_proto::tensor::parse_dtype(&a.dtype).unwrap_or(pb::Dtype::Unspecified) as i32,
                    shape: a.shape.clone(),
                }),
                stats: a.stats.as_ref().filter(|_| full).map(|s| pb::ArrayStats {
                    min: s.min.clone(),
                    max: s.max.clone(),
                    mean: s.mean.clone(),
                    std: s.std.clone(),
                }),
            })
            .collect(),
        episodes: r.episodes.as_ref().map(|e| pb::EpisodeInfo {
            count: e.count,
            min_length: e.min_length,
            max_length: e.max_length,
            mean_length: e.mean_length,
        }),
        sha256: r.sha256.clone(),
        size_bytes: r.size_bytes,
        created_at: Some(timestamp(r.created_at_ms)),
        description: r.description.clone(),
    }
}

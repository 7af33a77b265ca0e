//! Building dataset uploads for the end-to-end tests (here and in server/tests/): upload
//! messages sent raw (header, chunks, commit), so that malformed streams can be built too, and
//! a small valid trajectory upload.

use relreward_client::Client;
use relreward_client::pb::{self, Dtype, upload_dataset_request::Message};
use relreward_client::tensor::encode_f32;
use sha2::{Digest, Sha256};

pub fn header(name: &str, kind: pb::DatasetKind, arrays: &[(&str, Dtype, &[u64])]) -> pb::UploadDatasetRequest {
    let arrays = arrays
        .iter()
        .map(|(n, d, s)| pb::ArraySpec { name: (*n).into(), dtype: *d as i32, shape: s.to_vec() })
        .collect();
    msg(Message::Header(pb::UploadHeader { name: name.into(), kind: kind as i32, arrays, description: String::new() }))
}

pub fn chunk(array: &str, t: pb::Tensor) -> pb::UploadDatasetRequest {
    msg(Message::Chunk(pb::DatasetChunk { array: array.into(), data: Some(t) }))
}

pub fn commit(sha256: &str) -> pb::UploadDatasetRequest {
    msg(Message::Commit(pb::UploadCommit { sha256: sha256.into() }))
}

pub fn msg(m: Message) -> pb::UploadDatasetRequest {
    pb::UploadDatasetRequest { message: Some(m) }
}

pub fn sha(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update(p);
    }
    hex::encode(h.finalize())
}

pub fn flags(v: &[u8]) -> pb::Tensor {
    pb::Tensor { shape: vec![v.len() as u64], dtype: Dtype::Bool as i32, data: v.to_vec() }
}

pub async fn raw_upload(client: &Client, msgs: Vec<pb::UploadDatasetRequest>) -> Result<pb::Dataset, tonic::Status> {
    client.datasets().upload_dataset(tokio_stream::iter(msgs)).await.map(|r| r.into_inner())
}

/// A valid 6-row trajectory upload: observations [6, 3], actions [6, 2], terminals [6].
pub fn small_upload(name: &str) -> Vec<pb::UploadDatasetRequest> {
    let obs: Vec<f32> = (0..18).map(|i| i as f32 * 0.5).collect();
    let act: Vec<f32> = (0..12).map(|i| (i as f32 - 6.0) / 6.0).collect();
    let o1 = encode_f32(&[4, 3], &obs[..12]);
    let o2 = encode_f32(&[2, 3], &obs[12..]);
    let a = encode_f32(&[6, 2], &act);
    let t = flags(&[0, 0, 1, 0, 0, 1]);
    let digest = sha(&[&o1.data, &o2.data, &a.data, &t.data]);
    vec![
        header(
            name,
            pb::DatasetKind::Trajectories,
            &[
                ("observations", Dtype::Float32, &[6, 3]),
                ("actions", Dtype::Float32, &[6, 2]),
                ("terminals", Dtype::Bool, &[6]),
            ],
        ),
        chunk("observations", o1),
        chunk("observations", o2),
        chunk("actions", a),
        chunk("terminals", t),
        commit(&digest),
    ]
}

//! Sampling through the service from a model registered by upload: the analytic Gaussian
//! eps-model for data N(m, I), exported as TorchScript by a fixture script, sampled 4096 times
//! with the Sample RPC on T = 1000 steps (with few steps, DDPM's posterior variances lose
//! visibly more than 5% of the variance). The sample mean must be within 3 standard errors of
//! m and the variance within 5% of 1 per coordinate; the same seed must give the same samples.

use std::sync::Arc;

use relreward_client::client::UploadProgress;
use relreward_client::pb;
use relreward_client::tensor::decode_finite_f32;
use relreward_tests::{TestServer, python, repo_root};
use tokio_stream::StreamExt;

const M: [f64; 3] = [1.5, -0.5, 0.25];

async fn sample(client: &relreward_client::Client, n: u32, seed: u64) -> Vec<Vec<f32>> {
    let req = pb::SampleRequest { model: "gauss".into(), n, seed: Some(seed), batch_size: 1024, ..Default::default() };
    let mut stream = client.rewards().sample(req).await.expect("sample").into_inner();
    let mut out = vec![Vec::new(); n as usize];
    while let Some(item) = stream.next().await {
        let item = item.expect("item");
        let x = item.x.expect("x");
        assert_eq!(x.shape, vec![M.len() as u64]);
        out[item.index as usize] = decode_finite_f32(&x).expect("finite");
    }
    assert!(out.iter().all(|v| v.len() == M.len()), "every index answered once");
    out
}

#[tokio::test(flavor = "multi_thread")]
async fn analytic_gaussian_registered_by_upload_samples_its_distribution() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = server.client().await;
    let tmp = tempfile::tempdir().expect("tmp");
    let mean = M.iter().map(f64::to_string).collect::<Vec<_>>().join(",");
    let status = std::process::Command::new(python())
        .arg(repo_root().join("tests/python/analytic_gaussian.py"))
        .args(["--out", tmp.path().to_str().expect("utf8"), "--mean", &mean, "--schedule", "cosine", "--T", "1000"])
        .status()
        .expect("python");
    assert!(status.success());
    let manifest = pb::DiffusionManifest {
        parametrization: pb::Parametrization::Epsilon as i32,
        schedule: Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.008 })) }),
        n_timesteps: 1000,
        clip_denoised: false,
        space: Some(pb::diffusion_manifest::Space::Sample(pb::diffusion_manifest::Sample {
            shape: vec![M.len() as u64],
        })),
        normalizer: Some(pb::Normalizer { kind: Some(pb::normalizer::Kind::Identity(pb::normalizer::Identity {})) }),
        architecture: None,
        conditioning: None,
    };
    let header = pb::UploadModelHeader {
        name: "gauss".into(),
        manifest: Some(manifest),
        description: String::new(),
        format: 0,
        reward: None,
        autoencoder: None,
    };
    client
        .upload_model(header, &tmp.path().join("model.pt"), Arc::new(UploadProgress::default()))
        .await
        .expect("upload");

    let n = 4096;
    let samples = sample(&client, n, 5).await;
    for (j, &m) in M.iter().enumerate() {
        let v: Vec<f64> = samples.iter().map(|s| f64::from(s[j])).collect();
        let mean = v.iter().sum::<f64>() / f64::from(n);
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / f64::from(n - 1);
        let se = (var / f64::from(n)).sqrt();
        assert!((mean - m).abs() < 3.0 * se, "coordinate {j}: mean {mean} vs {m} (3 se = {})", 3.0 * se);
        assert!((var - 1.0).abs() < 0.05, "coordinate {j}: variance {var}");
    }
    assert_eq!(sample(&client, 16, 9).await, sample(&client, 16, 9).await, "same seed, same samples");
    assert_ne!(sample(&client, 16, 9).await, sample(&client, 16, 10).await);

    // Bad requests: unknown model, too many samples, a condition on a sample-space model.
    let err = client
        .rewards()
        .sample(pb::SampleRequest { model: "nope".into(), ..Default::default() })
        .await
        .expect_err("missing");
    assert_eq!(err.code(), tonic::Code::NotFound);
    let err = client
        .rewards()
        .sample(pb::SampleRequest { model: "gauss".into(), n: 1_000_000, ..Default::default() })
        .await
        .expect_err("n");
    assert!(err.message().starts_with("n:"), "{}", err.message());
    let cond = pb::Condition { index: 0, state: Some(relreward_client::tensor::encode_f32(&[3], &[0.0; 3])) };
    let req = pb::SampleRequest { model: "gauss".into(), conditions: vec![cond], ..Default::default() };
    let err = client.rewards().sample(req).await.expect_err("condition");
    assert_eq!(err.code(), tonic::Code::InvalidArgument);
    assert!(err.message().contains("conditions[0]"), "{}", err.message());
}

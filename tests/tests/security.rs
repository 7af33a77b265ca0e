//! Access control, safe defaults and TLS, end to end (issue 8, parts 1 to 3).
//!
//! - Tokens made by `relreward-server token create` and pasted into the configuration as it
//!   says: every scope (and no, a bad, an expired token) against a representative RPC of each
//!   service, unary and streaming, native and OIP; refusals come before any handler, so a
//!   missing resource behind a missing scope is PERMISSION_DENIED, never NOT_FOUND.
//! - The same tokens through the CLI (`--token`, `RELREWARD_TOKEN`), the Rust client and the
//!   Python planner example, on a real trained reward model.
//! - The server refuses to start on all interfaces without tokens, unless told to.
//! - TLS and mutual TLS with certificates generated here (rcgen): the TLS listener refuses
//!   plaintext and unknown CAs; with a client CA, a client without a certificate it signed
//!   is refused; tokens and OIP work over TLS.
//! - Names never reach the filesystem as paths (path traversal).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;

use relreward_client::client::{ConnectOptions, DatasetUpload, TlsOptions, UploadProgress};
use relreward_client::pb;
use relreward_client::{Client, ClientError, MemorySource, tensor};
use relreward_proto::inference as oip;
use relreward_proto::inference::grpc_inference_service_client::GrpcInferenceServiceClient;
use relreward_tests::{Access, TestServer, bin, ok, python, refused, repo_root, stderr, stdout, train_tiny_reward};
use tokio_stream::StreamExt;
use tonic::Code;

// ---------------------------------------------------------------------------------------------
// Tokens

/// A token from `relreward-server token create`, and the entry it printed for the config.
struct Made {
    token: String,
    entry: String,
}

fn token_create(args: &[&str]) -> Made {
    let out = Command::new(bin("relreward-server")).args(["token", "create"]).args(args).output().expect("run");
    assert!(out.status.success(), "token create {args:?}: {}", stderr(&out));
    let text = stdout(&out);
    let token = text.lines().find_map(|l| l.strip_prefix("token: ")).expect("a token line").to_owned();
    let line = text.lines().find(|l| l.starts_with("tokens = [")).expect("a config line");
    let entry = line.strip_prefix("tokens = [").and_then(|l| l.strip_suffix(']')).expect("one entry").to_owned();
    assert!(!text.contains(&format!("\"{token}\"")), "the config entry must not hold the token itself:\n{text}");
    Made { token, entry }
}

/// Four tokens (read, train, admin and an expired admin one) and the `[security]` section
/// listing them.
struct Tokens {
    read: String,
    train: String,
    admin: String,
    expired: String,
    config: String,
}

fn tokens() -> Tokens {
    let read = token_create(&["--scopes", "read", "--name", "reader"]);
    let train = token_create(&["--scopes", "read,train", "--name", "trainer", "--expires", "30d"]);
    let admin = token_create(&["--scopes", "admin", "--name", "operator"]);
    let expired = token_create(&["--scopes", "admin", "--name", "old", "--expires", "2001-01-01T00:00:00Z"]);
    let config = format!(
        "[security]\ntokens = [\n  {},\n  {},\n  {},\n  {},\n]\n",
        read.entry, train.entry, admin.entry, expired.entry
    );
    Tokens { read: read.token, train: train.token, admin: admin.token, expired: expired.token, config }
}

/// A plaintext client of `server` with `token`.
async fn connect(server: &TestServer, token: Option<&str>) -> Client {
    let options = ConnectOptions { token: token.map(str::to_owned), tls: None };
    Client::connect_with(&format!("http://{}", server.addr), &options).await.expect("connect")
}

fn code<T>(result: Result<T, ClientError>) -> Code {
    match result {
        Ok(_) => Code::Ok,
        Err(ClientError::Status(s)) => s.code(),
        Err(e) => panic!("not a gRPC status: {e}"),
    }
}

fn status_code<T>(result: Result<T, tonic::Status>) -> Code {
    result.map_or_else(|s| s.code(), |_| Code::Ok)
}

fn lines_source() -> MemorySource {
    let n = 24u64;
    let obs: Vec<f32> = (0..2 * n).map(|i| i as f32 * 0.1).collect();
    let mut timeouts = vec![false; n as usize];
    timeouts[n as usize - 1] = true;
    let mut source = MemorySource::new();
    source.push_f32("observations", &[n, 2], &obs).push_f32("actions", &[n, 2], &obs).push_bool("timeouts", &timeouts);
    source
}

async fn upload(client: &Client, name: &str) -> Result<pb::Dataset, ClientError> {
    let upload = DatasetUpload {
        name: name.into(),
        kind: pb::DatasetKind::Trajectories,
        description: String::new(),
        chunk_bytes: 1 << 20,
    };
    client.upload_dataset(upload, lines_source(), Arc::new(UploadProgress::default())).await
}

/// A representative call of every service, each on a resource that does not exist (or a
/// harmless one), so what an admitted caller gets is the handler's own answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Rpc {
    ListDatasets,
    GetMissingDataset,
    UploadDataset,
    DeleteMissingDataset,
    GetMissingModel,
    DownloadMissingModel,
    UploadModelBadName,
    DeleteMissingModel,
    SubmitJobMissingDataset,
    ListJobs,
    WatchMissingJob,
    CancelMissingJob,
    ScoreMissingModel,
    GradientStreamMissingModel,
    SampleMissingModel,
    EncodeMissingModel,
    DecodeMissingModel,
    OipServerLive,
    OipMetadataMissingModel,
}

const MISSING: &str = "no-such-thing";

async fn call(client: &Client, rpc: Rpc, who: &str) -> Code {
    let x = tensor::encode_f32(&[1, 8, 4], &[0.0; 32]);
    match rpc {
        Rpc::ListDatasets => code(client.list_datasets().await),
        Rpc::GetMissingDataset => code(client.get_dataset(MISSING).await),
        // A fresh name per caller: the upload itself must succeed when admitted.
        Rpc::UploadDataset => code(upload(client, &format!("up-{who}")).await),
        Rpc::DeleteMissingDataset => code(client.delete_dataset(MISSING).await),
        Rpc::GetMissingModel => code(client.get_model(MISSING).await),
        Rpc::DownloadMissingModel => status_code(
            client
                .models()
                .download_model(pb::DownloadModelRequest { name: MISSING.into(), ..Default::default() })
                .await,
        ),
        Rpc::UploadModelBadName => {
            let header = pb::UploadModelHeader { name: "Not A Name".into(), ..Default::default() };
            let msg = pb::UploadModelRequest { message: Some(pb::upload_model_request::Message::Header(header)) };
            status_code(client.models().upload_model(tokio_stream::iter([msg])).await)
        }
        Rpc::DeleteMissingModel => code(client.delete_model(MISSING).await),
        Rpc::SubmitJobMissingDataset => {
            let spec = pb::JobSpec {
                output_model: format!("out-{who}"),
                kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
                    dataset: MISSING.into(),
                    ..Default::default()
                })),
                ..Default::default()
            };
            code(client.submit_job(spec, None).await)
        }
        Rpc::ListJobs => code(client.list_jobs(pb::JobState::Unspecified).await),
        Rpc::WatchMissingJob => match client.watch_job(MISSING, 0).await {
            Ok(mut stream) => match stream.next().await {
                Some(Err(s)) => s.code(),
                other => panic!("watch of a missing job: {other:?}"),
            },
            Err(e) => code::<()>(Err(e)),
        },
        Rpc::CancelMissingJob => code(client.cancel_job(MISSING).await),
        Rpc::ScoreMissingModel => {
            code(client.score(pb::ScoreRequest { model: MISSING.into(), x: Some(x), ..Default::default() }).await)
        }
        Rpc::GradientStreamMissingModel => {
            let stream = match client.gradient_stream().await {
                Ok(s) => s,
                Err(e) => return code::<()>(Err(e)),
            };
            let req = pb::GradientRequest {
                request_id: 1,
                model: MISSING.into(),
                x: Some(x),
                t: vec![0],
                ..Default::default()
            };
            // A refused call may end before the request is taken: then the status is in the
            // responses.
            let _ = stream.send(req).await;
            let mut stream = stream;
            match stream.message().await {
                // An admitted call answers per request, with the error inside the response.
                Ok(Some(resp)) => resp.error.map_or(Code::Ok, |e| Code::from(e.code)),
                Ok(None) => panic!("gradient stream ended without an answer"),
                Err(e) => code::<()>(Err(e)),
            }
        }
        Rpc::SampleMissingModel => {
            match client.sample(pb::SampleRequest { model: MISSING.into(), n: 1, ..Default::default() }).await {
                Ok(mut stream) => match stream.next().await {
                    Some(Err(s)) => s.code(),
                    other => panic!("sample of a missing model: {other:?}"),
                },
                Err(e) => code::<()>(Err(e)),
            }
        }
        Rpc::EncodeMissingModel => {
            code(client.encode(pb::EncodeRequest { model: MISSING.into(), images: Some(x) }).await)
        }
        Rpc::DecodeMissingModel => {
            code(client.decode(pb::DecodeRequest { model: MISSING.into(), latents: Some(x) }).await)
        }
        Rpc::OipServerLive => {
            let mut oip = GrpcInferenceServiceClient::new(client.transport());
            status_code(oip.server_live(oip::ServerLiveRequest {}).await)
        }
        Rpc::OipMetadataMissingModel => {
            let mut oip = GrpcInferenceServiceClient::new(client.transport());
            let req = oip::ModelMetadataRequest { name: MISSING.into(), version: String::new() };
            status_code(oip.model_metadata(req).await)
        }
    }
}

/// What an admitted caller gets (the handler's own answer), and the scope the call needs.
fn expectation(rpc: Rpc) -> (Code, &'static str) {
    use Code::*;
    match rpc {
        Rpc::ListDatasets | Rpc::ListJobs | Rpc::OipServerLive => (Ok, "read"),
        Rpc::GetMissingDataset
        | Rpc::GetMissingModel
        | Rpc::DownloadMissingModel
        | Rpc::WatchMissingJob
        | Rpc::ScoreMissingModel
        | Rpc::GradientStreamMissingModel
        | Rpc::SampleMissingModel
        | Rpc::EncodeMissingModel
        | Rpc::DecodeMissingModel
        | Rpc::OipMetadataMissingModel => (NotFound, "read"),
        Rpc::UploadDataset => (Ok, "train"),
        Rpc::DeleteMissingDataset | Rpc::CancelMissingJob => (NotFound, "train"),
        Rpc::SubmitJobMissingDataset => (NotFound, "train"),
        Rpc::UploadModelBadName => (InvalidArgument, "admin"),
        Rpc::DeleteMissingModel => (NotFound, "admin"),
    }
}

const RPCS: [Rpc; 19] = [
    Rpc::ListDatasets,
    Rpc::GetMissingDataset,
    Rpc::UploadDataset,
    Rpc::DeleteMissingDataset,
    Rpc::GetMissingModel,
    Rpc::DownloadMissingModel,
    Rpc::UploadModelBadName,
    Rpc::DeleteMissingModel,
    Rpc::SubmitJobMissingDataset,
    Rpc::ListJobs,
    Rpc::WatchMissingJob,
    Rpc::CancelMissingJob,
    Rpc::ScoreMissingModel,
    Rpc::GradientStreamMissingModel,
    Rpc::SampleMissingModel,
    Rpc::EncodeMissingModel,
    Rpc::DecodeMissingModel,
    Rpc::OipServerLive,
    Rpc::OipMetadataMissingModel,
];

#[tokio::test(flavor = "multi_thread")]
async fn every_scope_against_every_service() {
    let t = tokens();
    let config = format!("{}\n[models]\nallow_torchscript_upload = true\n", t.config);
    let server = TestServer::start_with_config(&config, &[]);
    let rank = |scope: &str| ["read", "train", "admin"].iter().position(|s| *s == scope).expect("scope");
    let callers: [(&str, Option<&str>, Option<usize>); 6] = [
        ("none", None, None),
        ("bad", Some("rrt_0000000000000000000000000000000000000000000000000000000000000000"), None),
        ("expired", Some(&t.expired), None),
        ("read", Some(&t.read), Some(0)),
        ("train", Some(&t.train), Some(1)),
        ("admin", Some(&t.admin), Some(2)),
    ];
    let mut failures = Vec::new();
    for (who, token, level) in callers {
        let client = connect(&server, token).await;
        for rpc in RPCS {
            let (admitted, scope) = expectation(rpc);
            let want = match level {
                None => Code::Unauthenticated,
                Some(level) if level >= rank(scope) => admitted,
                Some(_) => Code::PermissionDenied,
            };
            let got = call(&client, rpc, who).await;
            if got != want {
                failures.push(format!("{who} {rpc:?}: got {got:?}, want {want:?}"));
            }
        }
        // Health stays open to every caller (probes carry no token).
        let health = client.health().await.expect("health needs no token");
        assert_eq!(health, tonic_health::pb::health_check_response::ServingStatus::Serving);
    }
    assert!(failures.is_empty(), "{}\nserver log:\n{}", failures.join("\n"), server.log());

    // The refusals say what to do, and name the scope.
    let reader = connect(&server, Some(&t.read)).await;
    let err = reader.delete_dataset(MISSING).await.expect_err("denied").to_string();
    assert!(err.contains("PERMISSION_DENIED") && err.contains("'reader'") && err.contains("needs 'train'"), "{err}");
    assert!(!err.contains(MISSING), "the refusal must not discuss the resource: {err}");
    let anonymous = connect(&server, None).await;
    let err = anonymous.list_models(pb::ModelKind::Unspecified).await.expect_err("refused").to_string();
    assert!(err.contains("UNAUTHENTICATED") && err.contains("--token"), "{err}");
    let expired = connect(&server, Some(&t.expired)).await;
    let err = expired.list_jobs(pb::JobState::Unspecified).await.expect_err("expired").to_string();
    assert!(err.contains("'old' expired at 2001-01-01T00:00:00Z"), "{err}");

    // Only admitted uploads were stored.
    let names: Vec<String> = reader.list_datasets().await.expect("list").into_iter().map(|d| d.name).collect();
    assert_eq!(names, ["up-admin", "up-train"]);

    // Changes are audited by token name; no token ever reaches the log.
    let log = server.log();
    assert!(log.contains("authorized call") && log.contains("trainer"), "{log}");
    // Only calls that need train or admin are audited, not reads made with such a token (the
    // admin and train callers above listed datasets and jobs and scored).
    let audited_reads: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("authorized call"))
        .filter(|l| ["/ListDatasets", "/ListJobs", "/Score", "/GetModel", "ServerLive"].iter().any(|m| l.contains(m)))
        .collect();
    assert!(audited_reads.is_empty(), "reads in the audit log:\n{}", audited_reads.join("\n"));
    for secret in [&t.read, &t.train, &t.admin, &t.expired] {
        assert!(!log.contains(secret.as_str()), "a token leaked into the log");
    }
}

/// A whole workflow with least privilege: data and training with a train token (the CLI's
/// RELREWARD_TOKEN), serving with a read token (CLI --token, Rust client, OIP, the Python
/// planner example), model deletion with admin only.
#[tokio::test(flavor = "multi_thread")]
async fn tokens_through_the_cli_the_client_and_the_python_example() {
    let t = tokens();
    let mut server = TestServer::start_with_config(&t.config, &[]);
    server.set_access(Access {
        options: ConnectOptions { token: Some(t.train.clone()), tls: None },
        cli_env: vec![("RELREWARD_TOKEN".into(), t.train.clone())],
        ..Access::default()
    });
    let tmp = tempfile::tempdir().expect("tmp");
    let models = train_tiny_reward(&server, tmp.path());
    let input = tmp.path().join("traj.npz");
    let input = input.to_str().expect("utf8");

    // --token overrides RELREWARD_TOKEN.
    ok(&server, &["--token", &t.read, "score", "--model", &models.reward, "--input", input]);
    refused(&server, &["--token", "", "dataset", "list"], &["UNAUTHENTICATED", "--token"]);
    refused(&server, &["--token", &t.read, "dataset", "delete", "traj"], &["PERMISSION_DENIED", "'train'"]);
    refused(&server, &["model", "delete", &models.reward], &["PERMISSION_DENIED", "'admin'"]);

    // Rust client with the read token: a gradient stream on the real model, and OIP.
    let reader = connect(&server, Some(&t.read)).await;
    let stream = reader.gradient_stream().await.expect("open stream");
    let x = tensor::encode_f32(&[2, models.horizon as u64, models.transition_dim as u64], &vec![0.1; 2 * 8 * 4]);
    let req = pb::GradientRequest {
        request_id: 7,
        model: models.reward.clone(),
        x: Some(x),
        t: vec![3],
        ..Default::default()
    };
    stream.send(req).await.expect("send");
    let mut stream = stream;
    let resp = stream.message().await.expect("answer").expect("one response");
    assert_eq!(resp.request_id, 7);
    assert!(resp.error.is_none() && resp.gradient.is_some(), "{resp:?}");
    let mut oip = GrpcInferenceServiceClient::new(reader.transport());
    let ready = oip
        .model_ready(oip::ModelReadyRequest { name: models.reward.clone(), version: String::new() })
        .await
        .expect("model ready");
    assert!(ready.into_inner().ready);

    // The Python planner example: with the read token it runs, without one it is refused.
    let example = |token: Option<&str>| {
        let mut cmd = Command::new(python());
        cmd.arg(repo_root().join("examples/planner_gradient_stream.py"))
            .args(["--endpoint", &server.addr.to_string(), "--model", &models.reward, "--n-guide-steps", "1"])
            .env_remove("RELREWARD_TOKEN");
        if let Some(token) = token {
            cmd.env("RELREWARD_TOKEN", token);
        }
        cmd.output().expect("python")
    };
    let out = example(Some(&t.read));
    assert!(out.status.success(), "{}", stderr(&out));
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    assert_eq!(summary["requests"], models.n_timesteps);
    let out = example(None);
    assert!(!out.status.success() && stderr(&out).contains("UNAUTHENTICATED"), "{}", stderr(&out));

    // Deleting a model is admin's alone.
    ok(&server, &["--token", &t.admin, "model", "delete", &models.reward]);
    let err = reader.get_model(&models.reward).await.expect_err("deleted").to_string();
    assert!(err.contains("NOT_FOUND"), "{err}");
}

// ---------------------------------------------------------------------------------------------
// Safe defaults

/// Starts the server binary with `args` and `env`; returns its first stdout line (None when
/// it exited first), its exit status if it exited, and its log.
fn start_raw(args: &[&str], env: &[(&str, &str)]) -> (Option<String>, Option<i32>, String) {
    let tmp = tempfile::tempdir().expect("tmp");
    let log_path = tmp.path().join("server.log");
    let log = std::fs::File::create(&log_path).expect("log");
    let mut child = Command::new(bin("relreward-server"))
        .args(["--data-dir", tmp.path().join("data").to_str().expect("utf8")])
        .args(args)
        .env("RELREWARD__METRICS__LISTEN", "")
        .env("RELREWARD__ENGINE__INTRA_OP_THREADS", "1")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .expect("spawn");
    let stdout = child.stdout.take().expect("stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        let line = std::io::BufReader::new(stdout).lines().next().and_then(Result::ok);
        let _ = tx.send(line);
    });
    let line = rx.recv_timeout(Duration::from_secs(60)).ok().flatten();
    let status = if line.is_some() {
        // Running: wait for the start-up report (warnings come just before it), then stop.
        for _ in 0..200 {
            if std::fs::read_to_string(&log_path).is_ok_and(|l| l.contains("access control")) {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = child.kill();
        let _ = child.wait();
        None
    } else {
        child.wait().expect("wait").code()
    };
    let text = std::fs::read_to_string(&log_path).unwrap_or_default();
    assert!(!tmp.path().join("data").exists() || line.is_some(), "a refused start must not create the data directory");
    (line, status, text)
}

#[test]
fn all_interfaces_need_tokens_or_an_explicit_opt_out() {
    let (line, status, log) = start_raw(&["--listen", "0.0.0.0:0"], &[]);
    assert_eq!((line, status), (None, Some(2)), "{log}");
    assert!(log.contains("server.listen") && log.contains("security.allow_unauthenticated = true"), "{log}");

    let (line, _, log) =
        start_raw(&["--listen", "0.0.0.0:0"], &[("RELREWARD__SECURITY__ALLOW_UNAUTHENTICATED", "true")]);
    assert!(line.is_some_and(|l| l.starts_with("relreward-server listening on 0.0.0.0:")), "{log}");
    assert!(log.contains("WARN") && log.contains("without authentication"), "{log}");

    let tmp = tempfile::tempdir().expect("tmp");
    let config = tmp.path().join("config.toml");
    std::fs::write(&config, tokens().config).expect("config");
    let config = config.to_str().expect("utf8");
    let (line, _, log) = start_raw(&["--listen", "[::]:0", "--config", config], &[]);
    assert!(line.is_some_and(|l| l.contains("listening on [::]:")), "{log}");
    assert!(log.contains("plaintext"), "tokens over plaintext on a public address deserve a warning: {log}");

    // The OIP's HTTP listener follows the same rule, named by its own key.
    let (line, status, log) = start_raw(&["--listen", "127.0.0.1:0"], &[("RELREWARD__OIP_HTTP__LISTEN", "0.0.0.0:0")]);
    assert_eq!((line, status), (None, Some(2)), "{log}");
    assert!(log.contains("oip_http.listen") && log.contains("security.allow_unauthenticated = true"), "{log}");

    // A token pasted where its hash belongs stops the start, naming the entry.
    std::fs::write(
        tmp.path().join("bad.toml"),
        "[security]\ntokens = [{ name = \"x\", hash = \"rrt_abc\", scopes = [\"read\"] }]\n",
    )
    .expect("config");
    let bad = tmp.path().join("bad.toml");
    let (line, status, log) = start_raw(&["--listen", "127.0.0.1:0", "--config", bad.to_str().expect("utf8")], &[]);
    assert_eq!((line, status), (None, Some(2)), "{log}");
    assert!(log.contains("security.tokens[0].hash") && log.contains("looks like a token"), "{log}");
}

#[test]
fn token_create_refuses_bad_input() {
    for args in
        [&["--scopes", "write"][..], &["--scopes", "read", "--name", "a b"], &["--scopes", "read", "--expires", "soon"]]
    {
        let out = Command::new(bin("relreward-server")).args(["token", "create"]).args(args).output().expect("run");
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", stdout(&out));
        assert!(stdout(&out).is_empty(), "no token printed for {args:?}");
    }
    // Two tokens never repeat.
    assert_ne!(token_create(&["--scopes", "read"]).token, token_create(&["--scopes", "read"]).token);
}

// ---------------------------------------------------------------------------------------------
// TLS

/// A CA, and certificates it signed: the server's (for `localhost` and 127.0.0.1) and a
/// client's. `rogue_*` come from another CA.
struct Pki {
    dir: tempfile::TempDir,
}

impl Pki {
    fn new() -> Self {
        use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair};
        let dir = tempfile::tempdir().expect("tmp");
        let write = |name: &str, text: String| std::fs::write(dir.path().join(name), text).expect("write pem");
        let ca = |name: &str| {
            let key = KeyPair::generate().expect("key");
            let mut params = CertificateParams::new(Vec::<String>::new()).expect("params");
            params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
            params.distinguished_name.push(rcgen::DnType::CommonName, name);
            let cert = params.self_signed(&key).expect("ca");
            (Issuer::new(params, key), cert)
        };
        let leaf = |issuer: &Issuer<'_, KeyPair>, names: Vec<String>, prefix: &str| {
            let key = KeyPair::generate().expect("key");
            let cert = CertificateParams::new(names).expect("params").signed_by(&key, issuer).expect("sign");
            write(&format!("{prefix}.pem"), cert.pem());
            write(&format!("{prefix}.key"), key.serialize_pem());
        };
        let (issuer, ca_cert) = ca("relreward test CA");
        write("ca.pem", ca_cert.pem());
        leaf(&issuer, vec!["localhost".into(), "127.0.0.1".into()], "server");
        leaf(&issuer, vec!["planner.example".into()], "client");
        let (rogue, rogue_cert) = ca("rogue CA");
        write("rogue-ca.pem", rogue_cert.pem());
        leaf(&rogue, vec!["localhost".into(), "127.0.0.1".into()], "rogue-server");
        leaf(&rogue, vec!["planner.example".into()], "rogue-client");
        Self { dir }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn s(&self, name: &str) -> String {
        self.path(name).to_str().expect("utf8").to_owned()
    }

    fn tls_section(&self, mutual: bool) -> String {
        let ca = if mutual { format!("client_ca = \"{}\"\n", self.s("ca.pem")) } else { String::new() };
        format!("[security.tls]\ncert = \"{}\"\nkey = \"{}\"\n{ca}", self.s("server.pem"), self.s("server.key"))
    }

    fn tls(&self, ca: &str, client: Option<&str>) -> TlsOptions {
        let (cert, key) = client.map(|c| (self.path(&format!("{c}.pem")), self.path(&format!("{c}.key")))).unzip();
        let identity = cert.as_deref().zip(key.as_deref());
        TlsOptions::from_files(Some(&self.path(ca)), identity.map(|(c, k)| (c as &Path, k as &Path)), None)
            .expect("tls files")
    }
}

/// Health of the server through a client built with `options` on `endpoint`: Ok, or the
/// failure (at connect or at the call) as text.
async fn try_health(endpoint: &str, options: &ConnectOptions) -> Result<(), String> {
    let client = Client::connect_with(endpoint, options).await.map_err(|e| e.to_string())?;
    client.health().await.map(|_| ()).map_err(|e| e.to_string())
}

#[tokio::test(flavor = "multi_thread")]
async fn tls_serves_tokens_and_oip_and_refuses_plaintext_and_unknown_cas() {
    let pki = Pki::new();
    let t = tokens();
    let server = TestServer::start_with_config(
        &format!("{}\n{}", t.config, pki.tls_section(false)),
        &[("RELREWARD__OIP_HTTP__LISTEN", "127.0.0.1:0")],
    );
    let https = format!("https://{}", server.addr);
    let http = format!("http://{}", server.addr);
    let tls = |ca: &str| Some(pki.tls(ca, None));
    let with = |token: Option<&str>, tls: Option<TlsOptions>| ConnectOptions { token: token.map(str::to_owned), tls };

    // TLS with the right CA: health without a token, the API with one, OIP on the same port.
    try_health(&https, &with(None, tls("ca.pem"))).await.expect("health over TLS");
    let reader = Client::connect_with(&https, &with(Some(&t.read), tls("ca.pem"))).await.expect("connect");
    reader.list_datasets().await.expect("list over TLS with a token");
    let mut inference = GrpcInferenceServiceClient::new(reader.transport());
    assert!(inference.server_live(oip::ServerLiveRequest {}).await.expect("OIP over TLS").into_inner().live);
    let anonymous = Client::connect_with(&https, &with(None, tls("ca.pem"))).await.expect("connect");
    assert_eq!(code(anonymous.list_datasets().await), Code::Unauthenticated);

    // Plaintext to a TLS listener, a server certificate from an unknown CA, the system's
    // roots (which do not know the test CA): all fail.
    let err = try_health(&http, &with(None, None)).await.expect_err("plaintext must fail");
    assert!(!err.is_empty());
    let err = try_health(&https, &with(None, tls("rogue-ca.pem"))).await.expect_err("unknown CA");
    assert!(err.contains("certificate") || err.contains("Certificate") || err.contains("UnknownIssuer"), "{err}");
    try_health(&https, &with(None, None)).await.expect_err("system roots do not know the test CA");
    // TLS settings with an http:// endpoint are refused rather than silently unused.
    let err = try_health(&http, &with(None, tls("ca.pem"))).await.expect_err("http with a CA");
    assert!(err.contains("https://"), "{err}");
    // The certificate names localhost and 127.0.0.1; another expected name fails.
    let named = |name: &str| TlsOptions { server_name: Some(name.into()), ..pki.tls("ca.pem", None) };
    try_health(&https, &with(None, Some(named("localhost")))).await.expect("the certificate's DNS name");
    let err = try_health(&https, &with(None, Some(named("elsewhere.example")))).await.expect_err("another name");
    assert!(err.contains("not valid for name"), "{err}");

    // The Python example over TLS: with the CA and a token it reaches the handler (which
    // knows no such model); without the token it is refused.
    let example = |token: &[&str]| {
        let out = Command::new(python())
            .arg(repo_root().join("examples/planner_gradient_stream.py"))
            .args(["--endpoint", &server.addr.to_string(), "--model", MISSING, "--ca-cert", &pki.s("ca.pem")])
            .args(token)
            .env_remove("RELREWARD_TOKEN")
            .output()
            .expect("python");
        assert!(!out.status.success());
        stderr(&out)
    };
    let err = example(&["--token", &t.read]);
    assert!(err.contains("NOT_FOUND"), "{err}");
    let err = example(&[]);
    assert!(err.contains("UNAUTHENTICATED"), "{err}");

    // The CLI: https endpoint, --ca-cert and --token (or their environment variables).
    let cli = |args: &[&str], env: &[(&str, &str)]| {
        Command::new(bin("relreward"))
            .args(["--endpoint", &https])
            .args(args)
            .env_remove("RELREWARD_TOKEN")
            .envs(env.iter().copied())
            .output()
            .expect("cli")
    };
    let out = cli(&["--ca-cert", &pki.s("ca.pem"), "--token", &t.read, "--json", "dataset", "list"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let out =
        cli(&["--json", "dataset", "list"], &[("RELREWARD_CA_CERT", &pki.s("ca.pem")), ("RELREWARD_TOKEN", &t.read)]);
    assert!(out.status.success(), "{}", stderr(&out));
    let out = cli(&["--ca-cert", &pki.s("ca.pem"), "dataset", "list"], &[]);
    assert!(!out.status.success() && stderr(&out).contains("UNAUTHENTICATED"), "{}", stderr(&out));
    let out = cli(&["--ca-cert", &pki.s("rogue-ca.pem"), "--token", &t.read, "dataset", "list"], &[]);
    assert!(!out.status.success(), "a rogue CA must not verify the server");

    // The OIP over HTTP: the same TLS and tokens (KServe v2 REST through curl).
    let url = server.oip_http_url();
    assert!(url.starts_with("https://"), "{url}");
    let plain = url.replacen("https://", "http://", 1);
    let stats = "/v2/models/stats";
    assert_eq!(
        curl(&url, stats, &["--cacert", &pki.s("ca.pem"), "-H", &format!("Authorization: Bearer {}", t.read)]).0,
        200
    );
    let (status, body) = curl(&url, stats, &["--cacert", &pki.s("ca.pem")]);
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("authorization: missing"), "{body}");
    let (status, body) = curl(&url, stats, &["--cacert", &pki.s("ca.pem"), "-H", "Authorization: Bearer nope"]);
    assert_eq!(status, 401, "{body}");
    assert_eq!(curl(&url, stats, &["--cacert", &pki.s("rogue-ca.pem")]).0, 0, "a rogue CA must not verify the server");
    assert_eq!(curl(&plain, stats, &[]).0, 0, "plaintext to the TLS listener");
}

/// `curl` against `base` + `path` with `args`: the HTTP status (0 when no response came, e.g.
/// a failed handshake) and the body.
fn curl(base: &str, path: &str, args: &[&str]) -> (u16, String) {
    let out = Command::new("curl")
        .args(["-sS", "--max-time", "20", "-o", "-", "-w", "\n%{http_code}"])
        .args(args)
        .arg(format!("{base}{path}"))
        .output()
        .expect("curl");
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let (body, code) = text.rsplit_once('\n').unwrap_or(("", &text));
    (code.trim().parse().unwrap_or(0), body.to_owned())
}

#[tokio::test(flavor = "multi_thread")]
async fn mutual_tls_needs_a_client_certificate_from_the_ca() {
    let pki = Pki::new();
    let server =
        TestServer::start_with_config(&pki.tls_section(true), &[("RELREWARD__OIP_HTTP__LISTEN", "127.0.0.1:0")]);
    let https = format!("https://{}", server.addr);
    let with = |client: Option<&str>| ConnectOptions { token: None, tls: Some(pki.tls("ca.pem", client)) };

    try_health(&https, &with(Some("client"))).await.expect("a client certificate from the CA");
    let client = Client::connect_with(&https, &with(Some("client"))).await.expect("connect");
    client.list_datasets().await.expect("the API over mutual TLS");
    try_health(&https, &with(None)).await.expect_err("no client certificate");
    try_health(&https, &with(Some("rogue-client"))).await.expect_err("a client certificate from another CA");

    let cli = |args: &[&str]| {
        Command::new(bin("relreward"))
            .args(["--endpoint", &https, "--ca-cert", &pki.s("ca.pem")])
            .args(args)
            .output()
            .expect("cli")
    };
    let out = cli(&["--client-cert", &pki.s("client.pem"), "--client-key", &pki.s("client.key"), "health"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(!cli(&["health"]).status.success(), "no client certificate");
    let out = cli(&["--client-cert", &pki.s("client.pem"), "health"]);
    assert_eq!(out.status.code(), Some(2), "--client-cert without --client-key is a usage error: {}", stderr(&out));

    // The OIP over HTTP asks for the same client certificate.
    let url = server.oip_http_url();
    let ca = ["--cacert", &pki.s("ca.pem")];
    let (status, body) = curl(
        &url,
        "/v2/health/live",
        &[&ca[..], &["--cert", &pki.s("client.pem"), "--key", &pki.s("client.key")]].concat(),
    );
    assert_eq!(status, 200, "{body}");
    assert_eq!(curl(&url, "/v2/health/live", &ca).0, 0, "no client certificate");
    let rogue = ["--cert", &pki.s("rogue-client.pem"), "--key", &pki.s("rogue-client.key")];
    assert_eq!(curl(&url, "/v2/health/live", &[&ca[..], &rogue[..]].concat()).0, 0, "a certificate from another CA");
}

/// `engine.device` (issue 21): a CUDA device that libtorch does not see stops the start before
/// anything is bound or created, naming the key; `cpu` and `auto` start (auto is the CPU here
/// unless this machine has a GPU and a CUDA libtorch); a value that is no device is refused.
#[test]
fn an_absent_device_stops_the_start_and_cpu_or_auto_start() {
    for (device, needle) in [
        ("cuda:99", "engine.device: 'cuda:99' is not available"),
        ("gpu", "engine.device: 'gpu' is not one of cpu, cuda, cuda:N"),
    ] {
        let (line, status, log) = start_raw(&["--listen", "127.0.0.1:0"], &[("RELREWARD__ENGINE__DEVICE", device)]);
        assert_eq!((line, status), (None, Some(2)), "{device}: {log}");
        assert!(log.contains(needle), "{device}: {log}");
    }
    if !tch_sees_a_gpu() {
        let (line, status, log) = start_raw(&["--listen", "127.0.0.1:0"], &[("RELREWARD__ENGINE__DEVICE", "cuda")]);
        assert_eq!((line, status), (None, Some(2)), "{log}");
        assert!(log.contains("engine.device: 'cuda' is not available: libtorch sees 0 CUDA device(s)"), "{log}");
    }
    for device in ["cpu", "auto"] {
        let (line, _, log) = start_raw(&["--listen", "127.0.0.1:0"], &[("RELREWARD__ENGINE__DEVICE", device)]);
        assert!(line.is_some_and(|l| l.contains("listening on")), "{device}: {log}");
    }
}

/// Whether this machine has a GPU at all (nvidia-smi lists one); the refusal of `cuda` is only
/// certain without one.
fn tch_sees_a_gpu() -> bool {
    Command::new("nvidia-smi").arg("-L").output().is_ok_and(|o| o.status.success() && !o.stdout.is_empty())
}

#[test]
fn bad_tls_files_stop_the_start() {
    let pki = Pki::new();
    // A key that is not the certificate's.
    let tmp = tempfile::tempdir().expect("tmp");
    let config = tmp.path().join("c.toml");
    let text = format!("[security.tls]\ncert = \"{}\"\nkey = \"{}\"\n", pki.s("server.pem"), pki.s("client.key"));
    std::fs::write(&config, text).expect("write");
    let (line, status, log) = start_raw(&["--listen", "127.0.0.1:0", "--config", config.to_str().expect("utf8")], &[]);
    assert_eq!((line, status), (None, Some(2)), "{log}");
    assert!(log.contains("security.tls"), "{log}");
    // A file that is not there.
    let (line, status, log) = start_raw(
        &["--listen", "127.0.0.1:0"],
        &[
            ("RELREWARD__SECURITY__TLS__CERT", "/nonexistent.pem"),
            ("RELREWARD__SECURITY__TLS__KEY", &pki.s("server.key")),
        ],
    );
    assert_eq!((line, status), (None, Some(2)), "{log}");
    assert!(log.contains("security.tls.cert") && log.contains("/nonexistent.pem"), "{log}");
}

// ---------------------------------------------------------------------------------------------
// Path traversal

/// Every name that would create or address a stored resource is checked against the naming
/// rule (INVALID_ARGUMENT); references inside a job spec are looked up in the metadata store
/// (NOT_FOUND), whose records point at server-generated blob keys. Either way nothing is
/// created outside the data directory and nothing stays in staging.
#[tokio::test(flavor = "multi_thread")]
async fn names_never_become_paths() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = server.client().await;
    // So that a job spec fails on the name under test alone.
    upload(&client, "fine").await.expect("upload");
    let evil =
        ["../escape", "..", ".", "a/../../escape", "/tmp/escape", "a\\..\\escape", "%2e%2e%2fescape", "escape\0"];
    let invalid = |what: &str, name: &str, result: Code| {
        assert_eq!(result, Code::InvalidArgument, "{what} with name {name:?}");
    };
    for name in evil {
        invalid("upload dataset", name, code(upload(&client, name).await));
        invalid("get dataset", name, code(client.get_dataset(name).await));
        invalid("delete dataset", name, code(client.delete_dataset(name).await));
        invalid("get model", name, code(client.get_model(name).await));
        invalid("delete model", name, code(client.delete_model(name).await));
        invalid("get job", name, code(client.get_job(name).await));
        invalid("cancel job", name, code(client.cancel_job(name).await));
        let header = pb::UploadModelHeader { name: name.into(), ..Default::default() };
        let msg = pb::UploadModelRequest { message: Some(pb::upload_model_request::Message::Header(header)) };
        invalid("upload model", name, status_code(client.models().upload_model(tokio_stream::iter([msg])).await));
        let spec = |output: &str, dataset: &str| pb::JobSpec {
            output_model: output.into(),
            kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
                dataset: dataset.into(),
                ..Default::default()
            })),
            ..Default::default()
        };
        invalid("job id", name, code(client.submit_job(spec("fine", "fine"), Some(name)).await));
        invalid("job output model", name, code(client.submit_job(spec(name, "fine"), None).await));
        let reference = code(client.submit_job(spec("fine", name), None).await);
        assert!(matches!(reference, Code::InvalidArgument | Code::NotFound), "job dataset {name:?}: {reference:?}");
    }
    // Array names are a fixed vocabulary, never file names of the client's choosing.
    let mut source = MemorySource::new();
    source.push_f32("../../escape", &[4, 2], &[0.0; 8]);
    let spec = DatasetUpload {
        name: "ok-name".into(),
        kind: pb::DatasetKind::Samples,
        description: String::new(),
        chunk_bytes: 1 << 20,
    };
    let err = client.upload_dataset(spec, source, Arc::new(UploadProgress::default())).await.expect_err("refused");
    assert!(err.to_string().contains("INVALID_ARGUMENT") && err.to_string().contains("header.arrays[0]"), "{err}");

    assert!(!Path::new("/tmp/escape").exists(), "an absolute name was used as a path");
    let tmp_root = server.data_dir.parent().expect("temp dir").to_owned();
    let mut stack = vec![tmp_root.clone()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("read dir") {
            let path = entry.expect("entry").path();
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            assert!(!name.contains("escape") && !name.contains("ok-name"), "created {}", path.display());
            if path.is_dir() {
                stack.push(path);
            }
        }
    }
    assert!(!tmp_root.parent().expect("parent").join("escape").exists());
    assert_eq!(server.staging_entries(), 0, "a refused upload left files in staging");
    // The server still answers normally, and no job was queued.
    upload(&client, "after").await.expect("a valid upload after all the refused ones");
    assert!(client.list_jobs(pb::JobState::Unspecified).await.expect("jobs").is_empty());
}

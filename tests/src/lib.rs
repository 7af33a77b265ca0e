//! Harness for end-to-end tests: starts the real `relreward-server` binary on an ephemeral
//! loopback port with a temporary data directory, and reaches it through the real client
//! library and the real `relreward` CLI.
//!
//! Binaries are taken from the same target directory as the test executable (`make test`
//! builds them first; `cargo build --release --bins` does too).

pub mod dataset_upload;
pub mod model_upload;

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use relreward_client::client::{ConnectOptions, DatasetUpload, UploadProgress};
use relreward_client::{Client, MemorySource, pb};
use serde_json::Value;

/// Path of a workspace binary next to the running test executable.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe.parent().and_then(Path::parent).expect("target dir");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} not found: build the binaries first (make test, or cargo build --release --bins)",
        path.display()
    );
    path
}

/// Repository root (for scripts under tests/python and the project's .venv).
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("repo root").to_path_buf()
}

/// The project's Python (with numpy and torch), created by `make setup`.
pub fn python() -> PathBuf {
    let p = repo_root().join(".venv/bin/python");
    assert!(p.exists(), "{} not found: run `make setup` (make test does it)", p.display());
    p
}

pub struct TestServer {
    child: Option<Child>,
    pub addr: SocketAddr,
    pub data_dir: PathBuf,
    log: PathBuf,
    env: Vec<(String, String)>,
    /// Extra server arguments (`--config FILE`), kept for `restart`.
    args: Vec<String>,
    /// How `client()` and `cli()` reach the server: scheme, token, TLS (see `set_access`).
    access: Access,
    /// The metrics address the server printed on its second stdout line, once it has.
    metrics_addr: Arc<OnceLock<SocketAddr>>,
    /// The OIP HTTP listener's base URL (`http[s]://ADDR`) the server printed, once it has.
    oip_http_url: Arc<OnceLock<String>>,
    _tmp: Option<tempfile::TempDir>,
}

impl TestServer {
    /// A server on a fresh temporary data directory.
    pub fn start() -> Self {
        Self::start_with_env(&[])
    }

    /// A server on a fresh temporary data directory with extra `RELREWARD__*` variables.
    pub fn start_with_env(env: &[(&str, &str)]) -> Self {
        let tmp = tempfile::tempdir().expect("tempdir");
        let data_dir = tmp.path().join("data");
        let env = env.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())).collect();
        let mut s = Self::spawn(data_dir, tmp.path().join("server.log"), env);
        s._tmp = Some(tmp);
        s
    }

    /// A server on a fresh temporary data directory with `config` (TOML text, written to a
    /// file passed as `--config`) and extra `RELREWARD__*` variables.
    pub fn start_with_config(config: &str, env: &[(&str, &str)]) -> Self {
        let tmp = tempfile::tempdir().expect("tempdir");
        let path = tmp.path().join("config.toml");
        std::fs::write(&path, config).expect("config file");
        let env = env.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())).collect();
        let args = vec!["--config".to_owned(), path.to_str().expect("utf8 path").to_owned()];
        let mut s = Self::spawn_with(tmp.path().join("data"), tmp.path().join("server.log"), env, args);
        s._tmp = Some(tmp);
        s
    }

    /// How [`TestServer::client`] and [`TestServer::cli`] reach this server from now on.
    pub fn set_access(&mut self, access: Access) {
        self.access = access;
    }

    fn spawn(data_dir: PathBuf, log: PathBuf, env: Vec<(String, String)>) -> Self {
        Self::spawn_with(data_dir, log, env, Vec::new())
    }

    fn spawn_with(data_dir: PathBuf, log: PathBuf, env: Vec<(String, String)>, args: Vec<String>) -> Self {
        let log_file = std::fs::OpenOptions::new().create(true).append(true).open(&log).expect("log file");
        let mut cmd = Command::new(bin("relreward-server"));
        cmd.args(&args)
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--data-dir")
            .arg(&data_dir)
            .env("RELREWARD__ENGINE__INTRA_OP_THREADS", "1")
            // Many servers run at once: no fixed metrics port (a test that wants one sets it).
            .env("RELREWARD__METRICS__LISTEN", "")
            // No health drain on SIGTERM (tests of the drain set their own, through `env`).
            .env("RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS", "0")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log_file);
        for (k, v) in &env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("spawn relreward-server");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        let metrics_addr = Arc::new(OnceLock::new());
        let metrics_line = Arc::clone(&metrics_addr);
        let oip_http_url = Arc::new(OnceLock::new());
        let oip_http_line = Arc::clone(&oip_http_url);
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            if let Some(Ok(line)) = lines.next() {
                let _ = tx.send(line);
            }
            // The next lines, when the metrics endpoint (see `metrics_addr`) or the OIP's HTTP
            // listener (`oip_http_addr`) is on; then keep draining so the server never blocks
            // on a full pipe.
            for line in lines.map_while(Result::ok) {
                if let Some(addr) = line
                    .strip_prefix("relreward-server metrics on http://")
                    .and_then(|a| a.strip_suffix("/metrics"))
                    .and_then(|a| a.parse().ok())
                {
                    let _ = metrics_line.set(addr);
                }
                if let Some(url) = line.strip_prefix("relreward-server oip_http on ") {
                    let _ = oip_http_line.set(url.to_owned());
                }
            }
        });
        let line = rx.recv_timeout(Duration::from_secs(60)).unwrap_or_else(|_| {
            let _ = child.kill();
            panic!("server did not report its address; log:\n{}", std::fs::read_to_string(&log).unwrap_or_default())
        });
        let addr = line
            .strip_prefix("relreward-server listening on ")
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("unexpected first line: {line}"));
        let access = Access::default();
        Self { child: Some(child), addr, data_dir, log, env, args, access, metrics_addr, oip_http_url, _tmp: None }
    }

    /// Address of the Prometheus endpoint, for a server started with
    /// `RELREWARD__METRICS__LISTEN` set (e.g. `127.0.0.1:0`); waits for the line announcing it.
    pub fn metrics_addr(&self) -> SocketAddr {
        for _ in 0..1200 {
            if let Some(addr) = self.metrics_addr.get() {
                return *addr;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("server did not report a metrics address (is metrics.listen set?); log:\n{}", self.log())
    }

    /// Base URL (`http://ADDR` or `https://ADDR`) of the OIP's HTTP listener, for a server
    /// started with `RELREWARD__OIP_HTTP__LISTEN` set; waits for the line announcing it.
    pub fn oip_http_url(&self) -> String {
        for _ in 0..1200 {
            if let Some(url) = self.oip_http_url.get() {
                return url.clone();
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("server did not report an oip_http address (is oip_http.listen set?); log:\n{}", self.log())
    }

    pub fn endpoint(&self) -> String {
        format!("{}://{}", if self.access.https { "https" } else { "http" }, self.addr)
    }

    pub async fn client(&self) -> Client {
        // The address is reported once bound; retry briefly while the store opens.
        for _ in 0..100 {
            if let Ok(c) = Client::connect_with(&self.endpoint(), &self.access.options).await {
                return c;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!("cannot connect to {}; log:\n{}", self.endpoint(), self.log())
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// SIGKILL: the crash case, nothing gets to clean up.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM and wait: the graceful case. Returns whether the exit status was success.
    pub fn terminate(&mut self) -> bool {
        let Some(mut c) = self.child.take() else { return false };
        let _ = Command::new("kill").arg("-TERM").arg(c.id().to_string()).status();
        for _ in 0..300 {
            if let Ok(Some(status)) = c.try_wait() {
                return status.success();
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = c.kill();
        let _ = c.wait();
        false
    }

    /// Starts a new server process on the same data directory (after `kill` or `terminate`).
    pub fn restart(&mut self) {
        self.kill();
        let tmp = self._tmp.take();
        let mut next = Self::spawn_with(self.data_dir.clone(), self.log.clone(), self.env.clone(), self.args.clone());
        next._tmp = tmp;
        next.access = std::mem::take(&mut self.access);
        *self = next;
    }

    /// Files in the staging area (unfinished uploads).
    pub fn staging_entries(&self) -> usize {
        std::fs::read_dir(self.data_dir.join("staging")).map(|d| d.count()).unwrap_or(0)
    }

    /// Runs the `relreward` CLI against this server.
    pub fn cli(&self, args: &[&str]) -> Output {
        Command::new(bin("relreward"))
            .arg("--endpoint")
            .arg(self.endpoint())
            .args(args)
            .envs(self.access.cli_env.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .output()
            .expect("run relreward")
    }
}

/// How the harness reaches a server with access control or TLS: the endpoint scheme, the
/// client library's options and the CLI's environment (`RELREWARD_TOKEN`, `RELREWARD_CA_CERT`..).
#[derive(Debug, Clone, Default)]
pub struct Access {
    pub https: bool,
    pub options: ConnectOptions,
    pub cli_env: Vec<(String, String)>,
}

impl Drop for TestServer {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Waits until `f` holds, for at most `secs` seconds.
pub async fn eventually(secs: u64, mut f: impl FnMut() -> bool) -> bool {
    for _ in 0..secs * 20 {
        if f() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    f()
}

/// A process's stdout, lossily decoded.
pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A process's stderr, lossily decoded.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Runs the CLI, asserting success; returns stdout.
#[track_caller]
pub fn ok(server: &TestServer, args: &[&str]) -> String {
    let out = server.cli(args);
    assert!(
        out.status.success(),
        "relreward {args:?} failed ({}):\n{}\n{}\nserver log:\n{}",
        out.status,
        stdout(&out),
        stderr(&out),
        server.log()
    );
    stdout(&out)
}

/// Runs the CLI with `--json`, asserting success; returns the document.
#[track_caller]
pub fn ok_json(server: &TestServer, args: &[&str]) -> Value {
    let mut all = vec!["--json"];
    all.extend(args);
    let text = ok(server, &all);
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("relreward {args:?}: not JSON ({e}):\n{text}"))
}

/// Runs the CLI, asserting a non-zero exit and that stderr names every one of `needles`.
#[track_caller]
pub fn refused(server: &TestServer, args: &[&str], needles: &[&str]) {
    let out = server.cli(args);
    let err = stderr(&out);
    assert!(!out.status.success(), "relreward {args:?} succeeded:\n{}", stdout(&out));
    for needle in needles {
        assert!(err.contains(needle), "relreward {args:?}: stderr does not name {needle:?}:\n{err}");
    }
}

/// Runs `script` with the project's Python (`python -c script args..`), asserting success;
/// returns stdout.
#[track_caller]
pub fn run_python(script: &str, args: &[&str]) -> String {
    let out = Command::new(python()).arg("-c").arg(script).args(args).output().expect("python");
    assert!(out.status.success(), "python failed:\n{}", stderr(&out));
    stdout(&out)
}

/// Prints `{key: {"shape": [..], "dtype": "..", "values": [..]}}` for every array of an .npz.
const READ_NPZ: &str = r#"
import json, sys
import numpy as np
with np.load(sys.argv[1]) as d:
    print(json.dumps({k: {"shape": list(d[k].shape), "dtype": str(d[k].dtype),
                          "values": d[k].ravel().astype(float).tolist()} for k in d.files}))
"#;

/// numpy's view of an .npz file: `{key: {"shape", "dtype", "values"}}` (see [`npz_shape`],
/// [`npz_values`]).
pub fn np_load(path: &Path) -> Value {
    let text = run_python(READ_NPZ, &[path.to_str().expect("utf8")]);
    serde_json::from_str(&text).expect("json from python")
}

/// The shape of array `key` in an [`np_load`] document.
#[track_caller]
pub fn npz_shape(npz: &Value, key: &str) -> Vec<u64> {
    let shape = &npz[key]["shape"];
    assert!(shape.is_array(), "no array '{key}' in {npz}");
    shape.as_array().expect("shape").iter().map(|v| v.as_u64().expect("dim")).collect()
}

/// The values of array `key` in an [`np_load`] document, flattened.
#[track_caller]
pub fn npz_values(npz: &Value, key: &str) -> Vec<f64> {
    npz[key]["values"]
        .as_array()
        .unwrap_or_else(|| panic!("no '{key}'"))
        .iter()
        .map(|v| v.as_f64().expect("f64"))
        .collect()
}

/// The diffusion training config of [`train_models`]: 12 steps of batch 8, horizon 8, T = 10,
/// a temporal U-Net of dim 8.
pub const TINY_DIFFUSION_CONFIG: &str = "[optimization]\nsteps = 12\nbatch_size = 8\nlog_every = 4\n\
     [diffusion]\nhorizon = 8\nn_timesteps = 10\n\
     architecture = { kind = \"temporal_unet\", dim = 8, dim_mults = [1, 2] }\n";

/// Trains through the CLI, waiting for each job (`--watch`): diffusion models `base` (seed 1,
/// on dataset `base_data`) and `expert` (seed 2, on `expert_data`) with
/// [`TINY_DIFFUSION_CONFIG`] (written to `dir/diffusion.toml`), then a windowed-MLP reward
/// `rw` between them (window 4, hidden 16,16, seed 3) on both datasets (once if they are the
/// same one), with `reward_args` added (`--steps` and `--batch-size` at least).
pub fn train_models(server: &TestServer, dir: &Path, base_data: &str, expert_data: &str, reward_args: &[&str]) {
    let config = dir.join("diffusion.toml");
    std::fs::write(&config, TINY_DIFFUSION_CONFIG).expect("config");
    let config = config.to_str().expect("utf8 path");
    for (name, data, seed) in [("base", base_data, "1"), ("expert", expert_data, "2")] {
        ok(
            server,
            &["train", "diffusion", "--name", name, "--dataset", data, "--config", config, "--seed", seed, "--watch"],
        );
    }
    let mut args = vec!["train", "reward", "--name", "rw", "--base", "base", "--expert", "expert"];
    args.extend(["--dataset", base_data]);
    if expert_data != base_data {
        args.extend(["--dataset", expert_data]);
    }
    args.extend(["--arch", "windowed_mlp", "--window", "4", "--hidden", "16,16", "--seed", "3", "--watch"]);
    args.extend(reward_args);
    ok(server, &args);
}

/// Straight-line trajectories for [`upload_lines`]: `episodes` of 24 steps, obs =
/// (x0 + vx k, y0 + vy k), action = (vx, vy), where x0, y0, vx, vy are each `u * scale + offset`
/// (`start` = [x0, y0], `velocity` = [vx, vy], as (scale, offset)) for u uniform in [0, 1)
/// drawn from an LCG seeded with `seed`.
#[derive(Debug, Clone, Copy)]
pub struct Lines {
    pub episodes: usize,
    pub seed: u64,
    pub start: [(f32, f32); 2],
    pub velocity: [(f32, f32); 2],
}

/// Uploads [`Lines`] trajectories (observations, actions, timeouts) as dataset `name`.
pub async fn upload_lines(client: &Client, name: &str, lines: &Lines) {
    try_upload_lines(client, name, lines).await.expect("upload lines");
}

/// As [`upload_lines`], returning the server's answer (for tests of refused uploads).
pub async fn try_upload_lines(
    client: &Client,
    name: &str,
    lines: &Lines,
) -> Result<pb::Dataset, relreward_client::ClientError> {
    let Lines { episodes, seed, start: [sx, sy], velocity: [svx, svy] } = *lines;
    let len = 24usize;
    let mut obs = Vec::with_capacity(episodes * len * 2);
    let mut act = Vec::with_capacity(episodes * len * 2);
    let mut timeouts = vec![false; episodes * len];
    let mut r = seed;
    let mut uniform = || {
        r = r.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (r >> 11) as f32 / (1u64 << 53) as f32
    };
    for e in 0..episodes {
        let (x0, y0) = (uniform() * sx.0 + sx.1, uniform() * sy.0 + sy.1);
        let (vx, vy) = (uniform() * svx.0 + svx.1, uniform() * svy.0 + svy.1);
        for k in 0..len {
            obs.extend([x0 + vx * k as f32, y0 + vy * k as f32]);
            act.extend([vx, vy]);
        }
        timeouts[e * len + len - 1] = true;
    }
    let n = (episodes * len) as u64;
    let mut source = MemorySource::new();
    source.push_f32("observations", &[n, 2], &obs).push_f32("actions", &[n, 2], &act).push_bool("timeouts", &timeouts);
    let upload = DatasetUpload {
        name: name.into(),
        kind: pb::DatasetKind::Trajectories,
        description: String::new(),
        chunk_bytes: 1 << 20,
    };
    client.upload_dataset(upload, source, Arc::new(UploadProgress::default())).await
}

/// What [`train_tiny_reward`] registered on a server.
#[derive(Debug, Clone)]
pub struct TinyModels {
    /// Trajectories dataset (D4RL keys), uploaded as `traj`.
    pub dataset: String,
    /// Diffusion models `base` and `expert`, horizon [`TinyModels::horizon`], T = 10.
    pub base: String,
    pub expert: String,
    /// Windowed-MLP reward `rw` (window 4, hidden 16,16).
    pub reward: String,
    pub horizon: usize,
    /// Transition dimension: action 2 + observation 2.
    pub transition_dim: usize,
    pub n_timesteps: usize,
}

/// Uploads a small trajectories dataset (5 episodes, rows `[action | observation]`, obs
/// following sin/cos curves) and trains a base and an expert diffusion model and a windowed
/// reward for a few steps each through the CLI: seconds, for tests that need a servable reward
/// rather than a good one. `dir` receives `traj.npz`.
pub fn train_tiny_reward(server: &TestServer, dir: &Path) -> TinyModels {
    let lengths = [30usize, 5, 40, 12, 25];
    let n: usize = lengths.iter().sum();
    let (mut obs, mut act) = (Vec::with_capacity(2 * n), Vec::with_capacity(2 * n));
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f32 / (1u64 << 53) as f32 - 0.5
    };
    for i in 0..n {
        let t = i as f32;
        obs.extend([(t / 7.0).sin() + 0.1 * noise(), (t / 5.0).cos() + 0.1 * noise()]);
        act.extend([2.0 * noise(), 2.0 * noise()]);
    }
    let (mut terminals, mut timeouts) = (vec![false; n], vec![false; n]);
    let mut end = 0;
    for (k, l) in lengths.iter().enumerate() {
        end += l;
        if k == 0 { terminals[end - 1] = true } else { timeouts[end - 1] = true }
    }
    let path = dir.join("traj.npz");
    let mut npz = relreward_toolkit::npz_write::NpzWriter::create(&path).expect("npz");
    npz.add_f32("observations", &[n as u64, 2], &obs).expect("obs");
    npz.add_f32("actions", &[n as u64, 2], &act).expect("act");
    npz.add_bool("terminals", &[n as u64], &terminals).expect("terminals");
    npz.add_bool("timeouts", &[n as u64], &timeouts).expect("timeouts");
    npz.finish().expect("write npz");
    ok(server, &["dataset", "upload", path.to_str().expect("utf8 path"), "--name", "traj"]);
    train_models(server, dir, "traj", "traj", &["--steps", "8", "--batch-size", "8"]);
    TinyModels {
        dataset: "traj".into(),
        base: "base".into(),
        expert: "expert".into(),
        reward: "rw".into(),
        horizon: 8,
        transition_dim: 4,
        n_timesteps: 10,
    }
}

/// Crash-test helpers: fault injection (`RELREWARD_FAULT`, see the server's `fault` module),
/// waiting for the injected abort, and digests of every stored file.
impl TestServer {
    /// Sets (`Some`) or removes (`None`) a server environment variable for the next
    /// [`TestServer::restart`] (e.g. disarming `RELREWARD_FAULT`).
    pub fn set_env(&mut self, key: &str, value: Option<&str>) {
        self.env.retain(|(k, _)| k != key);
        if let Some(v) = value {
            self.env.push((key.to_owned(), v.to_owned()));
        }
    }

    /// Waits up to `secs` for the server process to exit by itself (an injected fault aborts
    /// it); returns whether it did.
    pub fn wait_exit(&mut self, secs: u64) -> bool {
        let Some(child) = self.child.as_mut() else { return true };
        for _ in 0..secs * 20 {
            if let Ok(Some(_)) = child.try_wait() {
                self.child = None;
                return true;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        false
    }
}

/// Flips one bit of the byte at `offset` from the end of `path` (1: the last byte): silent
/// on-disk corruption for integrity tests.
pub fn flip_byte(path: &Path, offset_from_end: usize) {
    let mut bytes = std::fs::read(path).expect("read file to corrupt");
    let i = bytes.len() - offset_from_end;
    bytes[i] ^= 0x10;
    std::fs::write(path, bytes).expect("write corrupted file");
}

impl TestServer {
    /// The server's process id (for memory sampling), while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }
}

/// Resident memory of process `pid` in bytes (Linux `/proc/PID/status` VmRSS), if readable.
pub fn rss_bytes(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kb = status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().strip_suffix("kB")?.trim();
    kb.parse::<u64>().ok().map(|kb| kb * 1024)
}

/// The gRPC status of a failed client call, or None for errors that are not a status (a
/// connection that could not be made, a local file).
pub fn status_code(error: &relreward_client::ClientError) -> Option<tonic::Code> {
    match error {
        relreward_client::ClientError::Status(s) => Some(s.code()),
        _ => None,
    }
}

/// A tiny diffusion job on a trajectories dataset (TemporalUnet dim 8, dim_mults (1, 2),
/// horizon 8, T = 10): seconds on a CPU, with the caller's seed and optimization settings.
pub fn tiny_diffusion_spec(dataset: &str, output: &str, seed: u64, optimization: pb::Optimization) -> pb::JobSpec {
    pb::JobSpec {
        output_model: output.into(),
        seed: Some(seed),
        optimization: Some(optimization),
        kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
            dataset: dataset.into(),
            horizon: Some(8),
            n_timesteps: Some(10),
            architecture: Some(pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet {
                dim: Some(8),
                dim_mults: vec![1, 2],
            })),
            ..Default::default()
        })),
    }
}

/// Every event of job `id` from `from_seq` until its stream ends (the job reached a terminal
/// state); panics if an event takes more than 5 minutes.
pub async fn watch_all(client: &Client, id: &str, from_seq: u64) -> Vec<pb::JobEvent> {
    use tokio_stream::StreamExt;
    let mut stream = client.watch_job(id, from_seq).await.expect("watch");
    let mut out = Vec::new();
    while let Some(e) = tokio::time::timeout(Duration::from_secs(300), stream.next()).await.expect("event in time") {
        out.push(e.expect("event"));
    }
    out
}

/// Waits until job `id` writes a checkpoint at or past `step` (what a test kills the server
/// after) and returns that checkpoint's step; panics if the job's events end first or one takes
/// more than 5 minutes.
pub async fn wait_for_checkpoint(client: &Client, id: &str, step: u64) -> u64 {
    use tokio_stream::StreamExt;
    let mut stream = client.watch_job(id, 0).await.expect("watch");
    while let Some(e) = tokio::time::timeout(Duration::from_secs(300), stream.next()).await.expect("event in time") {
        if let Some(pb::job_event::Event::Checkpoint(c)) = e.expect("event").event
            && c.step >= step
        {
            return c.step;
        }
    }
    panic!("job {id} ended before a checkpoint at step {step} or later");
}

/// The last state change among `events`.
pub fn final_state(events: &[pb::JobEvent]) -> Option<pb::JobState> {
    events.iter().rev().find_map(|e| match &e.event {
        Some(pb::job_event::Event::State(s)) => Some(s.state()),
        _ => None,
    })
}

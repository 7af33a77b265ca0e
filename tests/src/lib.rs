//! Harness for end-to-end tests: starts the real `relreward-server` binary on an ephemeral
//! loopback port with a temporary data directory, and reaches it through the real client
//! library and the real `relreward` CLI.
//!
//! Binaries are taken from the same target directory as the test executable (`make test`
//! builds them first; `cargo build --release --bins` does too).

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use relreward_client::Client;

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
    /// The metrics address the server printed on its second stdout line, once it has.
    metrics_addr: Arc<OnceLock<SocketAddr>>,
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

    fn spawn(data_dir: PathBuf, log: PathBuf, env: Vec<(String, String)>) -> Self {
        let log_file = std::fs::OpenOptions::new().create(true).append(true).open(&log).expect("log file");
        let mut cmd = Command::new(bin("relreward-server"));
        cmd.arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--data-dir")
            .arg(&data_dir)
            .env("RELREWARD__ENGINE__INTRA_OP_THREADS", "1")
            // Many servers run at once: no fixed metrics port (a test that wants one sets it).
            .env("RELREWARD__METRICS__LISTEN", "")
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
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            if let Some(Ok(line)) = lines.next() {
                let _ = tx.send(line);
            }
            // The second line, when the metrics endpoint is on (see `metrics_addr`).
            if let Some(Ok(line)) = lines.next()
                && let Some(addr) = line
                    .strip_prefix("relreward-server metrics on http://")
                    .and_then(|a| a.strip_suffix("/metrics"))
                    .and_then(|a| a.parse().ok())
            {
                let _ = metrics_line.set(addr);
            }
            // Keep draining so the server never blocks on a full pipe.
            for _ in lines {}
        });
        let line = rx.recv_timeout(Duration::from_secs(60)).unwrap_or_else(|_| {
            let _ = child.kill();
            panic!("server did not report its address; log:\n{}", std::fs::read_to_string(&log).unwrap_or_default())
        });
        let addr = line
            .strip_prefix("relreward-server listening on ")
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("unexpected first line: {line}"));
        Self { child: Some(child), addr, data_dir, log, env, metrics_addr, _tmp: None }
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

    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub async fn client(&self) -> Client {
        // The address is reported once bound; retry briefly while the store opens.
        for _ in 0..100 {
            if let Ok(c) = Client::connect(&self.endpoint()).await {
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
        let mut next = Self::spawn(self.data_dir.clone(), self.log.clone(), self.env.clone());
        next._tmp = tmp;
        *self = next;
    }

    /// Files in the staging area (unfinished uploads).
    pub fn staging_entries(&self) -> usize {
        std::fs::read_dir(self.data_dir.join("staging")).map(|d| d.count()).unwrap_or(0)
    }

    /// Published blob directories of datasets.
    pub fn dataset_blobs(&self) -> usize {
        std::fs::read_dir(self.data_dir.join("blobs/datasets")).map(|d| d.count()).unwrap_or(0)
    }

    /// Runs the `relreward` CLI against this server.
    pub fn cli(&self, args: &[&str]) -> Output {
        Command::new(bin("relreward"))
            .arg("--endpoint")
            .arg(self.endpoint())
            .args(args)
            .stdin(Stdio::null())
            .output()
            .expect("run relreward")
    }
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
    let mut npz = relreward_client::npz_write::NpzWriter::create(&path).expect("npz");
    npz.add_f32("observations", &[n as u64, 2], &obs).expect("obs");
    npz.add_f32("actions", &[n as u64, 2], &act).expect("act");
    npz.add_bool("terminals", &[n as u64], &terminals).expect("terminals");
    npz.add_bool("timeouts", &[n as u64], &timeouts).expect("timeouts");
    npz.finish().expect("write npz");
    let config = dir.join("diffusion.toml");
    std::fs::write(
        &config,
        "[optimization]\nsteps = 12\nbatch_size = 8\nlog_every = 4\n[diffusion]\nhorizon = 8\nn_timesteps = 10\n\
         architecture = { kind = \"temporal_unet\", dim = 8, dim_mults = [1, 2] }\n",
    )
    .expect("config");
    let run = |args: &[&str]| {
        let out = server.cli(args);
        assert!(out.status.success(), "relreward {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let path = path.to_str().expect("utf8 path");
    let config = config.to_str().expect("utf8 path");
    run(&["dataset", "upload", path, "--name", "traj"]);
    for (name, seed) in [("base", "1"), ("expert", "2")] {
        run(&[
            "train",
            "diffusion",
            "--name",
            name,
            "--dataset",
            "traj",
            "--config",
            config,
            "--seed",
            seed,
            "--watch",
        ]);
    }
    run(&[
        "train",
        "reward",
        "--name",
        "rw",
        "--base",
        "base",
        "--expert",
        "expert",
        "--dataset",
        "traj",
        "--arch",
        "windowed_mlp",
        "--window",
        "4",
        "--hidden",
        "16,16",
        "--steps",
        "8",
        "--batch-size",
        "8",
        "--seed",
        "3",
        "--watch",
    ]);
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

//! `relreward eval discriminate`, `eval heatmap` and `job plot` end to end: numpy writes a
//! base dataset (random walks in a 5 x 5 walled maze) and an expert dataset (walks drifting to
//! the goal (3, 3)), both with `walls` (uint8) and `goals`; a base and an expert diffusion
//! model and a windowed reward are trained on them for a few steps with the CLI; then the
//! evaluation commands run against the real server and their JSON documents and PNG files are
//! checked (fields present and in range, pictures that decode to 900 x 700 RGB). The reward is
//! barely trained, so the values are checked for consistency, not for quality.

use std::path::Path;

use relreward_tests::{TestServer, ok, ok_json, refused, run_python, train_models};
use serde_json::Value;

const H: usize = 8;

/// Writes `base.npz`, `expert.npz` (D4RL keys, `walls` uint8 [5, 5], `goals` [N, 2]),
/// `walls.npz` (`walls` only) and `x.npz` (`x`: expert windows [B, H, 4]). Both datasets end
/// with the same two-row episode holding the pooled minimum and maximum of every coordinate,
/// so that their min-max normalizers agree (a reward needs base and expert models trained
/// under one normalizer).
const MAKE_DATA: &str = r#"
import sys
import numpy as np
out, H = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(0)
walls = np.zeros((5, 5), dtype=np.uint8)
walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = 1
goal = np.array([3.0, 3.0])

def episodes(kind, n_episodes, length):
    obs, act, goals = [], [], []
    for _ in range(n_episodes):
        pos = rng.uniform(0.6, 3.4, size=2)
        g = goal if kind == "expert" else rng.uniform(0.6, 3.4, size=2)
        for _ in range(length):
            if kind == "expert":
                step = 0.25 * (g - pos) + 0.03 * rng.normal(size=2)
            else:
                step = 0.2 * rng.normal(size=2)
            new = np.clip(pos + step, 0.6, 3.4)
            obs.append(np.concatenate([pos, new - pos]))
            act.append(np.clip(5.0 * step, -1, 1))
            goals.append(g)
            pos = new
    return np.array(obs, np.float32), np.array(act, np.float32), np.array(goals, np.float32)

data = {k: episodes(k, 20, 40) for k in ("base", "expert")}
rows = np.concatenate([np.concatenate([a, o], 1) for o, a, _ in data.values()])
lo, hi = rows.min(0), rows.max(0)
for kind, (obs, act, goals) in data.items():
    obs = np.concatenate([obs, [lo[2:], hi[2:]]]).astype(np.float32)
    act = np.concatenate([act, [lo[:2], hi[:2]]]).astype(np.float32)
    goals = np.concatenate([goals, [goals[-1], goals[-1]]]).astype(np.float32)
    n = len(obs)
    timeouts = np.zeros(n, dtype=bool)
    timeouts[np.arange(39, n - 2, 40)] = True
    timeouts[-1] = True
    np.savez(f"{out}/{kind}.npz", observations=obs, actions=act, timeouts=timeouts,
             terminals=np.zeros(n, dtype=bool), walls=walls, goals=goals)
np.savez(f"{out}/walls.npz", walls=walls)
obs, act, _ = data["expert"]
r = np.concatenate([act, obs], 1)
np.savez(f"{out}/x.npz", x=np.stack([r[s:s + H] for s in range(0, 40 - H + 1, 2)]).astype(np.float32))
"#;

/// Checks that a file is a PNG that decodes (chunk CRCs, the IDAT stream inflates to exactly
/// the declared 8-bit RGB pixels) and prints its size.
const CHECK_PNG: &str = r#"
import struct, sys, zlib
data = open(sys.argv[1], "rb").read()
assert data[:8] == b"\x89PNG\r\n\x1a\n", "no PNG signature"
pos, idat, ihdr = 8, b"", None
while pos < len(data):
    (length,) = struct.unpack(">I", data[pos:pos + 4])
    kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
    (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
    assert zlib.crc32(kind + body) == crc, f"bad CRC in {kind}"
    if kind == b"IHDR":
        ihdr = struct.unpack(">IIBBBBB", body)
    elif kind == b"IDAT":
        idat += body
    pos += 12 + length
w, h, depth, color = ihdr[:4]
assert (depth, color) == (8, 2), f"not 8-bit RGB: {ihdr}"
raw = zlib.decompress(idat)
assert len(raw) == h * (1 + 3 * w), f"{len(raw)} bytes for {w} x {h}"
print(w, h)
"#;

/// Asserts that `path` is a 900 x 700 RGB PNG that decodes.
#[track_caller]
fn assert_png(path: &Path) {
    assert!(path.exists(), "{} was not written", path.display());
    let bytes = std::fs::read(path).expect("read png");
    assert_eq!(relreward_toolkit::eval::plot::png_size(&bytes), Some((900, 700)), "{}", path.display());
    assert_eq!(run_python(CHECK_PNG, &[path.to_str().expect("utf8")]).trim(), "900 700");
}

fn f64_of(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("no number '{key}' in {v}"))
}

fn in_unit(v: f64) -> bool {
    (0.0..=1.0).contains(&v)
}

#[tokio::test(flavor = "multi_thread")]
async fn discriminate_heatmap_and_plots_run_against_a_trained_reward() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let dir = tmp.path();
    let path = |name: &str| dir.join(name).to_str().expect("utf8").to_owned();
    run_python(MAKE_DATA, &[dir.to_str().expect("utf8"), &H.to_string()]);

    // ---- datasets, a base and an expert diffusion model, a windowed reward.
    ok(&server, &["dataset", "upload", &path("base.npz"), "--name", "base-data"]);
    ok(&server, &["dataset", "upload", &path("expert.npz"), "--name", "expert-data"]);
    let reward_args = ["--steps", "40", "--batch-size", "16", "--job-id", "rw-job"];
    train_models(&server, dir, "base-data", "expert-data", &reward_args);

    // ---- eval discriminate: balanced classes, an 80/20 split, accuracies in [0, 1].
    let hist = path("disc-hist.png");
    let args = [
        "eval",
        "discriminate",
        "--model",
        "rw",
        "--base-data",
        &path("base.npz"),
        "--expert-data",
        &path("expert.npz"),
        "--max-windows",
        "300",
        "--seed",
        "7",
        "--hist-out",
        &hist,
    ];
    let d = ok_json(&server, &args);
    assert_eq!(d["model"], "rw");
    assert_eq!(d["t"], 0);
    for class in ["base", "expert"] {
        let c = &d[class];
        // 20 episodes of 40 rows and one of 2: 20 * 33 windows of 8 rows.
        assert_eq!(c["windows_available"], 660, "{c}");
        assert_eq!(c["n"], 300, "{c}");
        assert_eq!((c["n_train"].as_u64(), c["n_test"].as_u64()), (Some(240), Some(60)), "{c}");
        assert!(f64_of(c, "mean_reward").is_finite() && f64_of(c, "std_reward") >= 0.0, "{c}");
        assert_eq!(c["source"]["kind"], "trajectories");
    }
    for split in ["train", "test"] {
        assert!(in_unit(f64_of(&d[split], "accuracy")) && in_unit(f64_of(&d[split], "balanced_accuracy")), "{d}");
    }
    assert!(in_unit(f64_of(&d["test"], "auc")));
    assert_eq!(d["balanced_accuracy"], d["test"]["balanced_accuracy"]);
    assert_eq!(d["expert_scores_higher"], f64_of(&d["logistic"], "weight") > 0.0);
    let limits = d["winsorize"]["limits"].as_array().expect("limits");
    assert!(limits[0].as_f64() <= limits[1].as_f64(), "{limits:?}");
    assert_eq!(d["winsorize"]["p"], 0.01);
    let logistic = &d["logistic"];
    assert_eq!(logistic["converged"], true, "{logistic}");
    assert!(f64_of(logistic, "weight").is_finite() && f64_of(logistic, "feature_std") > 0.0);
    assert_eq!(d["hist_out"], hist.as_str());
    assert_png(Path::new(&hist));
    // The same seed gives the same subsets, split and fit.
    let again = ok_json(&server, &args);
    assert_eq!(again["test"], d["test"]);
    assert_eq!(again["logistic"], d["logistic"]);
    // Items from an x [B, H, D] array, and the text report.
    let text = ok(
        &server,
        &["eval", "discriminate", "--model", "rw", "--base-data", &path("base.npz"), "--expert-data", &path("x.npz")],
    );
    assert!(text.contains("balanced accuracy") && text.contains("logistic") && text.contains('%'), "{text}");

    // ---- eval heatmap: walls from a file, the goal from the expert data's constant goals.
    let heat = path("heatmap.png");
    let h = ok_json(
        &server,
        &[
            "eval",
            "heatmap",
            "--model",
            "rw",
            "--dataset",
            &path("base.npz"),
            "--out",
            &heat,
            "--walls",
            &path("walls.npz"),
            "--goal-from",
            &path("expert.npz"),
            "--stride",
            "1",
            "--bins-per-cell",
            "2",
            "--min-count",
            "2",
        ],
    );
    assert_eq!(h["unit"], "window", "a windowed reward is mapped window by window");
    assert_eq!((h["unit_rows"].as_u64(), h["horizon"].as_u64()), (Some(4), Some(H as u64)));
    assert_eq!((h["grid"]["rows"].as_u64(), h["grid"]["cols"].as_u64()), (Some(5), Some(5)));
    assert_eq!(h["grid"]["walls"], true);
    assert_eq!(h["bins"], 100);
    // Items at every row (33 per episode): their four-row windows start at rows 0..=36 of each
    // episode, and each is counted once however many items it was scored in.
    assert_eq!(h["items_scored"], 660);
    assert_eq!(h["sub_trajectories"], 20 * 37);
    let covered = h["bins_covered"].as_u64().expect("covered");
    assert!(covered > 0 && covered <= 100, "{covered}");
    assert_eq!(h["goal"]["x"], 3.0);
    assert_eq!(h["goal"]["y"], 3.0);
    let argmax = &h["argmax"];
    let (x, y) = (f64_of(argmax, "x"), f64_of(argmax, "y"));
    assert!((0.5..3.5).contains(&x) && (0.5..3.5).contains(&y), "the maximum lies in the free cells: {argmax}");
    let cell = argmax["cell"].as_array().expect("cell");
    assert_eq!((cell[0].as_f64(), cell[1].as_f64()), (Some(x.round()), Some(y.round())));
    assert!(in_unit(f64_of(argmax, "value")));
    let distance = f64_of(&h, "distance_cells");
    assert!((distance - (x - 3.0).abs().max((y - 3.0).abs())).abs() < 1e-9);
    assert_eq!(h["goal_recovered"], distance <= 1.0);
    assert!(f64_of(&h, "distance_euclidean") >= distance);
    assert_png(Path::new(&heat));
    // Defaults (10 bins per cell, at least 5 per bin), whole items, the walls of the dataset
    // itself, an explicit goal, and the text report.
    let heat_items = path("heatmap-items.png");
    let text = ok(
        &server,
        &[
            "eval",
            "heatmap",
            "--model",
            "rw",
            "--dataset",
            &path("base.npz"),
            "--out",
            &heat_items,
            "--unit",
            "item",
            "--goal",
            "1,2",
        ],
    );
    assert!(text.contains("goal") && text.contains("x = 1.00, y = 2.00") && text.contains("grid"), "{text}");
    assert_png(Path::new(&heat_items));
    let h = ok_json(
        &server,
        &["eval", "heatmap", "--model", "rw", "--dataset", &path("base.npz"), "--out", &heat_items, "--unit", "item"],
    );
    assert_eq!(h["unit"], "item");
    assert_eq!(h["bins"], 2500);
    assert!(h["goal"].is_null(), "the base data's goals vary: no goal: {}", h["goal"]);
    assert!(h["goal_recovered"].is_null());

    // ---- job plot: the reward job's loss curve and a two-dataset reward histogram.
    let loss = path("loss.png");
    let rewards = path("rewards.png");
    let p = ok_json(
        &server,
        &[
            "job",
            "plot",
            "rw-job",
            "--out",
            &loss,
            "--hist-out",
            &rewards,
            "--dataset",
            &path("base.npz"),
            "--dataset",
            &path("expert.npz"),
            "--max-windows",
            "200",
        ],
    );
    assert_eq!(
        (p["job"].as_str(), p["kind"].as_str(), p["state"].as_str()),
        (Some("rw-job"), Some("reward"), Some("succeeded"))
    );
    assert!(p["loss_points"].as_u64() > Some(0));
    assert_eq!(p["last_step"], 40.0);
    assert!(p["log_scale"].is_boolean());
    assert_eq!(p["histogram"]["model"], "rw", "the job's own model by default");
    let per = p["histogram"]["datasets"].as_array().expect("datasets");
    assert_eq!(per.len(), 2);
    assert!(per.iter().all(|d| d["windows"] == 200 && f64_of(d, "mean").is_finite()));
    assert_png(Path::new(&loss));
    assert_png(Path::new(&rewards));
    // A diffusion job: the loss alone (its model is not a reward).
    let jobs = ok_json(&server, &["job", "list"]);
    let diffusion_job = jobs
        .as_array()
        .expect("jobs")
        .iter()
        .find(|j| j["spec"]["kind"] == "diffusion")
        .and_then(|j| j["id"].as_str())
        .expect("a diffusion job")
        .to_owned();
    let text = ok(&server, &["job", "plot", &diffusion_job, "--out", &loss]);
    assert!(text.contains("diffusion") && text.contains("loss"), "{text}");
    assert_png(Path::new(&loss));

    // ---- refusals name the flag.
    refused(
        &server,
        &[
            "eval",
            "discriminate",
            "--model",
            "rw",
            "--base-data",
            &path("missing.npz"),
            "--expert-data",
            &path("x.npz"),
        ],
        &["--base-data"],
    );
    refused(
        &server,
        &["eval", "heatmap", "--model", "rw", "--dataset", &path("x.npz"), "--out", &heat],
        &["--xy-columns"],
    );
    refused(
        &server,
        &["eval", "heatmap", "--model", "rw", "--dataset", &path("base.npz"), "--out", &path("no/dir/h.png")],
        &["--out"],
    );
    refused(
        &server,
        &[
            "eval",
            "heatmap",
            "--model",
            "rw",
            "--dataset",
            &path("base.npz"),
            "--out",
            &heat,
            "--goal-from",
            &path("base.npz"),
        ],
        &["--goal-from"],
    );
    refused(
        &server,
        &["eval", "heatmap", "--model", "base", "--dataset", &path("base.npz"), "--out", &heat],
        &["--model base", "diffusion"],
    );
    refused(&server, &["job", "plot", "no-such-job", "--out", &loss], &["NOT_FOUND"]);
    refused(
        &server,
        &["job", "plot", &diffusion_job, "--out", &loss, "--hist-out", &rewards, "--dataset", &path("base.npz")],
        &["--model"],
    );
}

//! `relreward extract` end to end on users' formats: a D4RL-layout HDF5 file as the base data
//! and a Minari dataset directory (dict observations) as the expert data, with the tiny sizes,
//! against a real server: upload, both diffusion models, the reward and the discriminator,
//! evaluation with the file's own `wall_map`, report and pictures. A second run reuses every
//! dataset and model by name (fingerprints of the files and sizes).

use std::path::{Path, PathBuf};

use relreward_client::pb;
use relreward_tests::TestServer;
use relreward_toolkit::eval::plot::png_size;
use serde_json::Value;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../client/toolkit/tests/data/e2e").join(name)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_d4rl_file_and_a_minari_dataset_extract_end_to_end() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let out_dir = tmp.path().join("extract");
    let (base, expert) = (data("base_d4rl.hdf5"), data("expert_minari"));
    let args = [
        "--json",
        "extract",
        "--base",
        base.to_str().expect("utf8"),
        "--expert",
        expert.to_str().expect("utf8"),
        "--goal",
        "3,3",
        "--size",
        "tiny",
        "--discriminator",
        "--out",
        out_dir.to_str().expect("utf8"),
    ];
    let out = server.cli(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).expect("report JSON");
    // Both files were read: 20 x 100 base rows, 10 x 100 expert rows (Minari's last
    // observation of each episode dropped).
    let profiles = report["profiles"].as_array().expect("profiles");
    assert_eq!((profiles[0]["rows"].as_u64(), profiles[0]["episodes"].as_u64()), (Some(2000), Some(20)));
    assert_eq!((profiles[1]["rows"].as_u64(), profiles[1]["episodes"].as_u64()), (Some(1000), Some(10)));
    // The horizon came from the data and fits its 100-row episodes.
    let horizon = report["sizes"]["horizon"].as_u64().expect("horizon");
    assert!((4..=64).contains(&horizon), "{horizon}");
    let rows = report["rewards"].as_array().expect("rewards");
    assert_eq!(rows.len(), 1);
    let row = &rows[0];
    let acc = row["balanced_accuracy"].as_f64().expect("accuracy");
    assert!((0.0..=1.0).contains(&acc), "{acc}");
    assert!(row["goal_recovered"].is_boolean(), "the wall_map in the base file enables the heatmap: {row}");
    assert!(row["discriminator"]["balanced_accuracy"].is_number(), "{row}");
    // The at-rest heatmap ran beside the paper's, or was refused with its reason (a state
    // that is more than a position and its velocities cannot be held still).
    assert!(row["goal_recovered_at_rest"].is_boolean() || row["at_rest_refused"].is_string(), "{row}");
    for key in ["heatmap", "loss_plot", "histogram"] {
        let bytes = std::fs::read(row[key].as_str().expect("path")).expect("picture");
        let (w, h) = png_size(&bytes).expect("a PNG");
        assert!(w >= 400 && h >= 300, "{key}: {w}x{h}");
    }
    assert!(out_dir.join("report.md").exists() && out_dir.join("report.json").exists());
    assert!(out_dir.join("data/base.npz").exists(), "HDF5 inputs are converted to the canonical .npz");

    // Again: everything is found by name and reused.
    let again = server.cli(&args[1..]);
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
    let text = String::from_utf8_lossy(&again.stderr);
    for what in ["reusing dataset", "reusing diffusion model", "reusing reward", "reusing discriminator"] {
        assert!(text.contains(what), "second run should say '{what}':\n{text}");
    }
}

/// A goal-terminated expert of the fixtures' room as a canonical `.npz`: the fixture's PD
/// controller to position (3, 3) (rows `[achieved_goal, desired_goal, position, velocity]`,
/// as `base_d4rl.hdf5`), each episode ending with a `terminals` row on arrival (within 0.3 of
/// the goal) or cut by a timeout after 100 steps; `goals` `[N, 2]` as `goals(row)` says.
fn goal_terminated_expert(path: &std::path::Path, goals: Option<&dyn Fn(usize) -> [f32; 2]>) {
    let mut seed = 12345u64;
    let mut uniform = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let (mut obs, mut act, mut terminals, mut timeouts) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..12 {
        let mut pos = [0.7 + 2.6 * uniform(), 0.7 + 2.6 * uniform()];
        let mut vel = [0.0f64; 2];
        for step in 0..100 {
            obs.extend([pos[0], pos[1], 3.0, 3.0, pos[0], pos[1], vel[0], vel[1]].map(|v| v as f32));
            let mut a = [0.0f64; 2];
            for k in 0..2 {
                a[k] = (2.0 * (3.0 - pos[k]) - vel[k] + 0.3 * (uniform() - 0.5)).clamp(-1.0, 1.0);
                vel[k] = 0.9 * vel[k] + 0.1 * a[k];
                pos[k] = (pos[k] + vel[k]).clamp(0.55, 3.45);
            }
            act.extend(a.map(|v| v as f32));
            let arrived = (pos[0] - 3.0).hypot(pos[1] - 3.0) < 0.3;
            terminals.push(arrived);
            timeouts.push(!arrived && step == 99);
            if arrived {
                break;
            }
        }
    }
    let n = terminals.len() as u64;
    let mut w = relreward_toolkit::npz_write::NpzWriter::create(path).expect("npz");
    w.add_f32("observations", &[n, 8], &obs).expect("observations");
    w.add_f32("actions", &[n, 2], &act).expect("actions");
    w.add_bool("terminals", &[n], &terminals).expect("terminals");
    w.add_bool("timeouts", &[n], &timeouts).expect("timeouts");
    if let Some(goal) = goals {
        let values: Vec<f32> = (0..n as usize).flat_map(goal).collect();
        w.add_f32("goals", &[n, 2], &values).expect("goals");
    }
    w.finish().expect("npz");
    assert!(terminals.iter().filter(|&&t| t).count() >= 6, "most episodes arrive");
}

/// Issue 34 item 4: `--absorbing` keeps the expert file's constant `goals` in the converted
/// file, so the goal defaults to them and the maze evaluation runs (before the fix the run
/// trained everything and then failed: "--goal-from OUT/data/e0-...npz: no 'goals' array");
/// the same run with an explicit `--goal` reuses every model and measures the same.
#[tokio::test(flavor = "multi_thread")]
async fn absorbing_keeps_the_goals_the_evaluation_reads() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let expert = tmp.path().join("expert.npz");
    goal_terminated_expert(&expert, Some(&|_| [3.0, 3.0]));
    let out_dir = tmp.path().join("extract");
    let base = data("base_d4rl.hdf5");
    let run = |extra: &[&str]| {
        let mut args = vec![
            "extract",
            "--base",
            base.to_str().expect("utf8"),
            "--expert",
            expert.to_str().expect("utf8"),
            "--absorbing",
            "8",
            "--size",
            "tiny",
            "--out",
            out_dir.to_str().expect("utf8"),
        ];
        args.extend_from_slice(extra);
        let out = server.cli(&args);
        assert!(out.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&out.stderr));
        let report: Value =
            serde_json::from_slice(&std::fs::read(out_dir.join("report.json")).expect("report")).expect("report JSON");
        (report["rewards"][0].clone(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (row, _) = run(&[]);
    assert_eq!(row["goal"], serde_json::json!([3.0, 3.0]), "the goal came from the expert's goals: {row}");
    assert!(row["goal_recovered"].is_boolean(), "{row}");
    let converted = PathBuf::from(row["expert_data"].as_str().expect("expert_data"));
    assert!(converted.starts_with(out_dir.join("data")), "--absorbing writes the padded file: {row}");
    let (shape, goals) = relreward_toolkit::npz::read_numbers(&converted, "goals").expect("read").expect("goals kept");
    let rows = relreward_toolkit::npz::npz_array_shape(&converted, "observations").expect("read").expect("rows")[0];
    assert_eq!(shape, [rows, 2], "goals stay one per row after padding");
    assert!(goals.iter().all(|&g| g == 3.0));

    // The same run with the goal given: every model reused, the same measures.
    let (explicit, stderr) = run(&["--goal", "3,3"]);
    for what in ["reusing diffusion model", "reusing reward"] {
        assert!(stderr.contains(what), "the explicit run should say '{what}':\n{stderr}");
    }
    for key in ["goal", "goal_recovered", "argmax_cell", "balanced_accuracy"] {
        assert_eq!(explicit[key], row[key], "{key}");
    }
}

/// `relreward extract --size tiny` of one base and one expert file into `out`, with `extra` flags.
fn tiny_extract(server: &TestServer, base: &Path, expert: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let paths = [base, expert, out].map(|p| p.to_str().expect("utf8").to_owned());
    let mut args = vec!["extract", "--base", &paths[0], "--expert", &paths[1], "--size", "tiny", "--out", &paths[2]];
    args.extend_from_slice(extra);
    server.cli(&args)
}

/// Issue 34 item 4: an expert whose goal the maze evaluation cannot know (no `goals`, or goals
/// that are not one constant goal, and no `--goal`) fails in seconds, naming the flag and the
/// file, before anything is uploaded or trained.
#[tokio::test(flavor = "multi_thread")]
async fn an_expert_without_a_constant_goal_fails_before_any_upload() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let base = data("base_d4rl.hdf5");
    let varying = tmp.path().join("varying.npz");
    goal_terminated_expert(&varying, Some(&|row| if row % 2 == 0 { [3.0, 3.0] } else { [1.0, 1.0] }));
    let missing = tmp.path().join("missing.npz");
    goal_terminated_expert(&missing, None);
    for (expert, absorbing, why) in
        [(&varying, "8", "not one constant goal"), (&missing, "0", "no 'goals' array"), (&varying, "0", "constant")]
    {
        let started = std::time::Instant::now();
        let out = tiny_extract(&server, &base, expert, &tmp.path().join("out"), &["--absorbing", absorbing]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{}: should fail:\n{stderr}", expert.display());
        assert!(stderr.contains("--goal") && stderr.contains(why), "{stderr}");
        assert!(started.elapsed().as_secs() < 60, "failed late: {:?}", started.elapsed());
    }
    let client = server.client().await;
    assert!(client.list_datasets().await.expect("datasets").is_empty(), "nothing uploaded");
    assert!(client.list_jobs(pb::JobState::Unspecified).await.expect("jobs").is_empty(), "no job submitted");
    assert!(client.list_models(pb::ModelKind::Unspecified).await.expect("models").is_empty());
}

/// Base and expert recordings whose rows differ in width (two environments) fail in seconds,
/// naming both files and their widths, before anything is uploaded (they failed at the
/// normalizer of the first training job, after both uploads).
#[tokio::test(flavor = "multi_thread")]
async fn recordings_of_different_widths_fail_before_any_upload() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let base = data("base_d4rl.hdf5");
    let expert = tmp.path().join("other-env.npz");
    let n = 40u64;
    let mut w = relreward_toolkit::npz_write::NpzWriter::create(&expert).expect("npz");
    let obs: Vec<f32> = (0..n * 3).map(|i| (i % 7) as f32 * 0.1).collect();
    w.add_f32("observations", &[n, 3], &obs).expect("observations");
    w.add_f32("actions", &[n, 1], &vec![0.5; n as usize]).expect("actions");
    w.finish().expect("npz");
    let out = tiny_extract(&server, &base, &expert, &tmp.path().join("out"), &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "should fail:\n{stderr}");
    assert!(stderr.contains("rows of 3 observation and 1 action values, but the base data"), "{stderr}");
    assert!(stderr.contains("has 8 and 2"), "{stderr}");
    let client = server.client().await;
    assert!(client.list_datasets().await.expect("datasets").is_empty(), "nothing uploaded");
}

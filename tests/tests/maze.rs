//! `relreward maze generate` end to end: the real binary writes Maze2D files without a server,
//! numpy reads them with D4RL's keys, the same arguments give the same bytes, bad arguments
//! exit 2 naming their flag, and a generated file uploads to a real server as a trajectories
//! dataset.

use std::path::Path;
use std::process::{Command, Output, Stdio};

use relreward_tests::{TestServer, bin, run_python, stderr};
use serde_json::Value;

/// Runs `relreward [--json] maze generate ARGS` directly (the command needs no server).
fn maze(json: bool, args: &[&str]) -> Output {
    let mut cmd = Command::new(bin("relreward"));
    if json {
        cmd.arg("--json");
    }
    cmd.args(["maze", "generate"]).args(args).stdin(Stdio::null()).output().expect("run relreward")
}

/// Runs a generation that must succeed; returns its JSON summary.
#[track_caller]
fn generate(args: &[&str]) -> Value {
    let out = maze(true, args);
    assert!(out.status.success(), "{args:?} failed: {}", stderr(&out));
    serde_json::from_slice(&out.stdout).expect("JSON summary")
}

/// The archive's bytes with every entry's DOS modification time and date zeroed: the zip writer
/// stamps entries with the current time, the one thing two runs may differ in.
fn without_zip_times(path: &Path) -> Vec<u8> {
    let mut b = std::fs::read(path).expect("read archive");
    let u16_at = |b: &[u8], i: usize| usize::from(u16::from_le_bytes([b[i], b[i + 1]]));
    let u32_at = |b: &[u8], i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]) as usize;
    // No archive comment: the end-of-central-directory record is the last 22 bytes.
    let eocd = b.len() - 22;
    assert_eq!(u32_at(&b, eocd), 0x0605_4b50, "end of central directory");
    let entries = u16_at(&b, eocd + 10);
    let mut at = u32_at(&b, eocd + 16);
    for _ in 0..entries {
        assert_eq!(u32_at(&b, at), 0x0201_4b50, "central directory header");
        let local = u32_at(&b, at + 42);
        assert_eq!(u32_at(&b, local), 0x0403_4b50, "local header");
        b[at + 12..at + 16].fill(0);
        b[local + 10..local + 14].fill(0);
        at += 46 + u16_at(&b, at + 28) + u16_at(&b, at + 30) + u16_at(&b, at + 32);
    }
    b
}

/// Reads a generated file with numpy and reports what D4RL users would check.
const CHECK_NPZ: &str = r#"
import json, sys
import numpy as np
with np.load(sys.argv[1]) as d:
    arrays = {k: [str(d[k].dtype), list(d[k].shape)] for k in d.files}
    obs, walls, goals = d["observations"], d["walls"].astype(np.uint8), d["goals"]
    term, tout = d["terminals"], d["timeouts"]
    # The disc's bounding square (radius 0.1, a hair less for float32 rounding) stays in free cells.
    inside = 0
    for dx in (-0.0999, 0.0999):
        for dy in (-0.0999, 0.0999):
            i = np.floor(obs[:, 0] + dx + 0.5).astype(int)
            j = np.floor(obs[:, 1] + dy + 0.5).astype(int)
            inside += int(walls[i, j].sum())
    ends = np.flatnonzero(term | tout)
    lengths = np.diff(np.concatenate([[-1], ends]))
    # Within 0.5 of the goal in force (float32 rounding allowed for).
    near = np.hypot(obs[:, 0] - goals[:, 0], obs[:, 1] - goals[:, 1]) <= 0.5 + 1e-5
    print(json.dumps({
        "arrays": arrays,
        "rows_in_walls": inside,
        "episodes": int(len(ends)),
        "last_row_closed": bool(term[-1] or tout[-1]),
        "both_flags": int((term & tout).sum()),
        "max_length": int(lengths.max()),
        "lengths_but_last": sorted(set(lengths[:-1].tolist())),
        "near_goal_fraction": float(near.mean()),
        "episodes_ending_near_goal": int(near[ends].sum()),
        "terminals": int(term.sum()),
        "distinct_goals": int(len(np.unique(goals, axis=0))),
        "max_abs_action": float(np.abs(d["actions"]).max()),
        "walls": walls.tolist(),
    }))
"#;

fn check_npz(path: &Path) -> Value {
    let text = run_python(CHECK_NPZ, &[path.to_str().expect("utf8")]);
    serde_json::from_str(&text).expect("JSON from the numpy check")
}

/// `--layout umaze --mode expert --transitions 20000 --seed SEED --out OUT`.
fn umaze_expert<'a>(out: &'a str, seed: &'a str) -> [&'a str; 10] {
    ["--layout", "umaze", "--mode", "expert", "--transitions", "20000", "--seed", seed, "--out", out]
}

#[test]
fn generated_files_have_d4rl_keys_and_the_same_arguments_give_the_same_bytes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = |name: &str| dir.path().join(name).display().to_string();
    let (a, b, c) = (path("a.npz"), path("b.npz"), path("c.npz"));
    let summary = generate(&umaze_expert(&a, "3"));
    assert_eq!(summary["out"], a.as_str());
    assert_eq!((summary["layout"].as_str(), summary["mode"].as_str()), (Some("umaze"), Some("expert")));
    assert_eq!(summary["goal"], serde_json::json!([1, 1]), "D4RL's umaze goal by default");
    assert_eq!((summary["transitions"].as_u64(), summary["max_episode_steps"].as_u64()), (Some(20_000), Some(300)));
    // Episodes end only at the cap: 66 of 300 steps and the file's last 200 rows.
    let episodes = summary["episodes"].as_u64().expect("episodes");
    assert_eq!(episodes, 67);
    // Expert mode counts episodes that reached the goal (held from then on to the cap).
    let reached = summary["goals_reached"].as_u64().expect("goals_reached");
    assert!(reached as f64 >= 0.9 * episodes as f64 && reached <= episodes, "{reached} of {episodes}");

    let checked = check_npz(Path::new(&a));
    let arrays = &checked["arrays"];
    assert_eq!(arrays["observations"], serde_json::json!(["float32", [20000, 4]]));
    assert_eq!(arrays["actions"], serde_json::json!(["float32", [20000, 2]]));
    assert_eq!(arrays["terminals"], serde_json::json!(["bool", [20000]]));
    assert_eq!(arrays["timeouts"], serde_json::json!(["bool", [20000]]));
    assert_eq!(arrays["goals"], serde_json::json!(["float32", [20000, 2]]));
    assert_eq!(arrays["walls"], serde_json::json!(["bool", [5, 5]]));
    assert_eq!(checked["walls"][2], serde_json::json!([1, 1, 1, 0, 1]), "row 2 of umaze: ###O#");
    assert_eq!(checked["rows_in_walls"], 0);
    assert_eq!(checked["episodes"].as_u64(), Some(episodes));
    // D4RL's maze2d: reaching the goal sets no terminal; the goal is held until the cap.
    assert_eq!(checked["terminals"].as_u64(), Some(0), "no terminals in expert mode");
    assert_eq!((checked["last_row_closed"].as_bool(), checked["both_flags"].as_u64()), (Some(true), Some(0)));
    assert_eq!(checked["max_length"].as_u64(), Some(300));
    assert_eq!(checked["lengths_but_last"], serde_json::json!([300]), "every episode but the last is capped");
    let ending_near = checked["episodes_ending_near_goal"].as_u64().expect("episodes_ending_near_goal");
    assert!(ending_near >= reached, "{ending_near} episodes end at the goal, {reached} reached it");
    let near = checked["near_goal_fraction"].as_f64().expect("near_goal_fraction");
    assert!(near > 0.7, "only {near} of the expert rows lie at the goal");
    assert_eq!(checked["distinct_goals"], 1, "one expert goal");
    assert!(checked["max_abs_action"].as_f64().expect("actions") <= 1.0);

    // Same arguments, same bytes (but for the zip's time stamps); another seed, other data.
    generate(&umaze_expert(&b, "3"));
    let (bytes_a, bytes_b) = (without_zip_times(Path::new(&a)), without_zip_times(Path::new(&b)));
    assert!(bytes_a == bytes_b, "two runs with the same arguments wrote different files");
    generate(&umaze_expert(&c, "4"));
    assert_ne!(bytes_a, without_zip_times(Path::new(&c)));

    // Text output: a short summary.
    let out = maze(false, &["--layout", "large", "--mode", "base", "--transitions", "5000", "--out", &c]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = String::from_utf8_lossy(&out.stdout);
    for expected in ["wrote ", "layout", "large (9 x 12, 46 free cells)", "mode", "base", "transitions", "5000"] {
        assert!(text.contains(expected), "{expected:?} missing from:\n{text}");
    }
    let checked = check_npz(Path::new(&c));
    assert_eq!((checked["rows_in_walls"].as_u64(), checked["terminals"].as_u64()), (Some(0), Some(0)));
    assert!(checked["distinct_goals"].as_u64().expect("goals") > 10, "base goals are redrawn");
}

#[test]
fn bad_arguments_exit_2_naming_the_flag() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("x.npz").display().to_string();
    let missing_dir = dir.path().join("nope/x.npz").display().to_string();
    let base = |extra: &[&'static str]| {
        let mut v = vec!["--layout", "umaze", "--mode", "expert", "--transitions", "100"];
        v.extend_from_slice(extra);
        v
    };
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["--layout", "spiral", "--mode", "base", "--transitions", "10", "--out", &out], "--layout"),
        (vec!["--layout", "umaze", "--mode", "greedy", "--transitions", "10", "--out", &out], "--mode"),
        (vec!["--layout", "umaze", "--mode", "base", "--transitions", "0", "--out", &out], "--transitions"),
        (vec!["--layout", "umaze", "--mode", "base", "--transitions", "-5", "--out", &out], "--transitions"),
        (vec!["--layout", "umaze", "--mode", "base", "--out", &out], "--transitions"),
        // 3.4 PB of rows: more than any address space.
        (
            vec!["--layout", "umaze", "--mode", "base", "--transitions", "100000000000000", "--out", &out],
            "--transitions",
        ),
        ([base(&["--goal", "0,0"]), vec!["--out", &out]].concat(), "--goal"),
        ([base(&["--goal", "2,2"]), vec!["--out", &out]].concat(), "--goal"),
        ([base(&["--goal", "9,1"]), vec!["--out", &out]].concat(), "--goal"),
        ([base(&["--goal", "one,two"]), vec!["--out", &out]].concat(), "--goal"),
        (vec!["--layout", "umaze", "--mode", "base", "--goal", "1,1", "--transitions", "10", "--out", &out], "--goal"),
        ([base(&["--action-noise", "-1"]), vec!["--out", &out]].concat(), "--action-noise"),
        ([base(&["--seed", "-1"]), vec!["--out", &out]].concat(), "--seed"),
        ([base(&[]), vec!["--out", &missing_dir]].concat(), "--out"),
        (base(&[]), "--out"),
    ];
    for (args, flag) in cases {
        let result = maze(false, &args);
        let err = stderr(&result);
        assert_eq!(result.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(flag), "{args:?}: {flag} not named in: {err}");
    }
    let wall = stderr(&maze(false, &[base(&["--goal", "2,2"]), vec!["--out", &out]].concat()));
    assert!(wall.contains("is a wall"), "{wall}");
    assert!(!Path::new(&out).exists(), "nothing written on a usage error");
}

#[test]
fn a_generated_file_uploads_as_a_trajectories_dataset() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("medium.npz").display().to_string();
    let summary =
        generate(&["--layout", "medium", "--mode", "base", "--transitions", "30000", "--seed", "7", "--out", &path]);
    assert_eq!(summary["episodes"], 50, "episodes of 600 steps");

    let server = TestServer::start();
    let out = server.cli(&["--json", "dataset", "upload", &path, "--name", "maze"]);
    let err = stderr(&out);
    assert!(out.status.success(), "upload failed: {err}\nlog:\n{}", server.log());
    assert!(err.contains("'goals'") && err.contains("'walls'"), "extra keys reported as left out: {err}");
    let dataset: Value = serde_json::from_slice(&out.stdout).expect("dataset JSON");
    assert_eq!((dataset["kind"].as_str(), dataset["num_rows"].as_u64()), (Some("trajectories"), Some(30_000)));
    let names: Vec<&str> =
        dataset["arrays"].as_array().expect("arrays").iter().filter_map(|a| a["name"].as_str()).collect();
    assert_eq!(names, ["observations", "actions", "terminals", "timeouts"]);
    let episodes = &dataset["episodes"];
    assert_eq!((episodes["count"].as_u64(), episodes["max_length"].as_u64()), (Some(50), Some(600)));
    let obs = dataset["arrays"][0]["stats"]["min"].as_array().expect("observation minima");
    // Free positions of the medium maze lie within rows and columns 1..=6.
    assert!(obs[0].as_f64().expect("x min") > 0.5 && obs[1].as_f64().expect("y min") > 0.5, "{obs:?}");
}

//! `relreward demo` with its tiny configuration: the whole Maze2D pipeline runs against a real
//! server (generation, upload, diffusion models, rewards, heatmaps, discrimination, steering),
//! expert windows score higher than base windows, and the pictures are real PNGs.

use relreward_tests::TestServer;
use relreward_toolkit::eval::plot::png_size;
use serde_json::Value;

#[tokio::test(flavor = "multi_thread")]
async fn the_tiny_demo_runs_end_to_end_and_writes_its_pictures() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let out_dir = tmp.path().join("demo");
    let out =
        server.cli(&["--json", "demo", "--size", "tiny", "--goals", "2", "--out", out_dir.to_str().expect("utf8")]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: Value = serde_json::from_slice(&out.stdout).expect("summary JSON");
    assert_eq!(summary["layout"], "umaze");
    assert_eq!(summary["goals_total"], 2);
    let goals = summary["goals"].as_array().expect("goals");
    assert_eq!(goals.len(), 2);
    for g in goals {
        assert_eq!(g["expert_scores_higher"], true, "expert windows must score higher on average: {g}");
        let acc = g["balanced_accuracy"].as_f64().expect("accuracy");
        assert!((0.5..=1.0).contains(&acc), "{acc}");
        for key in ["heatmap", "loss_plot"] {
            let bytes = std::fs::read(g[key].as_str().expect("path")).expect("picture");
            let (w, h) = png_size(&bytes).expect("a PNG");
            assert!(w >= 400 && h >= 300, "{key}: {w}x{h}");
        }
        let steering = &g["steering"];
        for key in ["unguided_near_goal", "guided_near_goal"] {
            assert!((0.0..=1.0).contains(&steering[key].as_f64().expect("fraction")), "{steering}");
        }
    }
    // The summary names the models it made (their names carry fingerprints, so a user cannot
    // guess them): in the JSON, and in the text table (summary.md is the text `demo` prints).
    let rewards: Vec<&str> =
        summary["models"]["rewards"].as_array().expect("models.rewards").iter().filter_map(Value::as_str).collect();
    let experts: Vec<&str> =
        summary["models"]["experts"].as_array().expect("models.experts").iter().filter_map(Value::as_str).collect();
    let base = summary["models"]["base"].as_str().expect("models.base");
    assert_eq!((rewards.len(), experts.len()), (2, 2), "{summary}");
    for (g, (reward, expert)) in goals.iter().zip(rewards.iter().zip(&experts)) {
        assert_eq!(g["reward_model"], *reward, "{g}");
        assert_eq!(g["expert_model"], *expert, "{g}");
    }
    let table = std::fs::read_to_string(out_dir.join("summary.md")).expect("summary.md");
    for name in rewards.iter().chain(&experts).chain([&base]) {
        assert!(table.contains(name), "summary.md does not name model '{name}':\n{table}");
    }
    // Every named model is on the server, rewards as rewards.
    for name in &rewards {
        let shown: Value = serde_json::from_slice(&server.cli(&["--json", "model", "show", name]).stdout)
            .unwrap_or_else(|e| panic!("model show {name}: {e}"));
        assert_eq!(shown["kind"], "reward", "{shown}");
    }
    assert!(out_dir.join("summary.md").exists() && out_dir.join("summary.json").exists());
    assert!(out_dir.join("data/base.npz").exists());
}

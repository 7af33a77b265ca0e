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
    assert!(out_dir.join("summary.md").exists() && out_dir.join("summary.json").exists());
    assert!(out_dir.join("data/base.npz").exists());
}

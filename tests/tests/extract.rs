//! `relreward extract` end to end on users' formats: a D4RL-layout HDF5 file as the base data
//! and a Minari dataset directory (dict observations) as the expert data, with the tiny sizes,
//! against a real server: upload, both diffusion models, the reward and the discriminator,
//! evaluation with the file's own `wall_map`, report and pictures. A second run reuses every
//! dataset and model by name (fingerprints of the files and sizes).

use std::path::PathBuf;

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

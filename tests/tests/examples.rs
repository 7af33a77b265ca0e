//! The Python examples under `examples/` run against a real server and do what they say.

use relreward_tests::{TestServer, python, repo_root, train_tiny_reward};
use serde_json::Value;

/// `examples/planner_gradient_stream.py`: one GradientStream per episode, a request per guide
/// step; each step along the returned gradient raises rho.
#[tokio::test(flavor = "multi_thread")]
async fn the_planner_example_climbs_the_reward_over_one_gradient_stream() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let models = train_tiny_reward(&server, tmp.path());
    let out = std::process::Command::new(python())
        .arg(repo_root().join("examples/planner_gradient_stream.py"))
        .args(["--endpoint", &server.addr.to_string(), "--model", &models.reward, "--omega", "0.05"])
        .output()
        .expect("python");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    assert_eq!(summary["requests"], 2 * models.n_timesteps, "two guide steps per diffusion step");
    assert!(summary["rho_first_step"].is_f64() && summary["rho_last_step"].is_f64(), "{summary}");
    // A small step along grad_x rho raises rho at the same t (to first order).
    let gain = summary["mean_gain_per_guide_step"].as_f64().expect("gain");
    assert!(gain > 0.0, "guide steps must climb the reward: {summary}");
    assert!(summary["latency_ms"]["p50"].as_f64().expect("p50") > 0.0);
}

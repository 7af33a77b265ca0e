//! Training jobs end to end: submission, idempotent ids, watch replay, cancellation, and a
//! kill -9 of the server in the middle of a RUNNING diffusion job.

use relreward_client::Client;
use relreward_client::pb::{self, job_event::Event};
use relreward_tests::{Lines, TestServer, final_state, upload_lines, wait_for_checkpoint, watch_all};
use tokio_stream::StreamExt;
use tonic::Code;

/// Straight-line trajectories (see [`Lines`]): x0, y0 in [-1, 1), vx, vy in [-0.1, 0.1),
/// 200 episodes.
const LINES: Lines =
    Lines { episodes: 200, seed: 12345, start: [(2.0, -1.0), (2.0, -1.0)], velocity: [(0.2, -0.1), (0.2, -0.1)] };

fn spec(dataset: &str, output: &str, steps: u64, checkpoint_every: u64) -> pb::JobSpec {
    pb::JobSpec {
        output_model: output.into(),
        seed: Some(7),
        optimization: Some(pb::Optimization {
            steps: Some(steps),
            batch_size: Some(32),
            learning_rate: Some(1e-3),
            checkpoint_every: Some(checkpoint_every),
            eval_every: Some(100),
            log_every: Some(10),
            ema_start: Some(20),
            // A short run: average over the last ~100 steps, not over most of the run.
            ema_decay: Some(0.9),
            ..Default::default()
        }),
        kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
            dataset: dataset.into(),
            horizon: Some(8),
            n_timesteps: Some(10),
            // eps-prediction: its loss has no large irreducible floor at high noise levels,
            // unlike x0-prediction, so the fall of the loss measures learning.
            parametrization: pb::Parametrization::Epsilon as i32,
            architecture: Some(pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet {
                dim: Some(16),
                dim_mults: vec![1, 2],
            })),
            ..Default::default()
        })),
    }
}

async fn submit(client: &Client, spec: pb::JobSpec, id: &str) -> Result<pb::Job, tonic::Status> {
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: id.into() }).await.map(|r| r.into_inner())
}

fn progress(events: &[pb::JobEvent]) -> Vec<pb::job_event::Progress> {
    events
        .iter()
        .filter_map(|e| match &e.event {
            Some(Event::Progress(p)) => Some(*p),
            _ => None,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn diffusion_job_trains_registers_and_replays() {
    let server = TestServer::start();
    let client = server.client().await;
    upload_lines(&client, "lines", &LINES).await;

    let job = submit(&client, spec("lines", "lines-unet", 1500, 500), "train-lines").await.expect("submit");
    assert_eq!(job.id, "train-lines");
    // Idempotent: the same spec under the same id is the same job; a different spec is refused.
    let again = submit(&client, spec("lines", "lines-unet", 1500, 500), "train-lines").await.expect("resubmit");
    assert_eq!((again.id.as_str(), again.created_at), ("train-lines", job.created_at));
    let err = submit(&client, spec("lines", "lines-unet", 401, 100), "train-lines").await.expect_err("different spec");
    assert_eq!(err.code(), Code::AlreadyExists);

    let events = watch_all(&client, "train-lines", 0).await;
    assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "{events:?}");
    let seqs: Vec<u64> = events.iter().map(|e| e.seq).collect();
    assert_eq!(seqs, (1..=seqs.len() as u64).collect::<Vec<_>>(), "sequence numbers start at 1 without gaps");
    let p = progress(&events);
    let (first, last) = (p.first().expect("progress"), p.last().expect("progress"));
    assert_eq!(last.step, 1500);
    eprintln!("losses: {:?}", p.iter().map(|p| (p.step, p.loss, p.eval_loss)).collect::<Vec<_>>());
    assert!(last.loss < first.loss / 4.0, "loss fell from {} to {}", first.loss, last.loss);
    let evals: Vec<f64> = p.iter().filter_map(|p| p.eval_loss).collect();
    assert!(evals.len() >= 4 && evals.last() < evals.first(), "held-out loss {evals:?}");

    // Replay from a sequence number returns exactly the tail.
    let tail = watch_all(&client, "train-lines", 5).await;
    assert_eq!(tail, events[4..].to_vec());

    let model =
        client.models().get_model(pb::GetModelRequest { name: "lines-unet".into() }).await.expect("model").into_inner();
    assert_eq!((model.name.as_str(), model.kind()), ("lines-unet", pb::ModelKind::Diffusion));

    // Its samples look like the data: straight lines (constant velocity) moving about as far
    // per step as the data does (E|v| = 0.05 per coordinate). The yardstick is the same model
    // after a single training step, whose samples are noise over the data's range.
    let untrained = submit(&client, spec("lines", "lines-untrained", 1, 100), "").await.expect("baseline job");
    assert_eq!(final_state(&watch_all(&client, &untrained.id, 0).await), Some(pb::JobState::Succeeded));
    let (curvature, step_size) = line_statistics(&client, "lines-unet").await;
    let (noise_curvature, noise_step) = line_statistics(&client, "lines-untrained").await;
    eprintln!(
        "trained: curvature {curvature}, step {step_size}; untrained: curvature {noise_curvature}, step {noise_step}"
    );
    assert!(curvature < 0.15 * noise_curvature, "samples are not straight: {curvature} vs {noise_curvature} untrained");
    assert!(step_size < 0.15 * noise_step && step_size < 0.15, "samples move too far per step: {step_size}");

    let got = client.jobs().get_job(pb::GetJobRequest { id: "train-lines".into() }).await.expect("get").into_inner();
    assert_eq!((got.state(), got.step, got.total_steps), (pb::JobState::Succeeded, 1500, 1500));
    let err = client.jobs().cancel_job(pb::CancelJobRequest { id: "train-lines".into() }).await.expect_err("finished");
    assert_eq!(err.code(), Code::FailedPrecondition);
    // A finished job's output name is taken now.
    let err = submit(&client, spec("lines", "lines-unet", 10, 100), "").await.expect_err("name taken");
    assert_eq!(err.code(), Code::AlreadyExists);
}

/// Samples 64 trajectories and returns (mean |obs_{k+1} - 2 obs_k + obs_{k-1}|, mean |obs_{k+1} - obs_k|).
async fn line_statistics(client: &Client, model: &str) -> (f64, f64) {
    let req = pb::SampleRequest { model: model.into(), n: 64, seed: Some(3), ..Default::default() };
    let mut stream = client.rewards().sample(req).await.expect("sample").into_inner();
    let (mut curv, mut step, mut n_curv, mut n_step) = (0f64, 0f64, 0usize, 0usize);
    let mut count = 0;
    while let Some(item) = stream.next().await {
        let item = item.expect("sample item");
        let x = item.x.expect("x");
        assert_eq!(x.shape, vec![8, 4], "[horizon, action_dim + obs_dim]");
        let v = relreward_client::tensor::decode_finite_f32(&x).expect("finite");
        let obs = |k: usize, j: usize| f64::from(v[k * 4 + 2 + j]);
        for j in 0..2 {
            for k in 1..8 {
                step += (obs(k, j) - obs(k - 1, j)).abs();
                n_step += 1;
                if k < 7 {
                    curv += (obs(k + 1, j) - 2.0 * obs(k, j) + obs(k - 1, j)).abs();
                    n_curv += 1;
                }
            }
        }
        count += 1;
    }
    assert_eq!(count, 64);
    (curv / n_curv as f64, step / n_step as f64)
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_specs_are_refused_and_cancel_stops_a_running_job() {
    let server = TestServer::start();
    let client = server.client().await;
    upload_lines(&client, "lines", &LINES).await;

    let err = submit(&client, spec("nope", "m", 10, 10), "").await.expect_err("unknown dataset");
    assert_eq!(err.code(), Code::NotFound);
    assert!(err.message().contains("spec.diffusion.dataset"), "{}", err.message());
    let mut long_horizon = spec("lines", "m", 10, 10);
    if let Some(pb::job_spec::Kind::Diffusion(d)) = long_horizon.kind.as_mut() {
        d.horizon = Some(32);
    }
    let err = submit(&client, long_horizon, "").await.expect_err("horizon");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("32") && err.message().contains("longest episode (24)"), "{}", err.message());
    let mut odd = spec("lines", "m", 10, 10);
    if let Some(pb::job_spec::Kind::Diffusion(d)) = odd.kind.as_mut() {
        d.horizon = Some(7);
    }
    let err = submit(&client, odd, "").await.expect_err("divisibility");
    assert_eq!(err.code(), Code::InvalidArgument);
    let err = submit(&client, spec("lines", "Bad Name", 10, 10), "").await.expect_err("name");
    assert_eq!(err.code(), Code::InvalidArgument);
    let err = submit(&client, spec("lines", "m", 0, 10), "").await.expect_err("steps");
    assert!(err.message().contains("spec.optimization.steps"), "{}", err.message());
    let err = client.jobs().get_job(pb::GetJobRequest { id: "missing".into() }).await.expect_err("missing");
    assert_eq!(err.code(), Code::NotFound);

    let job = submit(&client, spec("lines", "long", 1_000_000, 1000), "long").await.expect("submit");
    // Wait until it runs, then cancel: it stops at its next step.
    let mut stream = client
        .jobs()
        .watch_job(pb::WatchJobRequest { id: job.id.clone(), from_seq: 0 })
        .await
        .expect("watch")
        .into_inner();
    while let Some(e) = stream.next().await {
        if matches!(e.expect("event").event, Some(Event::Progress(_))) {
            break;
        }
    }
    // Its dataset cannot be deleted while it runs (it is re-read if the job resumes).
    let err = client.delete_dataset("lines").await.expect_err("in use");
    assert!(err.to_string().starts_with("FAILED_PRECONDITION") && err.to_string().contains("job 'long'"), "{err}");
    let cancelled =
        client.jobs().cancel_job(pb::CancelJobRequest { id: "long".into() }).await.expect("cancel").into_inner();
    assert_eq!(cancelled.state(), pb::JobState::Cancelled);
    let rest: Vec<_> = stream.collect::<Vec<_>>().await;
    assert!(
        matches!(rest.last(), Some(Ok(pb::JobEvent { event: Some(Event::State(s)), .. })) if s.state() == pb::JobState::Cancelled)
    );
    assert!(
        client.models().get_model(pb::GetModelRequest { name: "long".into() }).await.is_err(),
        "no model registered"
    );
    client.delete_dataset("lines").await.expect("deletable once the job has ended");
}

#[tokio::test(flavor = "multi_thread")]
async fn kill_9_during_a_running_job_resumes_from_its_checkpoint() {
    let mut server = TestServer::start();
    let client = server.client().await;
    upload_lines(&client, "lines", &LINES).await;
    submit(&client, spec("lines", "resumed", 600, 50), "crash").await.expect("submit");

    // Let it pass at least two checkpoints, then kill the server without warning.
    let checkpoint = wait_for_checkpoint(&client, "crash", 100).await;
    server.kill();
    server.restart();
    let client = server.client().await;

    let events = watch_all(&client, "crash", 0).await;
    assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "{events:?}");
    // After the restart the job resumed at its checkpoint and its step counter continued.
    let resumed = events
        .iter()
        .position(|e| matches!(&e.event, Some(Event::State(s)) if s.message.starts_with("resumed at step")))
        .expect("a resume event");
    let Some(Event::State(s)) = &events[resumed].event else { unreachable!() };
    let at: u64 =
        s.message["resumed at step ".len()..].split_whitespace().next().and_then(|n| n.parse().ok()).expect("step");
    assert!(at >= checkpoint, "resumed at {at}, last checkpoint seen {checkpoint}");
    let after = progress(&events[resumed..]);
    assert!(after.iter().all(|p| p.step > at), "no step repeated before the checkpoint");
    assert_eq!(after.last().map(|p| p.step), Some(600));
    let job = client.jobs().get_job(pb::GetJobRequest { id: "crash".into() }).await.expect("get").into_inner();
    assert_eq!((job.state(), job.step), (pb::JobState::Succeeded, 600));
}

/// Steps checked on the device (`engine.step_checks = "device"`, CUDA's default: Adam's skip
/// and clip decided there, the losses read where progress is reported) train a diffusion model
/// (autograd's loss) to the same weights, with the same progress, as the host's checks; and a
/// kill -9 in the middle of the device's run resumes with its step count restored from the
/// checkpoint (read off the device when written) and still ends at the same weights.
#[tokio::test(flavor = "multi_thread")]
async fn steps_checked_on_the_device_train_alike_across_a_kill_9() {
    let mut outcomes = Vec::new();
    for checks in ["host", "device"] {
        let mut server = TestServer::start_with_env(&[("RELREWARD__ENGINE__STEP_CHECKS", checks)]);
        let mut client = server.client().await;
        upload_lines(&client, "lines", &LINES).await;
        let mut clipped = spec("lines", "alike", 300, 50);
        if let Some(o) = clipped.optimization.as_mut() {
            o.grad_clip = Some(0.5);
        }
        submit(&client, clipped, "alike").await.expect("submit");
        if checks == "device" {
            wait_for_checkpoint(&client, "alike", 100).await;
            server.kill();
            server.restart();
            client = server.client().await;
        }
        let events = watch_all(&client, "alike", 0).await;
        assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "{checks}: {events:?}");
        if checks == "device" {
            assert!(
                events
                    .iter()
                    .any(|e| matches!(&e.event, Some(Event::State(s)) if s.message.starts_with("resumed at step"))),
                "the device's run was not resumed"
            );
        }
        let lines: std::collections::BTreeSet<String> = progress(&events)
            .iter()
            .map(|p| format!("{} {:e} {:e} {:?}", p.step, p.loss, p.grad_norm, p.eval_loss))
            .collect();
        let model = client.models().get_model(pb::GetModelRequest { name: "alike".into() }).await.expect("model");
        let on_device = format!("step_checks_on_device={}", checks == "device");
        assert!(server.log().contains(&on_device), "{checks}: no '{on_device}' in the log");
        outcomes.push((lines, model.into_inner().sha256));
    }
    let ((host_lines, host_sha), (device_lines, device_sha)) = (&outcomes[0], &outcomes[1]);
    assert_eq!(host_sha, device_sha, "the weights differ");
    // The steps between the checkpoint and the kill are reported twice on the device, alike.
    assert_eq!(host_lines, device_lines);
    assert!(host_lines.len() >= 30, "{host_lines:?}");
}

//! Training jobs from the operations: submit a spec and wait for the job on the client's
//! `follow_job` watch (events streamed, reconnects survived), not by polling. Each event goes
//! to the caller's [`Progress`], so a terminal shows the same lines `train --watch` shows.

use anyhow::{Result, bail};
use relreward_client::retry::RetryPolicy;
use relreward_client::{Client, pb};

use super::Progress;
use crate::output::state_name;

/// Follows job `id` from event `from_seq` until it finishes: `Ok` if it succeeded, an error
/// with its state and message if it failed or was cancelled.
pub async fn wait(progress: &dyn Progress, client: &Client, id: &str, from_seq: u64) -> Result<()> {
    let outcome = client.follow_job(id, from_seq, RetryPolicy::default(), |notice| progress.job_notice(notice)).await;
    progress.job_done();
    let outcome = outcome?;
    if outcome.state != pb::JobState::Succeeded {
        let state = state_name(outcome.state).to_ascii_uppercase();
        if outcome.message.is_empty() {
            bail!("job {id} {state}");
        }
        bail!("job {id} {state}: {}", outcome.message);
    }
    Ok(())
}

/// Submits `spec` as job `job_id` and waits for it (see [`wait`]).
pub async fn train_and_wait(progress: &dyn Progress, client: &Client, spec: pb::JobSpec, job_id: &str) -> Result<()> {
    let job = client.submit_job(spec, Some(job_id)).await?;
    progress.submitted(&job);
    wait(progress, client, &job.id, 0).await
}

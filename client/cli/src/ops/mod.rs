//! The operations behind the `relreward` commands, as library functions with typed inputs and
//! typed results: nothing here parses a flag or prints a report (the commands in the binary's
//! `commands/` do both), so tests and other programs can call "evaluate this reward" or
//! "extract rewards from these recordings" directly. Progress (stages, bars, a job's events)
//! goes to a [`Progress`] the caller provides.
//!
//! Module map (imports point down this list, never up):
//! - [`extract`]: recordings to rewards: sizes from the data, upload or reuse, a base and one
//!   expert diffusion model per expert under one normalizer, the rewards (and discriminators),
//!   their evaluation, and `report.md` / `report.json`; `demo` runs it on generated data.
//! - [`steer`]: the demo's steering: guided vs unguided sampling, final states near a goal.
//! - [`evaluate`]: the paper's evaluation of one reward over local files: discriminability,
//!   the maze heatmap with goal recovery (over base sub-trajectories, or at rest), and a job's
//!   loss curve with reward histograms.
//! - [`jobs`]: submit a training job and wait for it on the client's `follow_job` watch.
//! - [`datasets`]: a recordings file opened as an upload (npz, npy, D4RL HDF5, Minari), sent,
//!   or reused by name.
//! - [`relabel`]: a trajectory archive's rewards replaced by a reward model's (offline RL).
//! - [`scoring`]: the toolkit's `Scorer` over the server's `Score`, checked answers, and
//!   server errors labelled with the flag behind the field they name.
//! - [`items`]: local files read as a reward model's items (arrays, or trajectory windows).
//! - [`latents`]: an `.npz` of images encoded into latents, or of latents decoded into images,
//!   through an autoencoder model (Encode, Decode), in batches under the message limits.

pub mod datasets;
pub mod evaluate;
pub mod extract;
pub mod items;
pub mod jobs;
pub mod latents;
pub mod relabel;
pub mod scoring;
pub mod steer;

use relreward_client::pb;
use relreward_client::watch::WatchNotice;

/// Where an operation reports how it is getting on. Every method but [`Progress::quiet`] has a
/// silent default.
pub trait Progress {
    /// No progress bars and no advisory notes (`--json`, or an operation run inside another).
    fn quiet(&self) -> bool;
    /// A stage of a long operation begins.
    fn stage(&self, _text: &str) {}
    /// A training job was submitted and will be waited for.
    fn submitted(&self, _job: &pb::Job) {}
    /// An event of a job being waited for, or a lost and regained connection.
    fn job_notice(&self, _notice: WatchNotice<'_>) {}
    /// The job being waited for has ended (or the wait failed).
    fn job_done(&self) {}
}

/// Progress nobody sees.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {
    fn quiet(&self) -> bool {
        true
    }
}

//! The `--config` file of `train`: the job spec's request form, defined once in the shared
//! schema (`relreward_proto::schema::job::request`, whose module documentation shows the file)
//! with the value kinds that flags and file share ([`Target`], [`EvalPoint`], [`ArchKind`]).

pub use relreward_proto::schema::job::request::{
    Algorithm, ArchKind, DiffusionConfig, DiscriminatorConfig, OptimizationConfig, RewardConfig, TrainConfig,
};
pub use relreward_proto::schema::job::{EvalPoint, RewardArchitecture, Target};
// The denoiser of a diffusion job: the same built-in architectures a native manifest names.
pub use relreward_proto::schema::manifest::Architecture;

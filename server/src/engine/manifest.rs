//! The diffusion model manifest: the contract between a model's weights and the service's math
//! (parametrization, schedule, T, data layout, normalizer, and for native models the
//! architecture). Its types, defaults and checks are the shared schema's
//! (`relreward_proto::schema::manifest`, one definition for the server, the CLI and the Python
//! package's tests); the engine adds what needs libtorch: the schedule's arithmetic
//! (`schedule.rs`) and the normalizer's on tensors (`normalizer.rs`). A bring-your-own
//! reward's upload manifest ([`RewardUploadManifest`]) is the shared schema's too.

pub use relreward_proto::schema::manifest::{
    Architecture, Conditioning, DiffusionManifest, MAX_TIMESTEPS, Parametrization, RewardSignature,
    RewardUploadManifest, ScheduleSpec, Space,
};

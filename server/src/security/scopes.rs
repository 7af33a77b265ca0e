//! Scopes and the one table saying which scope each gRPC method needs.
//!
//! The scopes are ordered: `admin` includes `train`, which includes `read`. A token that may
//! change data (upload a dataset, start a job) has no use without reading the results, and an
//! operator's token should not need three entries; so a token's power is the highest scope it
//! lists. The table is keyed by the HTTP/2 path of the method (`/package.Service/Method`);
//! a path that is not in it is denied to every token (fail closed), and a unit test checks
//! that every method of every service the server registers is in it, and nothing else.

use std::collections::HashMap;
use std::fmt;
use std::sync::OnceLock;

/// What a token may do. Ordered: a higher scope includes every lower one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Scope {
    /// Query: Score, Gradient, GradientStream, Sample, Encode, Decode, the OIP endpoint,
    /// Get/List/Watch.
    Read,
    /// Change data and use compute: dataset upload and delete, job submit and cancel.
    Train,
    /// Run code and remove models: TorchScript upload, model delete, anything else.
    Admin,
}

impl Scope {
    pub const ALL: [Scope; 3] = [Scope::Read, Scope::Train, Scope::Admin];

    pub fn as_str(self) -> &'static str {
        match self {
            Scope::Read => "read",
            Scope::Train => "train",
            Scope::Admin => "admin",
        }
    }

    pub fn parse(text: &str) -> Option<Scope> {
        Scope::ALL.into_iter().find(|s| s.as_str() == text)
    }
}

impl fmt::Display for Scope {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What calling a method requires.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// No credentials: `grpc.health.v1`, so load balancers and Kubernetes probes (which carry
    /// no token) can check the server. It reveals only SERVING / NOT_SERVING.
    Open,
    /// A valid token with at least this scope.
    Needs(Scope),
}

use Access::{Needs, Open};
use Scope::{Admin, Read, Train};

/// Every method the server serves and what it requires. Server reflection needs `read`: the
/// schema is public (the .proto files), but an anonymous caller has no use for it and
/// should learn nothing beyond health.
pub const METHOD_ACCESS: &[(&str, Access)] = &[
    ("/relreward.v1.DatasetService/UploadDataset", Needs(Train)),
    ("/relreward.v1.DatasetService/GetDataset", Needs(Read)),
    ("/relreward.v1.DatasetService/ListDatasets", Needs(Read)),
    ("/relreward.v1.DatasetService/DeleteDataset", Needs(Train)),
    // UploadModel takes TorchScript, which is code run inside the server, and native weights,
    // which replace what planners are served: both registered by operators.
    ("/relreward.v1.ModelService/UploadModel", Needs(Admin)),
    ("/relreward.v1.ModelService/GetModel", Needs(Read)),
    ("/relreward.v1.ModelService/ListModels", Needs(Read)),
    // A model's weights are what Score and Gradient already answer from: reading them is a read.
    ("/relreward.v1.ModelService/DownloadModel", Needs(Read)),
    // Models are the product of training jobs and the input of serving: removing one can
    // take a trained reward away from every planner that uses it.
    ("/relreward.v1.ModelService/DeleteModel", Needs(Admin)),
    // A recipe is data over a stored model (no weights, no code), as a job's spec is.
    ("/relreward.v1.ModelService/CreateRecipe", Needs(Train)),
    ("/relreward.v1.JobService/SubmitJob", Needs(Train)),
    ("/relreward.v1.JobService/GetJob", Needs(Read)),
    ("/relreward.v1.JobService/ListJobs", Needs(Read)),
    ("/relreward.v1.JobService/CancelJob", Needs(Train)),
    ("/relreward.v1.JobService/WatchJob", Needs(Read)),
    ("/relreward.v1.RewardService/Score", Needs(Read)),
    ("/relreward.v1.RewardService/Gradient", Needs(Read)),
    ("/relreward.v1.RewardService/GradientStream", Needs(Read)),
    ("/relreward.v1.RewardService/Sample", Needs(Read)),
    // Inference through an autoencoder, like Score: a query.
    ("/relreward.v1.RewardService/Encode", Needs(Read)),
    ("/relreward.v1.RewardService/Decode", Needs(Read)),
    // The Open Inference Protocol, liveness and readiness included: Triton clients send the
    // same headers on every call, and probes use grpc.health.v1.
    ("/inference.GRPCInferenceService/ServerLive", Needs(Read)),
    ("/inference.GRPCInferenceService/ServerReady", Needs(Read)),
    ("/inference.GRPCInferenceService/ModelReady", Needs(Read)),
    ("/inference.GRPCInferenceService/ServerMetadata", Needs(Read)),
    ("/inference.GRPCInferenceService/ModelMetadata", Needs(Read)),
    ("/inference.GRPCInferenceService/ModelInfer", Needs(Read)),
    ("/inference.GRPCInferenceService/ModelConfig", Needs(Read)),
    ("/inference.GRPCInferenceService/ModelStatistics", Needs(Read)),
    ("/inference.GRPCInferenceService/RepositoryIndex", Needs(Read)),
    ("/grpc.health.v1.Health/Check", Open),
    ("/grpc.health.v1.Health/Watch", Open),
    ("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo", Needs(Read)),
    ("/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", Needs(Read)),
];

/// What `path` requires; `None` for a path not in [`METHOD_ACCESS`] (denied).
pub fn access(path: &str) -> Option<Access> {
    static TABLE: OnceLock<HashMap<&'static str, Access>> = OnceLock::new();
    TABLE.get_or_init(|| METHOD_ACCESS.iter().copied().collect()).get(path).copied()
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use prost::Message as _;

    use super::*;

    // The descriptor sets of every service the server registers: the same list that names
    // the metrics' method labels, so the two cannot drift apart.
    use crate::metrics::DESCRIPTOR_SETS;

    fn served_methods() -> BTreeSet<String> {
        let mut paths = BTreeSet::new();
        for encoded in DESCRIPTOR_SETS {
            let set = prost_types::FileDescriptorSet::decode(*encoded).expect("descriptor set");
            for file in &set.file {
                for service in &file.service {
                    for method in &service.method {
                        paths.insert(format!("/{}.{}/{}", file.package(), service.name(), method.name()));
                    }
                }
            }
        }
        paths
    }

    #[test]
    fn every_served_method_is_in_the_table_and_nothing_else() {
        let served = served_methods();
        assert!(served.len() >= 25, "descriptor sets look incomplete: {served:?}");
        let table: BTreeSet<String> = METHOD_ACCESS.iter().map(|(p, _)| (*p).to_owned()).collect();
        assert_eq!(table.len(), METHOD_ACCESS.len(), "a method is listed twice");
        let missing: Vec<_> = served.difference(&table).collect();
        assert!(missing.is_empty(), "methods with no access rule (they would be denied to everyone): {missing:?}");
        let stale: Vec<_> = table.difference(&served).collect();
        assert!(stale.is_empty(), "access rules for methods no service declares: {stale:?}");
    }

    #[test]
    fn the_documented_rules() {
        let needs = |p: &str| match access(p) {
            Some(Needs(s)) => Some(s),
            _ => None,
        };
        assert_eq!(needs("/relreward.v1.RewardService/Score"), Some(Read));
        assert_eq!(needs("/relreward.v1.RewardService/GradientStream"), Some(Read));
        assert_eq!(needs("/inference.GRPCInferenceService/ModelInfer"), Some(Read));
        assert_eq!(needs("/relreward.v1.JobService/WatchJob"), Some(Read));
        assert_eq!(needs("/relreward.v1.ModelService/DownloadModel"), Some(Read));
        assert_eq!(needs("/relreward.v1.DatasetService/UploadDataset"), Some(Train));
        assert_eq!(needs("/relreward.v1.DatasetService/DeleteDataset"), Some(Train));
        assert_eq!(needs("/relreward.v1.JobService/SubmitJob"), Some(Train));
        assert_eq!(needs("/relreward.v1.JobService/CancelJob"), Some(Train));
        assert_eq!(needs("/relreward.v1.ModelService/UploadModel"), Some(Admin));
        assert_eq!(needs("/relreward.v1.ModelService/DeleteModel"), Some(Admin));
        assert_eq!(access("/grpc.health.v1.Health/Check"), Some(Open));
        // Only health is open.
        let open: Vec<_> = METHOD_ACCESS.iter().filter(|(_, a)| *a == Open).map(|(p, _)| *p).collect();
        assert!(open.iter().all(|p| p.starts_with("/grpc.health.v1.Health/")), "{open:?}");
        for unknown in ["/relreward.v1.RewardService/Nope", "/relreward.v1.RewardService/score", "", "/"] {
            assert_eq!(access(unknown), None, "{unknown}");
        }
    }

    /// No request field is a URL or URI: the server never fetches anything on a caller's
    /// behalf (the TorchServe "ShellTorch" lesson); models and data arrive as bytes.
    #[test]
    fn no_request_carries_a_url() {
        let mut suspicious = Vec::new();
        for encoded in &DESCRIPTOR_SETS[..2] {
            let set = prost_types::FileDescriptorSet::decode(*encoded).expect("descriptor set");
            for file in &set.file {
                let mut messages: Vec<(String, &prost_types::DescriptorProto)> =
                    file.message_type.iter().map(|m| (m.name().to_owned(), m)).collect();
                while let Some((path, message)) = messages.pop() {
                    for field in &message.field {
                        let name = field.name().to_ascii_lowercase();
                        if name.contains("url") || name.contains("uri") || name.contains("href") {
                            suspicious.push(format!("{}.{path}.{}", file.package(), field.name()));
                        }
                    }
                    messages.extend(message.nested_type.iter().map(|n| (format!("{path}.{}", n.name()), n)));
                }
            }
        }
        assert!(suspicious.is_empty(), "fields that look like URLs: {suspicious:?}");
    }

    #[test]
    fn scopes_are_ordered_and_round_trip() {
        assert!(Read < Train && Train < Admin);
        for s in Scope::ALL {
            assert_eq!(Scope::parse(s.as_str()), Some(s));
        }
        assert_eq!(Scope::parse("Admin"), None);
        assert_eq!(Scope::parse("write"), None);
    }
}

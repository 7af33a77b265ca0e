//! The relreward v1 gRPC contract, and the Open Inference Protocol subset the server speaks.
//!
//! - [`v1`]: messages, service traits (servers) and clients generated from
//!   `proto/relreward/v1/*.proto` (package `relreward.v1`).
//! - [`inference`]: the KServe Open Inference Protocol v2 / Triton gRPC API generated from
//!   `proto/inference/grpc_service.proto` (package `inference`, service
//!   `GRPCInferenceService`), wire-compatible with `tritonclient.grpc`.
//! - [`FILE_DESCRIPTOR_SET`], [`INFERENCE_FILE_DESCRIPTOR_SET`]: the encoded descriptors of
//!   each package, for server reflection.
//!
//! - [`tensor`]: the codec of `relreward.v1.Tensor` (dtype names and sizes, byte lengths,
//!   little-endian encode/decode). It is part of the wire contract: the server validates with
//!   it what the client encodes with it, so it lives here and neither end depends on the other.
//! - [`upload`]: [`upload::UploadSource`], where a dataset upload's array bytes come from (the
//!   toolkit's file readers produce one, the client sends one), and [`upload::MemorySource`].
//! - [`schema`]: the diffusion manifest and the job spec, defined once: their file, stored and
//!   wire forms, their defaults and their checks (no tch; the server and the CLI both use it).
//! - [`error_chain`]: an error with its causes, for messages at both ends.
//! - [`given_number`]: a number a user gave, echoed in a message, at both ends.
//!
//! Everything else about a message (the server's checks of the other messages' fields, the
//! client's helpers) lives with its users.

pub mod schema;
pub mod tensor;
pub mod upload;

/// Package `relreward.v1`.
pub mod v1 {
    #![allow(clippy::all, clippy::pedantic, missing_docs)]
    tonic::include_proto!("relreward.v1");
}

/// Package `inference`: the KServe Open Inference Protocol v2 (Triton's `GRPCInferenceService`).
pub mod inference {
    #![allow(clippy::all, clippy::pedantic, missing_docs)]
    tonic::include_proto!("inference");
}

/// Encoded `FileDescriptorSet` of every relreward.v1 file, for `tonic-reflection`.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("relreward_v1_descriptor");

/// Encoded `FileDescriptorSet` of the `inference` package, for `tonic-reflection`.
pub const INFERENCE_FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("inference_descriptor");

/// An error and its causes, `: `-separated: libraries such as tonic and tokio-postgres keep the
/// reason ("invalid peer certificate", "connection refused") in the source, not the message.
/// Both ends use it (the client's connection errors, the server's TLS and PostgreSQL
/// messages); it lives here, the one crate both depend on, so the server needs no client.
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        let more = cause.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        source = cause.source();
    }
    text
}

/// A number a user gave, echoed in a message: exact (the shortest round-trip form) and compact
/// at any magnitude (scientific outside [1e-4, 1e6): 1e308 as `1e308`, not 309 digits). The
/// server's refusals and the CLI's checks of the same fields word numbers the same way.
pub fn given_number(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e6).contains(&v.abs()) { format!("{v}") } else { format!("{v:e}") }
}

#[cfg(test)]
mod tests {
    use super::given_number;

    #[test]
    fn given_numbers_are_exact_and_compact() {
        assert_eq!(given_number(1e308), "1e308");
        assert_eq!(given_number(-2.5e-9), "-2.5e-9");
        assert_eq!(given_number(0.25), "0.25");
        assert_eq!(given_number(0.0), "0");
        assert!(given_number(-f64::MAX).len() < 30);
    }
}

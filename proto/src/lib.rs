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
//! This crate holds the contract and its generated code only; conversions live with their
//! users (the client's tensor codec, the server's `api` layer).

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

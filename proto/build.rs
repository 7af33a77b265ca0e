//! Generates the Rust code for `relreward.v1` and for `inference` (the KServe Open Inference
//! Protocol v2 / Triton gRPC subset the server also speaks), with one file descriptor set per
//! package for server reflection.
//!
//! protoc comes from the `protoc-bin-vendored` crate, so building needs no system package.

use std::path::{Path, PathBuf};

const PROTOS: &[&str] = &[
    "relreward/v1/tensor.proto",
    "relreward/v1/autoencoder.proto",
    "relreward/v1/datasets.proto",
    "relreward/v1/models.proto",
    "relreward/v1/jobs.proto",
    "relreward/v1/reward.proto",
];

const INFERENCE_PROTOS: &[&str] = &["inference/grpc_service.proto"];

fn compile(out: &Path, descriptor: &str, protos: &[&str], bytes: &[&str]) -> Result<(), Box<dyn std::error::Error>> {
    for p in protos {
        println!("cargo:rerun-if-changed={p}");
    }
    let mut config = prost_build::Config::new();
    config.protoc_executable(protoc_bin_vendored::protoc_bin_path()?).bytes(bytes);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out.join(descriptor))
        .emit_rerun_if_changed(false)
        .compile_with_config(config, protos, &["."])?;
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    compile(&out, "relreward_v1_descriptor.bin", PROTOS, &[])?;
    // Raw tensor payloads as `Bytes`: decoded without a copy per input.
    compile(
        &out,
        "inference_descriptor.bin",
        INFERENCE_PROTOS,
        &[".inference.ModelInferRequest.raw_input_contents", ".inference.ModelInferResponse.raw_output_contents"],
    )?;
    Ok(())
}

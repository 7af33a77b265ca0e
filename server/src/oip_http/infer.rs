//! The infer body of the OIP over HTTP: KServe v2 JSON tensors (`data`, flat or nested) and the
//! binary tensor extension (`Inference-Header-Content-Length`, `binary_data_size`,
//! `binary_data`, `binary_data_output`) turned into the gRPC `ModelInferRequest` (every input's
//! data as raw contents, so that [`crate::api::oip::Inference`] checks it as it checks gRPC's),
//! and its answer back into JSON, or JSON followed by binary outputs.

use std::time::Duration;

use bytes::Bytes;
use http::{HeaderMap, HeaderValue, StatusCode};
use relreward_proto::inference::{
    self as pb, InferParameter, infer_parameter::ParameterChoice, model_infer_request::InferInputTensor,
    model_infer_request::InferRequestedOutputTensor,
};
use relreward_proto::tensor;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::Reply;
use crate::error::{Error, brief, quote};

/// The header of the binary tensor extension: the JSON part's length in bytes.
const HEADER_LENGTH: &str = "inference-header-content-length";

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InferRequestJson {
    #[serde(default)]
    id: String,
    #[serde(default)]
    parameters: Map<String, Value>,
    inputs: Vec<InputJson>,
    #[serde(default)]
    outputs: Vec<OutputJson>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InputJson {
    name: String,
    shape: Vec<i64>,
    datatype: String,
    #[serde(default)]
    parameters: Map<String, Value>,
    #[serde(default)]
    data: Option<Value>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OutputJson {
    name: String,
    #[serde(default)]
    parameters: Map<String, Value>,
}

/// The request's `timeout` parameter (microseconds, as Triton's HTTP API takes it).
pub(super) fn request_timeout(request: &pb::ModelInferRequest) -> crate::error::Result<Option<Duration>> {
    match request.parameters.get("timeout").and_then(|p| p.parameter_choice.as_ref()) {
        None => Ok(None),
        Some(ParameterChoice::Int64Param(us)) if *us > 0 => Ok(Some(Duration::from_micros(*us as u64))),
        Some(ParameterChoice::Uint64Param(us)) if *us > 0 => Ok(Some(Duration::from_micros(*us))),
        Some(other) => Err(Error::invalid(format!(
            "parameters.timeout: expected a positive integer of microseconds, got {}",
            brief(other)
        ))),
    }
}

/// A JSON parameter as the gRPC request carries it.
fn parameter(field: &str, value: &Value) -> crate::error::Result<InferParameter> {
    let choice = match value {
        Value::Bool(b) => ParameterChoice::BoolParam(*b),
        Value::String(s) => ParameterChoice::StringParam(s.clone()),
        Value::Number(n) => match (n.as_i64(), n.as_u64(), n.as_f64()) {
            (Some(i), _, _) => ParameterChoice::Int64Param(i),
            (None, Some(u), _) => ParameterChoice::Uint64Param(u),
            (None, None, Some(f)) => ParameterChoice::DoubleParam(f),
            _ => return Err(Error::invalid(format!("{field}: not a number a parameter can hold"))),
        },
        _ => return Err(Error::invalid(format!("{field}: a parameter is a bool, a number or a string"))),
    };
    Ok(InferParameter { parameter_choice: Some(choice) })
}

/// The parameters the gRPC request carries, without the REST-only keys in `skip`.
fn parameters(
    what: &str,
    map: &Map<String, Value>,
    skip: &[&str],
) -> crate::error::Result<std::collections::HashMap<String, InferParameter>> {
    map.iter()
        .filter(|(k, _)| !skip.contains(&k.as_str()))
        .map(|(k, v)| Ok((k.clone(), parameter(&format!("{what}.parameters.{k}"), v)?)))
        .collect()
}

/// The bytes per element of the datatypes reward models take (others are refused by name in
/// [`Inference::infer`], whose checks come before any count).
fn element_bytes(datatype: &str) -> Option<usize> {
    match datatype {
        "FP32" => Some(4),
        "INT64" => Some(8),
        _ => None,
    }
}

/// `data` flattened in row-major order (nested arrays or already flat) into little-endian
/// bytes of `datatype`.
fn encode_data(name: &str, datatype: &str, data: &Value) -> crate::error::Result<(usize, Vec<u8>)> {
    fn walk<'a>(v: &'a Value, out: &mut Vec<&'a Value>) {
        match v {
            Value::Array(items) => items.iter().for_each(|i| walk(i, out)),
            other => out.push(other),
        }
    }
    let mut flat = Vec::new();
    walk(data, &mut flat);
    let mut bytes = Vec::with_capacity(flat.len() * element_bytes(datatype).unwrap_or(0));
    for (i, v) in flat.iter().enumerate() {
        match datatype {
            "FP32" => {
                let f = v
                    .as_f64()
                    .ok_or_else(|| Error::invalid(format!("{name}: data[{i}] is {}, not a number", json_text(v))))?;
                // Narrowed, it would reach the model's checks as an infinity the client never sent.
                if tensor::beyond_f32(f) {
                    return Err(Error::invalid(format!("{name}: data[{i}] ({f:e}) is {}", tensor::OUTSIDE_F32)));
                }
                bytes.extend_from_slice(&(f as f32).to_le_bytes());
            }
            "INT64" => {
                let n = v
                    .as_i64()
                    .ok_or_else(|| Error::invalid(format!("{name}: data[{i}] is {}, not an integer", json_text(v))))?;
                bytes.extend_from_slice(&n.to_le_bytes());
            }
            _ => {}
        }
    }
    Ok((flat.len(), bytes))
}

/// The ModelInferRequest a REST infer body stands for (every input's data as raw contents),
/// and for each output the gRPC answer will carry (in request order; all when none is named)
/// whether it goes back as binary.
pub(super) fn infer_request(
    name: String,
    version: String,
    headers: &HeaderMap,
    body: &[u8],
) -> crate::error::Result<(pb::ModelInferRequest, Vec<(String, bool)>)> {
    let (json, mut binary) = match headers.get(HEADER_LENGTH) {
        None => (body, &[][..]),
        Some(v) => {
            let n = v.to_str().ok().and_then(|s| s.trim().parse::<usize>().ok()).ok_or_else(|| {
                Error::invalid(format!("Inference-Header-Content-Length: {} is not a byte count", brief(v)))
            })?;
            if n > body.len() {
                return Err(Error::invalid(format!(
                    "Inference-Header-Content-Length: {n} bytes, but the body has {}",
                    body.len()
                )));
            }
            body.split_at(n)
        }
    };
    let parsed: InferRequestJson = serde_json::from_slice(json)
        .map_err(|e| Error::invalid(format!("request body: not a KServe v2 inference request: {e}")))?;
    let mut request = pb::ModelInferRequest {
        model_name: name,
        model_version: version,
        id: parsed.id,
        parameters: parameters("request", &parsed.parameters, &["binary_data_output"])?,
        ..Default::default()
    };
    for input in parsed.inputs {
        let InputJson { name, shape, datatype, parameters: params, data } = input;
        let size = params.get("binary_data_size");
        let raw = match (size, data) {
            (Some(size), None) => {
                let size = size.as_u64().and_then(|s| usize::try_from(s).ok()).ok_or_else(|| {
                    Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {}, not a byte count",
                        json_text(size)
                    ))
                })?;
                if size > binary.len() {
                    return Err(Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {size}, but only {} bytes of binary data are left",
                        binary.len()
                    )));
                }
                let (mine, rest) = binary.split_at(size);
                binary = rest;
                if let (Some(width), Ok(count)) = (element_bytes(&datatype), element_count(&shape))
                    && Some(size) != count.checked_mul(width)
                {
                    return Err(Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {size}, but {datatype} shape {} needs {} bytes",
                        brief(&shape),
                        count.saturating_mul(width)
                    )));
                }
                mine.to_vec()
            }
            (None, Some(data)) => {
                let (values, bytes) = encode_data(&name, &datatype, &data)?;
                if let (Some(_), Ok(count)) = (element_bytes(&datatype), element_count(&shape))
                    && values != count
                {
                    return Err(Error::invalid(format!(
                        "{name}: data holds {values} values but shape {} needs {count}",
                        brief(&shape)
                    )));
                }
                bytes
            }
            (Some(_), Some(_)) => {
                return Err(Error::invalid(format!(
                    "{name}: both data and parameters.binary_data_size are given; send one"
                )));
            }
            (None, None) => {
                return Err(Error::invalid(format!(
                    "{name}: no data; give `data`, or binary data with parameters.binary_data_size"
                )));
            }
        };
        let parameters = parameters(&name, &params, &["binary_data_size"])?;
        request.inputs.push(InferInputTensor { name, datatype, shape, parameters, contents: None });
        request.raw_input_contents.push(Bytes::from(raw));
    }
    if !binary.is_empty() {
        return Err(Error::invalid(format!(
            "request body: {} bytes of binary data that no input's parameters.binary_data_size accounts for",
            binary.len()
        )));
    }
    let all_binary = match parsed.parameters.get("binary_data_output") {
        None => false,
        Some(Value::Bool(b)) => *b,
        Some(other) => {
            return Err(Error::invalid(format!(
                "request.parameters.binary_data_output: expected true or false, got {}",
                json_text(other)
            )));
        }
    };
    let mut binary_outputs = Vec::new();
    for output in parsed.outputs {
        let binary = match output.parameters.get("binary_data") {
            None => all_binary,
            Some(Value::Bool(b)) => *b,
            Some(other) => {
                return Err(Error::invalid(format!(
                    "{}: parameters.binary_data: expected true or false, got {}",
                    output.name,
                    json_text(other)
                )));
            }
        };
        let parameters = parameters(&output.name, &output.parameters, &["binary_data"])?;
        binary_outputs.push((output.name.clone(), binary));
        request.outputs.push(InferRequestedOutputTensor { name: output.name, parameters });
    }
    if binary_outputs.is_empty() {
        // None named: the server's choice of outputs, each in the request's default form.
        binary_outputs.push((String::new(), all_binary));
    }
    Ok((request, binary_outputs))
}

/// A JSON value as the client wrote it, shortened for a message.
fn json_text(v: &Value) -> String {
    quote(&v.to_string()).trim_matches('\'').to_owned()
}

fn element_count(shape: &[i64]) -> Result<usize, ()> {
    shape.iter().try_fold(1usize, |n, &d| usize::try_from(d).ok().and_then(|d| n.checked_mul(d)).ok_or(()))
}

#[derive(Serialize)]
struct OutputTensorJson<'a> {
    name: &'a str,
    datatype: &'a str,
    shape: &'a [i64],
    #[serde(skip_serializing_if = "Option::is_none")]
    parameters: Option<BinarySize>,
    /// FP32 values written as f32 (the shortest text that reads back as the same float).
    #[serde(skip_serializing_if = "Option::is_none")]
    data: Option<Vec<f32>>,
}

#[derive(Serialize)]
struct BinarySize {
    binary_data_size: usize,
}

#[derive(Serialize)]
struct InferResponseJson<'a> {
    model_name: &'a str,
    model_version: &'a str,
    #[serde(skip_serializing_if = "str::is_empty")]
    id: &'a str,
    outputs: Vec<OutputTensorJson<'a>>,
}

/// The REST answer to a gRPC infer response: JSON, or with the binary extension the JSON
/// header followed by the binary outputs in order.
pub(super) fn infer_reply(
    response: pb::ModelInferResponse,
    binary_outputs: &[(String, bool)],
) -> crate::error::Result<Reply> {
    // Named outputs come back in request order; with none named, one default applies to all.
    let is_binary =
        |name: &str| binary_outputs.iter().find(|(n, _)| n == name || n.is_empty()).is_some_and(|(_, binary)| *binary);
    let mut outputs = Vec::with_capacity(response.outputs.len());
    let mut blobs: Vec<&[u8]> = Vec::new();
    for (meta, raw) in response.outputs.iter().zip(&response.raw_output_contents) {
        let (parameters, data) = if is_binary(&meta.name) {
            blobs.push(raw);
            (Some(BinarySize { binary_data_size: raw.len() }), None)
        } else {
            let values = raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            (None, Some(values))
        };
        outputs.push(OutputTensorJson {
            name: &meta.name,
            datatype: &meta.datatype,
            shape: &meta.shape,
            parameters,
            data,
        });
    }
    let header = InferResponseJson {
        model_name: &response.model_name,
        model_version: &response.model_version,
        id: &response.id,
        outputs,
    };
    let mut body = serde_json::to_vec(&header).map_err(|e| Error::internal("infer response", e))?;
    if blobs.is_empty() {
        return Ok(Reply { status: StatusCode::OK, content_type: "application/json", body, headers: Vec::new() });
    }
    let json_length = body.len();
    for blob in blobs {
        body.extend_from_slice(blob);
    }
    let headers = vec![(http::HeaderName::from_static(HEADER_LENGTH), HeaderValue::from(json_length))];
    Ok(Reply { status: StatusCode::OK, content_type: "application/octet-stream", body, headers })
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::oip_http::tests::headers;

    #[test]
    fn json_inputs_become_raw_contents_flat_or_nested() {
        let body = br#"{"id": "7", "inputs": [
            {"name": "x", "shape": [2, 2], "datatype": "FP32", "data": [[0.1, 2], [-3.5, 4e-3]]},
            {"name": "t", "shape": [2], "datatype": "INT64", "data": [1, 9]}],
            "outputs": [{"name": "reward"}], "parameters": {"timeout": 5000}}"#;
        let (req, binary) = infer_request("m".into(), String::new(), &HeaderMap::new(), body).expect("parse");
        assert_eq!(req.id, "7");
        assert_eq!(req.inputs.len(), 2);
        let x: Vec<f32> =
            req.raw_input_contents[0].chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(x, [0.1f32, 2.0, -3.5, 4e-3]);
        let t: Vec<i64> =
            req.raw_input_contents[1].chunks(8).map(|c| i64::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(t, [1, 9]);
        assert_eq!(binary, [("reward".to_owned(), false)]);
        assert_eq!(request_timeout(&req).expect("timeout"), Some(Duration::from_micros(5000)));
    }

    #[test]
    fn binary_inputs_are_split_by_their_sizes() {
        let json = br#"{"inputs": [
            {"name": "x", "shape": [1, 2], "datatype": "FP32", "parameters": {"binary_data_size": 8}},
            {"name": "t", "shape": [1], "datatype": "INT64", "data": [3]}],
            "parameters": {"binary_data_output": true}}"#;
        let mut body = json.to_vec();
        body.extend(1.5f32.to_le_bytes());
        body.extend((-2.0f32).to_le_bytes());
        let h = headers(&[(HEADER_LENGTH, &json.len().to_string())]);
        let (req, binary) = infer_request("m".into(), String::new(), &h, &body).expect("parse");
        assert_eq!(&req.raw_input_contents[0][..], &body[json.len()..]);
        assert_eq!(&req.raw_input_contents[1][..], &3i64.to_le_bytes());
        assert_eq!(binary, [(String::new(), true)]);
        assert!(!req.parameters.contains_key("binary_data_output"));
        assert!(req.inputs[0].parameters.is_empty());

        // Too few bytes, too many, a size that does not fit the shape.
        let err = |body: &[u8], h: &HeaderMap| {
            infer_request("m".into(), String::new(), h, body).expect_err("refused").to_string()
        };
        let e = err(&body[..body.len() - 1], &h);
        assert!(e.starts_with("x: parameters.binary_data_size is 8, but only 7"), "{e}");
        let mut extra = body.clone();
        extra.push(0);
        assert!(err(&extra, &h).contains("1 bytes of binary data that no input"), "{}", err(&extra, &h));
        let wrong = br#"{"inputs": [{"name": "x", "shape": [1, 3], "datatype": "FP32", "parameters": {"binary_data_size": 8}}]}"#;
        let mut body = wrong.to_vec();
        body.extend([0u8; 8]);
        let h = headers(&[(HEADER_LENGTH, &wrong.len().to_string())]);
        assert!(err(&body, &h).contains("FP32 shape [1, 3] needs 12 bytes"), "{}", err(&body, &h));
        let h = headers(&[(HEADER_LENGTH, "999")]);
        assert!(err(&body, &h).starts_with("Inference-Header-Content-Length: 999 bytes"), "{}", err(&body, &h));
    }

    #[test]
    fn malformed_bodies_name_the_field() {
        let err = |body: &str| {
            infer_request("m".into(), String::new(), &HeaderMap::new(), body.as_bytes()).expect_err(body).to_string()
        };
        assert!(err("{}").contains("missing field `inputs`"), "{}", err("{}"));
        assert!(err("not json").starts_with("request body:"));
        let e = err(r#"{"inputs": [], "outptus": []}"#);
        assert!(e.contains("unknown field `outptus`"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [2], "datatype": "FP32", "data": [1, "a"]}]}"#);
        assert!(e.starts_with("x: data[1] is"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [3], "datatype": "FP32", "data": [1, 2]}]}"#);
        assert_eq!(e, "x: data holds 2 values but shape [3] needs 3");
        let e = err(r#"{"inputs": [{"name": "t", "shape": [1], "datatype": "INT64", "data": [1.5]}]}"#);
        assert!(e.starts_with("t: data[0] is 1.5, not an integer"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [1], "datatype": "FP32"}]}"#);
        assert!(e.starts_with("x: no data"), "{e}");
        let e = err(r#"{"inputs": [], "outputs": [{"name": "reward", "parameters": {"binary_data": 1}}]}"#);
        assert!(e.starts_with("reward: parameters.binary_data"), "{e}");
        let e = err(r#"{"inputs": [], "parameters": {"x": null}}"#);
        assert!(e.starts_with("request.parameters.x"), "{e}");
    }

    #[test]
    fn replies_are_json_or_binary_per_output() {
        let response = pb::ModelInferResponse {
            model_name: "m".into(),
            model_version: "1".into(),
            outputs: vec![
                pb::model_infer_response::InferOutputTensor {
                    name: "reward".into(),
                    datatype: "FP32".into(),
                    shape: vec![2],
                    ..Default::default()
                },
                pb::model_infer_response::InferOutputTensor {
                    name: "grad_x".into(),
                    datatype: "FP32".into(),
                    shape: vec![2, 1],
                    ..Default::default()
                },
            ],
            raw_output_contents: vec![
                [0.1f32, -7.25].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
                [1f32, 2.0].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
            ],
            ..Default::default()
        };
        let reply = infer_reply(response.clone(), &[("reward".into(), false), ("grad_x".into(), true)]).expect("reply");
        let n: usize = reply.headers[0].1.to_str().expect("ascii").parse().expect("length");
        let header: Value = serde_json::from_slice(&reply.body[..n]).expect("json");
        assert_eq!(header["outputs"][0]["data"], json!([0.1, -7.25]));
        assert_eq!(header["outputs"][1]["parameters"]["binary_data_size"], 8);
        assert_eq!(&reply.body[n..], &response.raw_output_contents[1][..]);
        assert!(header.get("id").is_none());

        let reply = infer_reply(response, &[(String::new(), false)]).expect("reply");
        assert!(reply.headers.is_empty());
        let all: Value = serde_json::from_slice(&reply.body).expect("json");
        assert_eq!(all["outputs"][1]["data"], json!([1.0, 2.0]));
        assert_eq!(all["outputs"][1]["shape"], json!([2, 1]));
    }
}

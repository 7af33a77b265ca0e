//! gRPC server reflection, v1 and v1alpha, with the protocol's in-stream errors.
//!
//! `tonic-reflection` answers the lookups (its index keeps each file descriptor's original
//! bytes), but it ends the whole stream with a status at the first lookup that fails (an
//! unknown symbol, file or extension). The protocol answers such a request with a
//! `ServerReflectionResponse` carrying `error_response` (NOT_FOUND and a message) and goes on
//! with the next request, which is what grpcurl, grpcui and the gRPC libraries' reflection
//! clients expect. So here each request of a stream is put to an in-process tonic-reflection
//! v1 service on its own one-request stream, and whatever it answers, a response or a status,
//! becomes one response on the client's stream.
//!
//! A file descriptor answer carries, after the files asked for, every file they depend on
//! (transitively) that the stream has not carried yet, as the protocol describes: a client can
//! then build the descriptors from the answers alone (Node's proto-loader, grpc-go's clients);
//! tonic-reflection answers with the asked-for file only.
//!
//! v1alpha is the same protocol under another package name (the messages are wire-identical),
//! so its requests are re-encoded as v1, answered in the one place, and re-encoded back.

use std::collections::HashSet;
use std::pin::Pin;
use std::sync::Arc;

use futures::future::BoxFuture;
use futures::{Stream, StreamExt};
use prost::Message;
use tonic::{Request, Response, Status, Streaming};
use tonic_reflection::pb::v1 as v1pb;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
use tonic_reflection::pb::v1alpha as v1alphapb;

/// Answers one v1 request: always a response, an `error_response` when the lookup failed.
type Answer =
    Arc<dyn Fn(v1pb::ServerReflectionRequest) -> BoxFuture<'static, v1pb::ServerReflectionResponse> + Send + Sync>;

type ResponseStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

/// The v1 and v1alpha reflection services over the given encoded `FileDescriptorSet`s.
pub fn services(
    file_descriptor_sets: &[&'static [u8]],
) -> Result<
    (
        v1pb::server_reflection_server::ServerReflectionServer<V1>,
        v1alphapb::server_reflection_server::ServerReflectionServer<V1Alpha>,
    ),
    tonic_reflection::server::Error,
> {
    let mut builder = tonic_reflection::server::Builder::configure();
    for set in file_descriptor_sets {
        builder = builder.register_encoded_file_descriptor_set(set);
    }
    // The v1alpha descriptor too: the inner service only speaks v1, but clients of either
    // version may ask for either descriptor.
    let builder = builder.register_encoded_file_descriptor_set(tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET);
    let client = ServerReflectionClient::new(builder.build_v1()?);
    let answer: Answer = Arc::new(move |request| {
        let client = client.clone();
        Box::pin(answer(client, request))
    });
    Ok((
        v1pb::server_reflection_server::ServerReflectionServer::new(V1 { answer: answer.clone() }),
        v1alphapb::server_reflection_server::ServerReflectionServer::new(V1Alpha { answer }),
    ))
}

/// Puts `request` to the in-process tonic-reflection service on a stream of its own.
async fn answer<S>(
    mut inner: ServerReflectionClient<S>,
    request: v1pb::ServerReflectionRequest,
) -> v1pb::ServerReflectionResponse
where
    S: tonic::client::GrpcService<tonic::body::Body>,
    S::Error: Into<tonic::codegen::StdError>,
    S::ResponseBody: http_body::Body<Data = bytes::Bytes> + Send + 'static,
    <S::ResponseBody as http_body::Body>::Error: Into<tonic::codegen::StdError> + Send,
{
    // An extension-number query for a type nobody registered is NOT_FOUND (tonic-reflection
    // answers every such query with an empty list, which grpcurl needs for real types); for
    // a known type its answer names the type.
    if let Some(MessageRequest::AllExtensionNumbersOfType(type_name)) = &request.message_request {
        let probe = v1pb::ServerReflectionRequest {
            host: request.host.clone(),
            message_request: Some(MessageRequest::FileContainingSymbol(type_name.clone())),
        };
        if let Err(status) = ask(&mut inner, probe).await {
            return error_response(request, &status);
        }
        return match ask(&mut inner, request.clone()).await {
            Ok(mut response) => {
                if let Some(MessageResponse::AllExtensionNumbersResponse(numbers)) = &mut response.message_response {
                    numbers.base_type_name.clone_from(type_name);
                }
                response
            }
            Err(status) => error_response(request, &status),
        };
    }
    match ask(&mut inner, request.clone()).await {
        Ok(response) => response,
        Err(status) => error_response(request, &status),
    }
}

/// The inner service's one response to `request`, or the status it ended the stream with.
async fn ask<S>(
    inner: &mut ServerReflectionClient<S>,
    request: v1pb::ServerReflectionRequest,
) -> Result<v1pb::ServerReflectionResponse, Status>
where
    S: tonic::client::GrpcService<tonic::body::Body>,
    S::Error: Into<tonic::codegen::StdError>,
    S::ResponseBody: http_body::Body<Data = bytes::Bytes> + Send + 'static,
    <S::ResponseBody as http_body::Body>::Error: Into<tonic::codegen::StdError> + Send,
{
    let mut responses = inner.server_reflection_info(futures::stream::iter([request])).await?.into_inner();
    responses.message().await?.ok_or_else(|| Status::internal("reflection: no answer to the request"))
}

/// The protocol's in-stream error: the request echoed, its status code and message.
fn error_response(request: v1pb::ServerReflectionRequest, status: &Status) -> v1pb::ServerReflectionResponse {
    v1pb::ServerReflectionResponse {
        valid_host: request.host.clone(),
        original_request: Some(request),
        message_response: Some(MessageResponse::ErrorResponse(v1pb::ErrorResponse {
            error_code: status.code() as i32,
            error_message: status.message().to_owned(),
        })),
    }
}

/// One response per request, in order. The stream ends when the client half-closes it, or
/// with the status of a frame that cannot be read.
fn respond<Req, Resp>(inbound: Streaming<Req>, answer: Answer) -> ResponseStream<Resp>
where
    Req: prost::Message + Send + 'static,
    Resp: prost::Message + Default + Send + 'static,
{
    // The names of the files this stream has carried. `then` runs one request at a time, in
    // order, so the lock is never contended; it only makes the state shareable with the future.
    let sent = Arc::new(tokio::sync::Mutex::new(HashSet::new()));
    Box::pin(inbound.then(move |request| {
        let (answer, sent) = (answer.clone(), sent.clone());
        async move {
            let request: v1pb::ServerReflectionRequest = reencode(&request?);
            let host = request.host.clone();
            let response = answer(request).await;
            let response = with_dependencies(&answer, &host, response, &mut *sent.lock().await).await;
            Ok(reencode(&response))
        }
    }))
}

/// `response` with, after the files it carries (always sent: they were asked for), every file
/// they depend on, transitively, that is not in `sent`; every file sent is added to `sent`.
async fn with_dependencies(
    answer: &Answer,
    host: &str,
    mut response: v1pb::ServerReflectionResponse,
    sent: &mut HashSet<String>,
) -> v1pb::ServerReflectionResponse {
    let Some(MessageResponse::FileDescriptorResponse(files)) = &mut response.message_response else {
        return response;
    };
    let mut pending = Vec::new();
    for bytes in &files.file_descriptor_proto {
        let (name, dependencies) = name_and_dependencies(bytes);
        sent.insert(name);
        pending.extend(dependencies);
    }
    while let Some(name) = pending.pop() {
        if !sent.insert(name.clone()) {
            continue;
        }
        let lookup = v1pb::ServerReflectionRequest {
            host: host.to_owned(),
            message_request: Some(MessageRequest::FileByFilename(name)),
        };
        // A dependency the index lacks (it has every file of every registered set) is left
        // out rather than failing an answer that was found.
        if let Some(MessageResponse::FileDescriptorResponse(found)) = answer(lookup).await.message_response {
            for bytes in found.file_descriptor_proto {
                let (name, dependencies) = name_and_dependencies(&bytes);
                sent.insert(name);
                pending.extend(dependencies.into_iter().filter(|d| !sent.contains(d)));
                files.file_descriptor_proto.push(bytes);
            }
        }
    }
    response
}

/// A serialized `FileDescriptorProto`'s name and the names of the files it imports.
fn name_and_dependencies(bytes: &[u8]) -> (String, Vec<String>) {
    // The bytes are tonic-reflection's copies of our own descriptor sets: they decode.
    let file = prost_types::FileDescriptorProto::decode(bytes).unwrap_or_default();
    (file.name.unwrap_or_default(), file.dependency)
}

/// The same message under the other version's package (v1 and v1alpha are wire-identical).
fn reencode<A: prost::Message, B: prost::Message + Default>(message: &A) -> B {
    // Cannot fail: both versions have the same fields with the same numbers and types.
    B::decode(message.encode_to_vec().as_slice()).unwrap_or_default()
}

/// `grpc.reflection.v1.ServerReflection`.
pub struct V1 {
    answer: Answer,
}

#[tonic::async_trait]
impl v1pb::server_reflection_server::ServerReflection for V1 {
    type ServerReflectionInfoStream = ResponseStream<v1pb::ServerReflectionResponse>;

    async fn server_reflection_info(
        &self,
        request: Request<Streaming<v1pb::ServerReflectionRequest>>,
    ) -> Result<Response<Self::ServerReflectionInfoStream>, Status> {
        Ok(Response::new(respond(request.into_inner(), self.answer.clone())))
    }
}

/// `grpc.reflection.v1alpha.ServerReflection`.
pub struct V1Alpha {
    answer: Answer,
}

#[tonic::async_trait]
impl v1alphapb::server_reflection_server::ServerReflection for V1Alpha {
    type ServerReflectionInfoStream = ResponseStream<v1alphapb::ServerReflectionResponse>;

    async fn server_reflection_info(
        &self,
        request: Request<Streaming<v1alphapb::ServerReflectionRequest>>,
    ) -> Result<Response<Self::ServerReflectionInfoStream>, Status> {
        Ok(Response::new(respond(request.into_inner(), self.answer.clone())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(message: MessageRequest) -> v1pb::ServerReflectionRequest {
        v1pb::ServerReflectionRequest { host: "h".into(), message_request: Some(message) }
    }

    async fn answer_of(message: MessageRequest) -> v1pb::ServerReflectionResponse {
        let client = ServerReflectionClient::new(
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(relreward_proto::FILE_DESCRIPTOR_SET)
                .build_v1()
                .expect("reflection"),
        );
        answer(client, request(message)).await
    }

    fn error_code(response: &v1pb::ServerReflectionResponse) -> Option<i32> {
        match &response.message_response {
            Some(MessageResponse::ErrorResponse(e)) => Some(e.error_code),
            _ => None,
        }
    }

    #[tokio::test]
    async fn lookups_that_fail_are_error_responses_echoing_the_request() {
        for message in [
            MessageRequest::FileContainingSymbol("no.such.Symbol".into()),
            MessageRequest::FileByFilename("no/such.proto".into()),
            MessageRequest::FileContainingExtension(v1pb::ExtensionRequest {
                containing_type: "relreward.v1.GradientRequest".into(),
                extension_number: 100,
            }),
            MessageRequest::AllExtensionNumbersOfType("no.such.Type".into()),
        ] {
            let response = answer_of(message.clone()).await;
            assert_eq!(error_code(&response), Some(tonic::Code::NotFound as i32), "{message:?}: {response:?}");
            assert_eq!(response.original_request, Some(request(message)));
            assert_eq!(response.valid_host, "h");
        }
    }

    fn file_names(response: &v1pb::ServerReflectionResponse) -> Vec<String> {
        match &response.message_response {
            Some(MessageResponse::FileDescriptorResponse(f)) => {
                f.file_descriptor_proto.iter().map(|b| name_and_dependencies(b).0).collect()
            }
            other => panic!("{other:?}"),
        }
    }

    #[tokio::test]
    async fn file_answers_carry_the_dependencies_the_stream_has_not_carried() {
        let client = ServerReflectionClient::new(
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(relreward_proto::FILE_DESCRIPTOR_SET)
                .build_v1()
                .expect("reflection"),
        );
        let answer: Answer = Arc::new(move |r| Box::pin(answer(client.clone(), r)));
        let mut sent = HashSet::new();
        let ask = |symbol: &str| request(MessageRequest::FileContainingSymbol(symbol.into()));
        let first = answer(ask("relreward.v1.JobService")).await;
        let first = file_names(&with_dependencies(&answer, "h", first, &mut sent).await);
        assert_eq!(first[0], "relreward/v1/jobs.proto");
        for dep in ["relreward/v1/models.proto", "relreward/v1/tensor.proto", "google/protobuf/timestamp.proto"] {
            assert!(first.contains(&dep.to_owned()), "{dep} in {first:?}");
        }
        let unique: HashSet<_> = first.iter().collect();
        assert_eq!(unique.len(), first.len(), "{first:?}");
        // Asked again, the file comes alone: its dependencies were sent on this stream.
        let again = answer(ask("relreward.v1.RewardService")).await;
        let again = file_names(&with_dependencies(&answer, "h", again, &mut sent).await);
        assert_eq!(again, ["relreward/v1/reward.proto"]);
    }

    #[tokio::test]
    async fn lookups_that_succeed_are_tonic_reflections_answers() {
        let response = answer_of(MessageRequest::FileContainingSymbol("relreward.v1.RewardService".into())).await;
        assert!(
            matches!(&response.message_response, Some(MessageResponse::FileDescriptorResponse(f)) if f.file_descriptor_proto.len() == 1),
            "{response:?}"
        );
        let response =
            answer_of(MessageRequest::AllExtensionNumbersOfType("relreward.v1.GradientRequest".into())).await;
        match &response.message_response {
            Some(MessageResponse::AllExtensionNumbersResponse(n)) => {
                assert_eq!(n.base_type_name, "relreward.v1.GradientRequest");
                assert!(n.extension_number.is_empty());
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn v1alpha_messages_reencode_losslessly() {
        let v1 = request(MessageRequest::FileContainingExtension(v1pb::ExtensionRequest {
            containing_type: "a.B".into(),
            extension_number: 7,
        }));
        let alpha: v1alphapb::ServerReflectionRequest = reencode(&v1);
        let back: v1pb::ServerReflectionRequest = reencode(&alpha);
        assert_eq!(back, v1);
    }
}

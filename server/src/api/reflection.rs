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
//! v1alpha is the same protocol under another package name (the messages are wire-identical),
//! so its requests are re-encoded as v1, answered in the one place, and re-encoded back.

use std::pin::Pin;
use std::sync::Arc;

use futures::future::BoxFuture;
use futures::{Stream, StreamExt};
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
    Box::pin(inbound.then(move |request| {
        let answer = answer.clone();
        async move {
            let request: v1pb::ServerReflectionRequest = reencode(&request?);
            Ok(reencode(&answer(request).await))
        }
    }))
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

//! The classes of wrong answers an outside client battery found (issue 15), one test per
//! class, each with values other than the battery's examples: long values quoted whole in
//! error messages, a bad GradientStream frame ending the stream OK, WatchJob's from_seq
//! wrapping past 2^63, oversized messages answered OUT_OF_RANGE, extreme but finite inputs
//! answered with Inf, and the same kind of field validated differently by different RPCs.
//!
//! Run: `cargo test --release -p relreward-tests --test hardening`.

use std::time::Duration;

use prost::Message;
use relreward_client::{pb, tensor};
use relreward_tests::{TestServer, TinyModels, train_tiny_reward, watch_all};
use tonic::Code;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};

/// What a status message may quote of any input (the server cuts every message at 1 KiB;
/// C-core clients fail an answer whose metadata passes about 8 KiB).
const SHORT: usize = 1024;

fn assert_refused(status: &tonic::Status, code: Code, needle: &str) {
    assert_eq!(status.code(), code, "{}", status.message());
    assert!(status.message().contains(needle), "{:?} does not name {needle:?}", status.message());
    assert!(status.message().len() <= SHORT, "a {} byte message", status.message().len());
}

fn tiny_x(m: &TinyModels, value: f32) -> pb::Tensor {
    let (h, d) = (m.horizon as u64, m.transition_dim as u64);
    tensor::encode_f32(&[1, h, d], &vec![value; (h * d) as usize])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn values_are_quoted_short_and_escaped_in_every_message() {
    let server = TestServer::start();
    let client = server.client().await;
    for len in [300usize, 9_500, 20_000, 1 << 20] {
        // Not a valid name (upper case, a newline, a quote): refused before any lookup.
        let name = format!("Bad\n'{}", "n".repeat(len));
        let x = Some(tensor::encode_f32(&[1, 1], &[0.0]));
        let s = client
            .rewards()
            .score(pb::ScoreRequest { model: name.clone(), x: x.clone(), ..Default::default() })
            .await
            .expect_err("score");
        assert_refused(&s, Code::InvalidArgument, "model:");
        assert!(s.message().contains(&format!("({} bytes)", name.len())), "{}", s.message());
        assert!(!s.message().contains('\n'), "unescaped: {}", s.message());
        let s = client
            .rewards()
            .gradient(pb::GradientRequest { model: name.clone(), x, ..Default::default() })
            .await
            .expect_err("gradient");
        assert_refused(&s, Code::InvalidArgument, "model:");
        let s = client.jobs().cancel_job(pb::CancelJobRequest { id: name.clone() }).await.expect_err("cancel");
        assert_refused(&s, Code::InvalidArgument, "id:");
        let spec = relreward_tests::tiny_diffusion_spec(&name, "out", 0, pb::Optimization::default());
        let s = client
            .jobs()
            .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
            .await
            .expect_err("submit");
        assert_refused(&s, Code::InvalidArgument, "spec.diffusion.dataset:");
        let s = client
            .datasets()
            .get_dataset(pb::GetDatasetRequest { name: name.clone(), view: 0 })
            .await
            .expect_err("get");
        assert_refused(&s, Code::InvalidArgument, "name:");
        // Values that are not names: a digest, an array name, a shape.
        let header = pb::UploadHeader {
            name: "ok".into(),
            kind: pb::DatasetKind::Samples as i32,
            arrays: vec![pb::ArraySpec { name: name.clone(), dtype: pb::Dtype::Float32 as i32, shape: vec![1, 1] }],
            description: String::new(),
        };
        let s = upload(&client, vec![upload_header(header)]).await.expect_err("bad array name");
        assert_refused(&s, Code::InvalidArgument, "header.arrays[0]");
        let long_shape = vec![1u64; len.min(100_000)];
        let s = client
            .rewards()
            .score(pb::ScoreRequest {
                model: "m".into(),
                x: Some(tensor::encode_f32(&long_shape, &[0.0])),
                ..Default::default()
            })
            .await
            .expect_err("unknown model");
        // NOT_FOUND comes before the shape is checked; either way the message is short.
        assert!(s.message().len() <= SHORT);
    }
}

fn upload_header(h: pb::UploadHeader) -> pb::UploadDatasetRequest {
    pb::UploadDatasetRequest { message: Some(pb::upload_dataset_request::Message::Header(h)) }
}

async fn upload(
    client: &relreward_client::Client,
    messages: Vec<pb::UploadDatasetRequest>,
) -> Result<pb::Dataset, tonic::Status> {
    client.datasets().upload_dataset(futures::stream::iter(messages)).await.map(tonic::Response::into_inner)
}

/// Frames sent as given (a bad one among good ones); responses decoded as GradientResponse.
#[derive(Clone, Default)]
struct RawFrames;

struct RawEncoder;
struct ResponseDecoder;

impl Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), tonic::Status> {
        bytes::BufMut::put_slice(dst, &item);
        Ok(())
    }
}

impl Decoder for ResponseDecoder {
    type Item = pb::GradientResponse;
    type Error = tonic::Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<pb::GradientResponse>, tonic::Status> {
        pb::GradientResponse::decode(src).map(Some).map_err(|e| tonic::Status::internal(e.to_string()))
    }
}

impl Codec for RawFrames {
    type Encode = Vec<u8>;
    type Decode = pb::GradientResponse;
    type Encoder = RawEncoder;
    type Decoder = ResponseDecoder;

    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }

    fn decoder(&mut self) -> ResponseDecoder {
        ResponseDecoder
    }
}

/// Opens GradientStream on `channel` with `frames` sent in order, and collects what comes back:
/// the responses, then how the stream ended.
async fn raw_gradient_stream(
    channel: tonic::transport::Channel,
    frames: Vec<Vec<u8>>,
) -> (Vec<pb::GradientResponse>, Result<(), tonic::Status>) {
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.expect("ready");
    let path = http::uri::PathAndQuery::from_static("/relreward.v1.RewardService/GradientStream");
    let request = tonic::Request::new(futures::stream::iter(frames).chain(futures::stream::pending()));
    let mut stream = match grpc.streaming(request, path, RawFrames).await {
        Ok(r) => r.into_inner(),
        Err(s) => return (Vec::new(), Err(s)),
    };
    let mut responses = Vec::new();
    loop {
        match tokio::time::timeout(Duration::from_secs(30), stream.message()).await.expect("the stream ended in time") {
            Ok(Some(r)) => responses.push(r),
            Ok(None) => return (responses, Ok(())),
            Err(s) => return (responses, Err(s)),
        }
    }
}

use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_gradient_stream_frame_ends_the_stream_with_an_error_never_ok() {
    let server = TestServer::start();
    let client = server.client().await;
    let good =
        |id: u64| pb::GradientRequest { request_id: id, model: "absent".into(), ..Default::default() }.encode_to_vec();
    // Frames that do not decode as GradientRequest: a wrong wire type for `model` (field 2),
    // a truncated varint, a length past the end.
    for bad in [vec![0x10, 0x01], vec![0x08, 0xff], vec![0x1a, 0x7f, 0x00]] {
        let (responses, end) = raw_gradient_stream(client.channel(), vec![good(1), bad.clone(), good(2)]).await;
        let status = end.expect_err("the stream must not end OK after a bad frame");
        assert_refused(&status, Code::InvalidArgument, "request stream");
        // The request before the bad frame is answered (with its own error: no such model);
        // nothing after it is.
        let ids: Vec<u64> = responses.iter().map(|r| r.request_id).collect();
        assert_eq!(ids, [1], "frame {bad:?}");
        assert!(responses[0].error.is_some(), "the request before the bad frame is answered with its own error");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_job_from_any_seq_beyond_the_last_follows_live_and_never_replays() {
    let server = TestServer::start();
    let dir = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, dir.path());
    let client = server.client().await;
    let finished = client.list_jobs(pb::JobState::Succeeded).await.expect("jobs").into_iter().next().expect("a job");
    let all = watch_all(&client, &finished.id, 0).await;
    assert!(all.len() >= 2 && all[0].seq == 1, "{} events", all.len());
    let last = all.last().map(|e| e.seq).expect("events");
    for from in [last + 1, last + 1000, (1u64 << 63) - 1, 1u64 << 63, (1u64 << 63) + 5, u64::MAX] {
        assert!(watch_all(&client, &finished.id, from).await.is_empty(), "from_seq {from} replayed events");
    }
    // A running job: from far beyond, the watcher gets only what comes next (here the
    // cancellation), never a replay from seq 1.
    let spec = relreward_tests::tiny_diffusion_spec(
        &m.dataset,
        "slow",
        1,
        pb::Optimization { steps: Some(1_000_000), log_every: Some(1_000_000), ..Default::default() },
    );
    let job = client.submit_job(spec, None).await.expect("submit");
    for _ in 0..600 {
        if client.get_job(&job.id).await.expect("job").step > 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let running = client.get_job(&job.id).await.expect("job");
    let watcher = {
        let (c, id) = (client.clone(), job.id.clone());
        tokio::spawn(async move { watch_all(&c, &id, 1u64 << 63).await })
    };
    tokio::time::sleep(Duration::from_millis(500)).await;
    client.cancel_job(&job.id).await.expect("cancel");
    let seen = tokio::time::timeout(Duration::from_secs(60), watcher).await.expect("watch ended").expect("join");
    assert!(!seen.is_empty(), "the live cancellation was not delivered");
    assert!(
        seen.iter().all(|e| e.seq > running.last_seq),
        "replayed: {:?}",
        seen.iter().map(|e| e.seq).collect::<Vec<_>>()
    );
    assert_eq!(relreward_tests::final_state(&seen), Some(pb::JobState::Cancelled));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_over_the_size_limit_are_resource_exhausted_naming_the_setting() {
    let limit = 64 * 1024;
    let server = TestServer::start_with_env(&[("RELREWARD__SERVER__MAX_REQUEST_BYTES", &limit.to_string())]);
    let client = server.client().await;
    let big = |n: usize| Some(tensor::encode_f32(&[1, n as u64], &vec![0.5; n]));
    // Unary (Score, Gradient), server streaming (Sample), client streaming (UploadDataset),
    // bidirectional (GradientStream): the same answer.
    let s = client
        .rewards()
        .score(pb::ScoreRequest { model: "m".into(), x: big(limit / 2), ..Default::default() })
        .await
        .expect_err("score");
    assert_refused(&s, Code::ResourceExhausted, "server.max_request_bytes");
    assert!(s.message().contains(&limit.to_string()), "{}", s.message());
    let s = client
        .rewards()
        .gradient(pb::GradientRequest { model: "m".into(), x: big(limit), ..Default::default() })
        .await
        .expect_err("gradient");
    assert_refused(&s, Code::ResourceExhausted, "server.max_request_bytes");
    let conditions = vec![pb::Condition { index: 0, state: big(limit) }];
    let s = match client
        .rewards()
        .sample(pb::SampleRequest { model: "m".into(), conditions, ..Default::default() })
        .await
    {
        Err(s) => s,
        Ok(r) => r.into_inner().message().await.expect_err("sample"),
    };
    assert_refused(&s, Code::ResourceExhausted, "server.max_request_bytes");
    let header = pb::UploadHeader {
        name: "big".into(),
        kind: pb::DatasetKind::Samples as i32,
        arrays: vec![pb::ArraySpec {
            name: "samples".into(),
            dtype: pb::Dtype::Float32 as i32,
            shape: vec![1, limit as u64],
        }],
        description: String::new(),
    };
    let chunk = pb::UploadDatasetRequest {
        message: Some(pb::upload_dataset_request::Message::Chunk(pb::DatasetChunk {
            array: "samples".into(),
            data: big(limit),
        })),
    };
    let s = upload(&client, vec![upload_header(header), chunk]).await.expect_err("upload");
    assert_refused(&s, Code::ResourceExhausted, "server.max_request_bytes");
    let frame = pb::GradientRequest { request_id: 1, model: "m".into(), x: big(limit), ..Default::default() };
    let (_, end) = raw_gradient_stream(client.channel(), vec![frame.encode_to_vec()]).await;
    assert_refused(&end.expect_err("stream"), Code::ResourceExhausted, "server.max_request_bytes");
    // Nothing was stored, and the server still answers.
    assert!(client.list_datasets().await.expect("list").is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn extreme_finite_inputs_are_refused_never_answered_with_inf_or_nan() {
    let server = TestServer::start();
    let dir = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, dir.path());
    let client = server.client().await;
    let gradient = |x: pb::Tensor, omega: Option<f64>, units: pb::Units| pb::GradientRequest {
        model: m.reward.clone(),
        x: Some(x),
        t: vec![3],
        omega,
        input_units: units as i32,
        ..Default::default()
    };
    // In range: finite answers.
    let ok = client.rewards().gradient(gradient(tiny_x(&m, 0.5), Some(1e3), pb::Units::Raw)).await.expect("ok");
    let g = ok.into_inner().gradient.expect("gradient");
    tensor::decode_finite_f32(&g).expect("finite gradient");
    for omega in [1e308, -1e300, 3e38, 1e7] {
        let s = client
            .rewards()
            .gradient(gradient(tiny_x(&m, 0.5), Some(omega), pb::Units::Raw))
            .await
            .expect_err("huge omega");
        assert_eq!(s.code(), Code::InvalidArgument, "{omega}: {}", server.log());
        assert_refused(&s, Code::InvalidArgument, "omega:");
    }
    for (value, units) in [(3e38f32, pb::Units::Raw), (-1e30, pb::Units::Raw), (1e6, pb::Units::Normalized)] {
        let s = client
            .rewards()
            .score(pb::ScoreRequest { model: m.reward.clone(), x: Some(tiny_x(&m, value)), ..Default::default() })
            .await;
        let s = match units {
            pb::Units::Raw => s.expect_err("huge raw x"),
            _ => client
                .rewards()
                .gradient(gradient(tiny_x(&m, value), None, units))
                .await
                .expect_err("huge normalized x"),
        };
        assert_eq!(s.code(), Code::InvalidArgument, "{value} {units:?}: {}", server.log());
        assert_refused(&s, Code::InvalidArgument, "x: element 0");
    }
    // Guided sampling with an omega the rule refuses.
    let s = match client
        .rewards()
        .sample(pb::SampleRequest {
            model: m.base.clone(),
            reward_model: m.reward.clone(),
            omega: 1e300,
            n: 2,
            ..Default::default()
        })
        .await
    {
        Err(s) => s,
        Ok(r) => r.into_inner().message().await.expect_err("sample"),
    };
    assert_eq!(s.code(), Code::InvalidArgument, "{}", server.log());
    assert_refused(&s, Code::InvalidArgument, "omega:");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_kind_of_field_has_one_rule_on_every_rpc() {
    let server = TestServer::start();
    let dir = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, dir.path());
    let client = server.client().await;
    let page = |token: &str| Some(pb::PageRequest { page_size: 1, page_token: token.into() });

    // Page tokens: only what a List call returned.
    // A bare name is not a token either (the calls hand out "after:<name>").
    for token in ["!!garbage", "-1", "../x", "\u{1f600}", "a", "after:", "after:../x"] {
        let s = client
            .models()
            .list_models(pb::ListModelsRequest { page: page(token), kind: 0 })
            .await
            .expect_err("models token");
        assert_refused(&s, Code::InvalidArgument, "page.page_token");
        let s = client
            .datasets()
            .list_datasets(pb::ListDatasetsRequest { page: page(token), view: 0 })
            .await
            .expect_err("datasets token");
        assert_refused(&s, Code::InvalidArgument, "page.page_token");
        let s =
            client.jobs().list_jobs(pb::ListJobsRequest { page: page(token), state: 0 }).await.expect_err("jobs token");
        assert_refused(&s, Code::InvalidArgument, "page.page_token");
    }
    // The tokens the calls hand out are accepted back, page after page.
    let first = client.models().list_models(pb::ListModelsRequest { page: page(""), kind: 0 }).await.expect("page 1");
    let token = first.into_inner().next_page_token;
    assert!(!token.is_empty());
    client.models().list_models(pb::ListModelsRequest { page: page(&token), kind: 0 }).await.expect("page 2");
    let first = client.jobs().list_jobs(pb::ListJobsRequest { page: page(""), state: 0 }).await.expect("page 1");
    let token = first.into_inner().next_page_token;
    client.jobs().list_jobs(pb::ListJobsRequest { page: page(&token), state: 0 }).await.expect("page 2");

    // Enums: a value the proto does not define is refused wherever it appears.
    for v in [99, -1, 3] {
        let s = client
            .datasets()
            .list_datasets(pb::ListDatasetsRequest { page: None, view: v })
            .await
            .expect_err("list view");
        assert_refused(&s, Code::InvalidArgument, "view: unknown value");
        let s = client
            .datasets()
            .get_dataset(pb::GetDatasetRequest { name: m.dataset.clone(), view: v })
            .await
            .expect_err("get view");
        assert_refused(&s, Code::InvalidArgument, "view: unknown value");
        let s = client
            .rewards()
            .score(pb::ScoreRequest {
                model: m.reward.clone(),
                x: Some(tiny_x(&m, 0.1)),
                input_units: v,
                ..Default::default()
            })
            .await
            .expect_err("score units");
        assert_refused(&s, Code::InvalidArgument, "input_units: unknown value");
        let s =
            sample_error(&client, pb::SampleRequest { model: m.base.clone(), input_units: v, ..Default::default() })
                .await;
        assert_refused(&s, Code::InvalidArgument, "input_units: unknown value");
    }
    let s = client.models().list_models(pb::ListModelsRequest { page: None, kind: 99 }).await.expect_err("kind");
    assert_refused(&s, Code::InvalidArgument, "kind: unknown value 99");
    let s = client.jobs().list_jobs(pb::ListJobsRequest { page: None, state: 99 }).await.expect_err("state");
    assert_refused(&s, Code::InvalidArgument, "state: unknown value 99");

    // Diffusion times: [0, T) of the model, for Score's t and Sample's t_stopgrad alike.
    let big_t = m.n_timesteps as u32;
    for t in [big_t, 1000, u32::MAX] {
        let s = client
            .rewards()
            .score(pb::ScoreRequest {
                model: m.reward.clone(),
                x: Some(tiny_x(&m, 0.1)),
                t: vec![t],
                ..Default::default()
            })
            .await
            .expect_err("score t");
        assert_refused(&s, Code::InvalidArgument, &format!("t[0]: {t} is outside [0, {big_t})"));
        let s = sample_error(
            &client,
            pb::SampleRequest {
                model: m.base.clone(),
                reward_model: m.reward.clone(),
                omega: 0.1,
                t_stopgrad: Some(t),
                ..Default::default()
            },
        )
        .await;
        assert_refused(&s, Code::InvalidArgument, &format!("t_stopgrad: {t} is outside [0, {big_t})"));
    }

    // A reward job on the tiny models' dataset; `set` fills in the field under test.
    let reward_job = |set: &dyn Fn(&mut pb::TrainReward)| {
        let mut reward = pb::TrainReward {
            base_model: m.base.clone(),
            expert_model: m.base.clone(),
            algorithm: Some(pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
                datasets: vec![m.dataset.clone()],
            })),
            ..Default::default()
        };
        set(&mut reward);
        let spec = pb::JobSpec {
            output_model: "out".into(),
            kind: Some(pb::job_spec::Kind::Reward(reward)),
            ..Default::default()
        };
        pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() }
    };
    // Names: malformed is INVALID_ARGUMENT before any lookup, in every field that holds one.
    for bad in ["../x", "X", "a/b", ""] {
        let spec = relreward_tests::tiny_diffusion_spec(bad, "out", 0, pb::Optimization::default());
        let s = client
            .jobs()
            .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
            .await
            .expect_err("dataset name");
        assert_refused(&s, Code::InvalidArgument, "spec.diffusion.dataset:");
        let s = client.jobs().submit_job(reward_job(&|r| r.expert_model = bad.into())).await.expect_err("model name");
        assert_refused(&s, Code::InvalidArgument, "spec.reward.expert_model:");
        let s = sample_error(&client, pb::SampleRequest { model: bad.into(), ..Default::default() }).await;
        assert_refused(&s, Code::InvalidArgument, "model:");
    }
    // The alignment loss's entry weights: finite and zero or positive, each named.
    for (field, action_weight, condition_weight) in
        [("spec.reward.action_weight:", Some(-1.0), None), ("spec.reward.condition_weight:", None, Some(f64::NAN))]
    {
        let request = reward_job(&|r| {
            r.action_weight = action_weight;
            r.condition_weight = condition_weight;
        });
        let s = client.jobs().submit_job(request).await.expect_err("entry weight");
        assert_refused(&s, Code::InvalidArgument, field);
    }
    // A clean first observation in x_t is Algorithm 1's option; Algorithm 2 draws no x_t from data.
    let request = reward_job(&|r| {
        r.inpaint_condition = Some(true);
        r.algorithm = Some(pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly { num_chains: None }));
    });
    let s = client.jobs().submit_job(request).await.expect_err("inpaint_condition with models_only");
    assert_refused(&s, Code::InvalidArgument, "spec.reward.inpaint_condition: applies to with_dataset");
    // A well-formed name that does not exist is NOT_FOUND, as everywhere.
    let spec = relreward_tests::tiny_diffusion_spec("absent", "out", 0, pb::Optimization::default());
    let s = client
        .jobs()
        .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
        .await
        .expect_err("absent");
    assert_eq!(s.code(), Code::NotFound, "{}", s.message());
}

async fn sample_error(client: &relreward_client::Client, request: pb::SampleRequest) -> tonic::Status {
    match client.rewards().sample(request).await {
        Err(s) => s,
        Ok(r) => r.into_inner().message().await.expect_err("the sample request must be refused"),
    }
}

/// Sample's condition states, guide steps and wire floats, and the training jobs' fields that
/// were once only checked after the job was accepted (or checked under another field's name).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn conditions_guide_steps_and_job_fields_are_refused_at_the_door_by_their_own_names() {
    let server = TestServer::start();
    let dir = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, dir.path());
    let client = server.client().await;
    let obs = |values: &[f32], shape: &[u64]| Some(tensor::encode_f32(shape, values));
    let sample = |conditions: Vec<pb::Condition>| pb::SampleRequest {
        model: m.base.clone(),
        n: 1,
        seed: Some(1),
        conditions,
        ..Default::default()
    };
    // One observation has shape [obs_dim] (2 here): [2, 1] holds two values but is not one.
    let s = sample_error(&client, sample(vec![pb::Condition { index: 0, state: obs(&[0.1, 0.2], &[2, 1]) }])).await;
    assert_refused(&s, Code::InvalidArgument, "conditions[0].state: shape [2, 1]");
    // One condition per index.
    let twice = vec![
        pb::Condition { index: 1, state: obs(&[0.1, 0.2], &[2]) },
        pb::Condition { index: 1, state: obs(&[0.3, 0.4], &[2]) },
    ];
    let s = sample_error(&client, sample(twice)).await;
    assert_refused(&s, Code::InvalidArgument, "conditions[1].index: 1 is already fixed by conditions[0]");
    // A state far outside the data is refused like Score's x (it made Inf samples).
    for value in [3.4e38f32, 1e30, -1e9] {
        let s = sample_error(&client, sample(vec![pb::Condition { index: 0, state: obs(&[value, 0.0], &[2]) }])).await;
        assert_refused(&s, Code::InvalidArgument, "conditions[0].state: element 0");
    }
    // In range, the samples come back finite.
    let mut ok = client
        .rewards()
        .sample(sample(vec![pb::Condition { index: 0, state: obs(&[0.5, -0.5], &[2]) }]))
        .await
        .expect("sample")
        .into_inner();
    let first = ok.message().await.expect("stream").expect("one sample");
    tensor::decode_finite_f32(&first.x.expect("x")).expect("finite");
    // Zero guide steps with omega != 0 would sample unguided without saying so.
    let s = sample_error(
        &client,
        pb::SampleRequest {
            model: m.base.clone(),
            reward_model: m.reward.clone(),
            omega: 0.1,
            n_guide_steps: Some(0),
            ..Default::default()
        },
    )
    .await;
    assert_refused(&s, Code::InvalidArgument, "n_guide_steps: 0");
    // A finite float64 that float32 cannot hold is named as such, not as "not finite (inf)".
    let (h, d) = (m.horizon as u64, m.transition_dim as u64);
    let mut values = vec![0.0f64; (h * d) as usize];
    values[3] = 1e300;
    let s = client
        .rewards()
        .score(pb::ScoreRequest {
            model: m.reward.clone(),
            x: Some(tensor::encode_f64(&[1, h, d], &values)),
            ..Default::default()
        })
        .await
        .expect_err("1e300");
    assert_refused(&s, Code::InvalidArgument, "x: element 3 (1e300) is outside float32's range");

    // Diffusion jobs: the network is planned at submission, and errors name the job's fields;
    // a refused submission stores no job.
    let jobs_before = client.list_jobs(pb::JobState::Unspecified).await.expect("jobs").len();
    let submit = |spec: pb::JobSpec| pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() };
    let diffusion = |set: &dyn Fn(&mut pb::TrainDiffusion)| {
        let mut spec = relreward_tests::tiny_diffusion_spec(&m.dataset, "out", 0, pb::Optimization::default());
        if let Some(pb::job_spec::Kind::Diffusion(d)) = spec.kind.as_mut() {
            set(d);
        }
        submit(spec)
    };
    let mlp = |hidden: Vec<u32>| Some(pb::train_diffusion::Architecture::Mlp(pb::Mlp { hidden }));
    for (set, field) in [
        (
            Box::new(|d: &mut pb::TrainDiffusion| d.architecture = mlp(vec![100_000, 100_000]))
                as Box<dyn Fn(&mut pb::TrainDiffusion)>,
            "spec.diffusion.mlp",
        ),
        (Box::new(|d: &mut pb::TrainDiffusion| d.architecture = mlp(vec![1 << 31])), "spec.diffusion.mlp"),
        (Box::new(|d: &mut pb::TrainDiffusion| d.n_timesteps = Some(0)), "spec.diffusion.n_timesteps"),
        (Box::new(|d: &mut pb::TrainDiffusion| d.pooled_normalizer = Some(true)), "spec.diffusion.pooled_normalizer"),
    ] {
        let s = client.jobs().submit_job(diffusion(&*set)).await.expect_err(field);
        assert_refused(&s, Code::InvalidArgument, field);
    }
    // On a samples dataset, the trajectory-only fields are refused, not ignored.
    let header = pb::UploadHeader {
        name: "items".into(),
        kind: pb::DatasetKind::Samples as i32,
        arrays: vec![pb::ArraySpec { name: "samples".into(), dtype: pb::Dtype::Float32 as i32, shape: vec![8, 3] }],
        description: String::new(),
    };
    let items = tensor::encode_f32(&[8, 3], &[0.5; 24]);
    let sha256 = {
        use sha2::Digest;
        hex::encode(sha2::Sha256::digest(&items.data))
    };
    let chunk = pb::UploadDatasetRequest {
        message: Some(pb::upload_dataset_request::Message::Chunk(pb::DatasetChunk {
            array: "samples".into(),
            data: Some(items),
        })),
    };
    let commit = pb::UploadDatasetRequest {
        message: Some(pb::upload_dataset_request::Message::Commit(pb::UploadCommit { sha256 })),
    };
    upload(&client, vec![upload_header(header), chunk, commit]).await.expect("samples upload");
    for (set, needle) in [
        (
            Box::new(|d: &mut pb::TrainDiffusion| d.horizon = Some(16)) as Box<dyn Fn(&mut pb::TrainDiffusion)>,
            "spec.diffusion.horizon: 16 applies to trajectories only",
        ),
        (Box::new(|d: &mut pb::TrainDiffusion| d.action_weight = Some(10.0)), "spec.diffusion.action_weight: 10"),
    ] {
        let s = client
            .jobs()
            .submit_job(diffusion(&|d: &mut pb::TrainDiffusion| {
                d.dataset = "items".into();
                d.horizon = None;
                d.architecture = mlp(vec![16]);
                set(d);
            }))
            .await
            .expect_err(needle);
        assert_refused(&s, Code::InvalidArgument, needle);
    }
    let jobs_after = client.list_jobs(pb::JobState::Unspecified).await.expect("jobs").len();
    assert_eq!(jobs_after, jobs_before, "a refused diffusion job was stored");
    // Discriminator jobs: its own field names, not the reward job's it is checked as.
    let discriminator = |base: &str, expert: &str| {
        submit(pb::JobSpec {
            output_model: "disc".into(),
            kind: Some(pb::job_spec::Kind::Discriminator(pb::TrainDiscriminator {
                base_dataset: base.into(),
                expert_dataset: expert.into(),
                diffusion_model: m.base.clone(),
                ..Default::default()
            })),
            ..Default::default()
        })
    };
    let s = client.jobs().submit_job(discriminator("nope", &m.dataset)).await.expect_err("base");
    assert_refused(&s, Code::NotFound, "spec.discriminator.base_dataset:");
    let s = client.jobs().submit_job(discriminator(&m.dataset, "nope")).await.expect_err("expert");
    assert_refused(&s, Code::NotFound, "spec.discriminator.expert_dataset:");
}

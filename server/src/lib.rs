//! relreward-server: hosts base and expert diffusion models, extracts relative rewards from
//! them and serves those rewards over gRPC.
//!
//! Module map, a layering: each module may import the ones below it, never one above:
//! - [`oip_http`]: the Open Inference Protocol over HTTP/JSON (KServe v2 REST), its own
//!   listener: routes become [`api::oip`]'s requests, authorized by [`security`]'s policy.
//! - [`security`]: who may call what (bearer tokens, scopes, one tower layer in front of
//!   every service) and TLS; sits above [`api`], which it never imports.
//! - [`api`]: tonic services (relreward.v1 and the Open Inference Protocol); validate and
//!   convert at the door, nothing else.
//! - [`limits`]: server-wide limits: connections, call deadlines (read with [`serving`]'s
//!   `grpc-timeout` parser), the data directory's disk budget; layers at the door, above
//!   what they guard.
//! - [`sampling`]: Sample runs behind their own workers: one validation, a bounded queue, a
//!   stream of host rows back to the door.
//! - [`latents`]: Encode and Decode through an uploaded autoencoder: one validation, one pass
//!   under an inference slot, host values back to the door.
//! - [`serving`]: Score and Gradient queries: validation, units, the per-model dynamic batcher.
//! - [`jobs`]: the job system (queue, threads, events, checkpoints) and the training runners,
//!   which drive the engine's trainers (e.g. [`engine::reward_trainer`]).
//! - [`registry`]: stored models loaded on demand and cached: where the store's records and
//!   files become engine types.
//! - [`engine`]: tensor math on libtorch (tch): networks, diffusion, Algorithms 1 and 2.
//!   Knows nothing of gRPC, jobs or the store; of the configuration, only `engine.*`.
//! - [`store`]: metadata ([`store::MetadataStore`]) and files ([`store::BlobStore`]),
//!   dataset ingestion and crash recovery.
//! - [`fields`]: one rule per kind of request field (names, enums, page tokens, diffusion
//!   times, guidance scales), used at the door of every RPC.
//! - [`tasks`]: groups of background work (tokio tasks, blocking tasks, worker threads) that
//!   shutdown stops and waits for.
//! - [`fault`]: the test-only fault-injection hook (`RELREWARD_FAULT`), a no-op when unset.
//! - [`config`]: layered configuration and its validation.
//! - [`metrics`]: Prometheus metrics, the per-call recording layer and the `/metrics` endpoint.
//! - [`error`]: the one error type and its one mapping to gRPC status codes.
//! - `compression` (private): the response-compression policy layer; `with_compression!`
//!   (here) puts gzip and deflate on each service.
//!
//! Entry point: [`run`], which `main` calls with a bound listener and a shutdown future, and
//! tests call with a port-0 listener. Transport settings (HTTP/2 flow-control windows,
//! compression, the shutdown drain) are applied there too.

/// gzip and deflate on one generated tonic service (`$service`, with `$config`): compressed
/// requests are always accepted; responses may be compressed unless
/// `server.response_compression = "off"` (when they are: [`compression::RequestMirrorLayer`]).
/// Every service of the listener goes through it: relreward.v1, OIP, health, reflection.
macro_rules! with_compression {
    ($service:expr, $config:expr) => {{
        use tonic::codec::CompressionEncoding::{Deflate, Gzip};
        let service = $service.accept_compressed(Gzip).accept_compressed(Deflate);
        if $config.server.response_compression == "off" {
            service
        } else {
            service.send_compressed(Gzip).send_compressed(Deflate)
        }
    }};
}

pub mod api;
mod compression;
pub mod config;
pub mod engine;
pub mod error;
pub mod fault;
pub mod fields;
pub mod jobs;
pub mod latents;
pub mod limits;
pub mod metrics;
pub mod oip_http;
pub mod registry;
pub mod sampling;
pub mod security;
pub mod serving;
pub mod store;
pub mod tasks;

use std::future::Future;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;

pub use config::Config;

/// Serves until `shutdown` completes, then shuts down gracefully: health goes NOT_SERVING
/// while everything is still served for `server.shutdown_drain_secs` (or until `cut_drain`
/// completes: `main` passes a second signal), then the listener closes and in-flight calls get
/// `server.shutdown_grace_secs` to finish.
///
/// Unless `metrics.listen` is empty, also serves Prometheus metrics there (bound first, so a
/// taken port fails the start at once) and prints `relreward-server metrics on
/// http://ADDR/metrics` on stdout, the line after `main`'s `listening on` line. Likewise
/// `oip_http.listen` (KServe v2 REST): `relreward-server oip_http on http[s]://ADDR`, after
/// the metrics line.
pub async fn run(
    config: Config,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send,
    cut_drain: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    // First, so a bad token entry, an unreadable certificate or an exposed unauthenticated
    // listener stops the start before anything is opened.
    let security = security::Security::load(&config, listener.local_addr()?)?;
    for warning in &security.warnings {
        tracing::warn!("{warning}");
    }
    tracing::info!(
        authentication = if security.layer.is_open() { "none" } else { "bearer tokens" },
        tls = match (&security.tls, config.security.tls.client_ca.as_os_str().is_empty()) {
            (None, _) => "off",
            (Some(_), true) => "on",
            (Some(_), false) => "mutual",
        },
        "access control"
    );
    let metrics_listener = bind_metrics(&config).await?;
    let oip_http_listener = bind_oip_http(&config, security.http_tls.is_some()).await?;
    // Resolves `engine.device` (a device that is not there stops the start here).
    let device = engine::init(&config.engine)?;
    let store = store::Store::open(&config).await?;
    let role = config.role();
    // The server's shutdown token. Every background task, blocking task and worker thread
    // belongs to one group (`tasks::Tasks`) whose token is a child of it; each group is
    // stopped and waited for at its point of the shutdown order below, and whatever is left
    // is cancelled when `run` returns (early returns included: the guard).
    let server_token = CancellationToken::new();
    let _stop_everything = server_token.clone().drop_guard();
    let group = |name| tasks::Tasks::new(name, server_token.child_token());
    // GradientStream calls: stopped when the listener closes (they answer what is in flight,
    // then end UNAVAILABLE), since a stream has no end of its own for the grace to wait for.
    let streams = group("streams");
    // On shutdown, jobs stop at their next step (checkpointing first) and resume on the next
    // worker to claim them (this process after a restart, with the embedded store).
    let job_manager = jobs::JobManager::start(store.clone(), config.jobs.clone(), role.works(), group("jobs")).await?;
    // Diffusion models, loaded from the store on demand and cached (models.cache_bytes).
    let registry = registry::ModelRegistry::new(store.clone(), &config.models, device);
    // Inference compute (batched Score/Gradient passes and sampling runs) at once.
    let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(config.engine.inference_workers));
    let metrics = metrics::Metrics::new();
    let serving = serving::Serving::new(
        registry.clone(),
        config.serving.clone(),
        slots.clone(),
        metrics.clone(),
        group("serving"),
    );
    let latents =
        latents::Latents::new(registry.clone(), slots.clone(), config.server.max_response_bytes, group("latents"));
    let sampling =
        sampling::Sampling::start(registry.clone(), slots, config.engine.inference_workers, group("sampling"));
    // Stopped after the gRPC drain (last, so the shutdown can be watched), or by the guard.
    let metrics_tasks = group("metrics");
    if let Some(listener) = metrics_listener {
        let refresh = scrape_refresh(metrics.clone(), store.clone(), registry.clone());
        metrics_tasks.spawn(metrics::serve_http(listener, metrics.clone(), refresh, metrics_tasks.token().clone()));
    }

    // The OIP over HTTP (serving roles only): stopped with the gRPC listener, after the drain.
    let oip_http_tasks = group("oip_http");
    let draining = CancellationToken::new();
    if let Some(listener) = oip_http_listener {
        let service = std::sync::Arc::new(oip_http::OipHttp::new(
            api::oip::Inference::new(serving.clone()),
            metrics.clone(),
            security.layer.policy(),
            config.server.max_request_bytes,
            config.serving.default_deadline_ms,
            draining.clone(),
        ));
        let tls = security.http_tls.clone().map(tokio_rustls::TlsAcceptor::from);
        oip_http_tasks.spawn(oip_http::serve(
            listener,
            tls,
            service,
            config.server.max_connections,
            oip_http_tasks.token().clone(),
        ));
    }

    // A worker ("work") answers health checks only, for its orchestrator's probes.
    let served_services: &[&str] = if role.serves() { api::SERVICE_NAMES } else { &[] };
    let (health, health_service) = tonic_health::server::health_reporter();
    for name in served_services {
        health.set_service_status(*name, ServingStatus::Serving).await;
    }
    health.set_service_status("", ServingStatus::Serving).await;
    let health_service = with_compression!(health_service, config);

    // v1 and v1alpha, answering a failed lookup in-stream (api::reflection).
    let (reflection_v1, reflection_v1alpha) = api::reflection::services(&[
        relreward_proto::FILE_DESCRIPTOR_SET,
        relreward_proto::INFERENCE_FILE_DESCRIPTOR_SET,
        tonic_health::pb::FILE_DESCRIPTOR_SET,
    ])?;
    let reflection_v1 = with_compression!(reflection_v1, config);
    let reflection_v1alpha = with_compression!(reflection_v1alpha, config);

    let stop_accepting = CancellationToken::new();
    // TCP_NODELAY on every accepted connection: without it a small unary response waits for
    // the client's delayed ACK (Nagle), about 40 ms per Gradient call. tonic's own
    // `tcp_nodelay` setting does not apply to a listener passed in.
    let incoming = tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
    let incoming = limits::limit_connections(incoming, config.server.max_connections);
    // Flow control: a call that stops reading its requests (a GradientStream whose client does
    // not read the responses stops being read: backpressure) holds at most its stream window of
    // unread data, and the connection window, at least max_concurrent_streams stream windows
    // (config validation), always leaves room for the connection's other calls. With hyper's
    // defaults (1 MiB each) one such call held the whole connection window and stalled every
    // other call on the connection, health checks included. No adaptive window: hyper's BDP
    // estimate sets both windows to one value, which would bring that back.
    let mut builder = tonic::transport::Server::builder()
        .max_concurrent_streams(Some(config.server.max_concurrent_streams))
        .initial_stream_window_size(config.server.http2_stream_window_bytes)
        .initial_connection_window_size(config.server.http2_connection_window_bytes)
        .http2_adaptive_window(Some(false))
        // Metadata is bounded by `limits::MetadataLimitLayer` (a status on the call alone);
        // HTTP/2's own bound sits far above it (hyper's default, 16 KiB, answered HTTP 431).
        .http2_max_header_list_size(Some(config.server.http2_header_list_bytes()));
    if config.server.max_connection_age_secs > 0 {
        builder = builder
            .max_connection_age(Duration::from_secs(config.server.max_connection_age_secs))
            .max_connection_age_grace(Duration::from_secs(config.server.max_connection_age_grace_secs));
    }
    if let Some(tls) = security.tls {
        // The one listener then speaks TLS only: native API, OIP, health and reflection.
        builder = builder.tls_config(tls)?;
    }
    let routes = if role.serves() {
        api::routes(
            &config,
            store,
            job_manager.clone(),
            serving.clone(),
            sampling.clone(),
            latents.clone(),
            streams.clone(),
        )
    } else {
        tonic::service::Routes::default()
    };
    let server = {
        let token = stop_accepting.clone();
        builder
            // Metrics outermost, so refused calls are counted with their status like any other.
            .layer(metrics::GrpcMetricsLayer::new(metrics))
            // Statuses tonic and the layers below make themselves, by the error module's rules.
            .layer(error::wire::WireStatusLayer)
            .layer(limits::MetadataLimitLayer::new(config.server.max_metadata_bytes))
            .layer(security.layer)
            // Inside the security layer: a refused call gets no default deadline.
            .layer(limits::DeadlineLayer::new(config.serving.default_deadline_ms))
            .layer(compression::RequestMirrorLayer::new(config.server.response_compression == "request"))
            .add_routes(routes)
            .add_service(health_service)
            .add_service(reflection_v1)
            .add_service(reflection_v1alpha)
            .serve_with_incoming_shutdown(incoming, async move { token.cancelled().await })
    };
    tokio::pin!(server);
    tokio::select! {
        result = &mut server => return result.map_err(Into::into),
        () = shutdown => {}
    }

    let drain = Duration::from_secs(config.server.shutdown_drain_secs);
    tracing::info!(
        drain_secs = drain.as_secs(),
        "shutdown requested: reporting NOT_SERVING, serving on for the drain (a second signal ends it)"
    );
    for name in served_services {
        health.set_service_status(*name, ServingStatus::NotServing).await;
    }
    health.set_service_status("", ServingStatus::NotServing).await;
    draining.cancel();
    // The drain: everything is still served (new connections and calls too) while health says
    // NOT_SERVING, so that load balancers and clients polling health see it and stop sending
    // before the listener closes; closing at once, they saw only UNAVAILABLE.
    if !drain.is_zero() {
        tokio::pin!(cut_drain);
        tokio::select! {
            result = &mut server => return result.map_err(Into::into),
            () = tokio::time::sleep(drain) => {}
            () = &mut cut_drain => tracing::info!("drain cut short"),
        }
    }
    tracing::info!("closing the listener and draining in-flight calls");
    stop_accepting.cancel();
    oip_http_tasks.token().cancel();
    streams.token().cancel();
    // Jobs checkpoint and stop while in-flight calls finish: one grace for both, so a
    // supervisor's stop timeout of preStop + drain + grace holds (docs/deployment.md).
    let grace = Duration::from_secs(config.server.shutdown_grace_secs);
    let calls = async {
        match tokio::time::timeout(grace, server).await {
            Ok(result) => result,
            Err(_) => {
                tracing::warn!(grace_secs = grace.as_secs(), "in-flight calls did not finish in time; exiting anyway");
                Ok(())
            }
        }
    };
    let ((), served) = tokio::join!(job_manager.shutdown(grace), calls);
    // After the grace, what still runs is stopped: streams (ended already, unless a client
    // never read its answers), sampling runs (at their next denoising step; queued ones are
    // answered UNAVAILABLE), Encode/Decode passes (waited for; callers still waiting for a
    // slot are answered UNAVAILABLE), then the serving threads (which may wait for a slot a sampling
    // run held), then the metrics endpoint.
    streams.stop(STOP_BOUND).await;
    sampling.stop(STOP_BOUND).await;
    latents.stop(STOP_BOUND).await;
    oip_http_tasks.stop(STOP_BOUND).await;
    serving.stop(STOP_BOUND).await;
    metrics_tasks.stop(STOP_BOUND).await;
    server_token.cancel();
    served?;
    tracing::info!("stopped");
    Ok(())
}

/// How long the shutdown waits for each group of background work once it is told to stop:
/// each checks its token at least once per step (a denoising step, a served batch, a stream
/// message), so this is a bound for a stuck task, not a pause.
const STOP_BOUND: Duration = Duration::from_secs(5);

/// Binds `metrics.listen` (None when empty: disabled) and announces the address.
async fn bind_metrics(config: &Config) -> anyhow::Result<Option<TcpListener>> {
    let addr = config.metrics.listen.as_str();
    if addr.is_empty() {
        return Ok(None);
    }
    let listener =
        TcpListener::bind(addr).await.map_err(|e| anyhow::anyhow!("cannot listen on {addr} (metrics.listen): {e}"))?;
    let local = listener.local_addr()?;
    tracing::info!(%local, "metrics endpoint listening");
    // The second machine-readable line on stdout (tests bind port 0 and read it).
    println!("relreward-server metrics on http://{local}/metrics");
    Ok(Some(listener))
}

/// Binds `oip_http.listen` (None when empty: disabled) and announces the address on stdout,
/// the line after the metrics line (or after `listening on` when metrics are off).
async fn bind_oip_http(config: &Config, tls: bool) -> anyhow::Result<Option<TcpListener>> {
    let addr = config.oip_http.listen.as_str();
    // A worker ("work") serves no API.
    if addr.is_empty() || !config.role().serves() {
        return Ok(None);
    }
    let listener =
        TcpListener::bind(addr).await.map_err(|e| anyhow::anyhow!("cannot listen on {addr} (oip_http.listen): {e}"))?;
    let local = listener.local_addr()?;
    tracing::info!(%local, tls, "OIP over HTTP (KServe v2 REST) listening");
    println!("relreward-server oip_http on {}://{local}", if tls { "https" } else { "http" });
    Ok(Some(listener))
}

/// The gauges read at scrape time: jobs by state (a COUNT in the metadata store) and models
/// in memory.
fn scrape_refresh(
    metrics: metrics::Metrics,
    store: store::Store,
    registry: registry::ModelRegistry,
) -> impl Fn() -> std::pin::Pin<Box<dyn Future<Output = ()> + Send>> + Clone + Send + Sync + 'static {
    move || {
        let (metrics, store, registry) = (metrics.clone(), store.clone(), registry.clone());
        Box::pin(async move {
            match store.meta.count_jobs_by_state().await {
                Ok(counts) => {
                    for (state, n) in counts {
                        metrics.set_jobs(state.as_str(), usize::try_from(n).unwrap_or(usize::MAX));
                    }
                }
                // The scrape still answers, with the previous job counts.
                Err(e) => tracing::warn!(error = %e, "metrics: cannot count jobs"),
            }
            metrics.set_loaded_models(registry.cached_names().len());
        })
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::time::Instant;

    use relreward_proto::v1::{self as pb, reward_service_client::RewardServiceClient};
    use tokio_stream::wrappers::ReceiverStream;

    use super::*;

    /// At shutdown an open GradientStream (whose client never closes its side) answers what
    /// it had in flight and ends UNAVAILABLE when the listener closes, and `run` returns well
    /// within the grace: no task of the server is left that nobody stops.
    #[tokio::test(flavor = "multi_thread")]
    async fn an_open_gradient_stream_ends_unavailable_at_shutdown_and_run_returns() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let overrides = config::Overrides { data_dir: Some(tmp.path().join("data")), ..Default::default() };
        let env = ::config::Environment::with_prefix("RELREWARD").source(Some(HashMap::from([
            ("RELREWARD__METRICS__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
            ("RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS".to_owned(), "0".to_owned()),
        ])));
        let config = Config::load_with_env(None, &overrides, env).expect("config");
        let grace = Duration::from_secs(config.server.shutdown_grace_secs);
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("address");
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let shutdown = async move {
            let _ = stopped.await;
        };
        let server = tokio::spawn(run(config, listener, shutdown, std::future::pending()));

        let mut client = RewardServiceClient::connect(format!("http://{addr}")).await.expect("connect");
        let (requests, outbound) = tokio::sync::mpsc::channel(4);
        // Refused in-stream (no x), and the stream goes on.
        let request = pb::GradientRequest { model: "absent".into(), request_id: 7, ..Default::default() };
        requests.send(request).await.expect("queue a request");
        let mut responses =
            client.gradient_stream(ReceiverStream::new(outbound)).await.expect("open the stream").into_inner();
        let first = responses.message().await.expect("an answer").expect("one response");
        assert_eq!(first.request_id, 7);
        let error = first.error.expect("an in-stream error");
        assert_eq!((error.code, error.message.as_str()), (tonic::Code::InvalidArgument as i32, "x: missing"));

        let signalled = Instant::now();
        stop.send(()).expect("signal");
        let end = responses.message().await.expect_err("the stream ends with a status");
        assert_eq!(end.code(), tonic::Code::Unavailable, "{end:?}");
        assert!(end.message().contains("shutting down"), "{}", end.message());
        server.await.expect("join").expect("run");
        assert!(signalled.elapsed() < grace / 2, "run returned after {:?}", signalled.elapsed());
        drop(requests);
    }
}

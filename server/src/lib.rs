//! relreward-server: hosts base and expert diffusion models, extracts relative rewards from
//! them and serves those rewards over gRPC.
//!
//! Module map (each may import the ones below it, never above):
//! - [`security`]: who may call what (bearer tokens, scopes, one tower layer in front of
//!   every service) and TLS; sits above [`api`], which it never imports.
//! - [`api`]: tonic services (relreward.v1 and the Open Inference Protocol); validate and
//!   convert at the door, nothing else.
//! - [`serving`]: Score and Gradient queries: validation, units, the per-model dynamic batcher.
//! - [`engine`]: tensor math on libtorch (tch). Knows nothing of gRPC.
//! - [`jobs`]: the job system (queue, threads, events, checkpoints) and the training runners.
//! - [`store`]: metadata ([`store::MetadataStore`]) and files ([`store::BlobStore`]),
//!   dataset ingestion and crash recovery.
//! - [`limits`]: server-wide limits: connections, call deadlines, the data directory's disk budget.
//! - [`fault`]: the test-only fault-injection hook (`RELREWARD_FAULT`), a no-op when unset.
//! - [`config`]: layered configuration and its validation.
//! - [`metrics`]: Prometheus metrics, the per-call recording layer and the `/metrics` endpoint.
//! - [`error`]: the one error type and its one mapping to gRPC status codes.
//!
//! Entry point: [`run`], which `main` calls with a bound listener and a shutdown future, and
//! tests call with a port-0 listener.

pub mod api;
pub mod config;
pub mod engine;
pub mod error;
pub mod fault;
pub mod jobs;
pub mod limits;
pub mod metrics;
pub mod security;
pub mod serving;
pub mod store;

use std::future::Future;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;

pub use config::Config;

/// Serves until `shutdown` completes, then shuts down gracefully: health goes NOT_SERVING,
/// the listener closes, in-flight calls get `server.shutdown_grace_secs` to finish.
///
/// Unless `metrics.listen` is empty, also serves Prometheus metrics there (bound first, so a
/// taken port fails the start at once) and prints `relreward-server metrics on
/// http://ADDR/metrics` on stdout, the line after `main`'s `listening on` line.
pub async fn run(
    config: Config,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send,
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
    engine::init(&config.engine);
    let store = store::Store::open(&config).await?;
    let role = config.role();
    // On shutdown, jobs stop at their next step (checkpointing first) and resume on the next
    // worker to claim them (this process after a restart, with the embedded store).
    let job_manager =
        jobs::JobManager::start(store.clone(), config.jobs.clone(), role.works(), CancellationToken::new()).await?;
    // Diffusion models, loaded from the store on demand and cached (models.cache_bytes).
    let registry = engine::registry::ModelRegistry::new(store.clone(), &config.models, tch::Device::Cpu);
    // Inference compute (batched Score/Gradient passes and sampling runs) at once.
    let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(config.engine.inference_workers));
    let metrics = metrics::Metrics::new();
    let serving = serving::Serving::new(registry.clone(), config.serving.clone(), slots.clone(), metrics.clone());
    // Stopped after the gRPC drain, or by the guard when `run` returns early.
    let stop_metrics = CancellationToken::new();
    let _stop_metrics_guard = stop_metrics.clone().drop_guard();
    let metrics_endpoint = metrics_listener.map(|listener| {
        let refresh = scrape_refresh(metrics.clone(), store.clone(), registry.clone());
        tokio::spawn(metrics::serve_http(listener, metrics.clone(), refresh, stop_metrics.clone()))
    });

    // A worker ("work") answers health checks only, for its orchestrator's probes.
    let served_services: &[&str] = if role.serves() { api::SERVICE_NAMES } else { &[] };
    let (health, health_service) = tonic_health::server::health_reporter();
    for name in served_services {
        health.set_service_status(*name, ServingStatus::Serving).await;
    }
    health.set_service_status("", ServingStatus::Serving).await;

    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(relreward_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(relreward_proto::INFERENCE_FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(relreward_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(relreward_proto::INFERENCE_FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let stop_accepting = CancellationToken::new();
    // TCP_NODELAY on every accepted connection: without it a small unary response waits for
    // the client's delayed ACK (Nagle), about 40 ms per Gradient call. tonic's own
    // `tcp_nodelay` setting does not apply to a listener passed in.
    let incoming = tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
    let incoming = limits::limit_connections(incoming, config.server.max_connections);
    let mut builder =
        tonic::transport::Server::builder().max_concurrent_streams(Some(config.server.max_concurrent_streams));
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
        api::routes(&config, store, job_manager.clone(), serving, slots)
    } else {
        tonic::service::Routes::default()
    };
    let server = {
        let token = stop_accepting.clone();
        builder
            // Metrics outermost, so refused calls are counted with their status like any other.
            .layer(metrics::GrpcMetricsLayer::new(metrics))
            .layer(security.layer)
            // Inside the security layer: a refused call gets no default deadline.
            .layer(limits::DeadlineLayer::new(config.serving.default_deadline_ms))
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

    tracing::info!("shutdown requested: reporting NOT_SERVING and draining in-flight calls");
    for name in served_services {
        health.set_service_status(*name, ServingStatus::NotServing).await;
    }
    health.set_service_status("", ServingStatus::NotServing).await;
    stop_accepting.cancel();
    let grace = Duration::from_secs(config.server.shutdown_grace_secs);
    job_manager.shutdown(grace).await;
    match tokio::time::timeout(grace, server).await {
        Ok(result) => result?,
        Err(_) => {
            tracing::warn!(grace_secs = grace.as_secs(), "in-flight calls did not finish in time; exiting anyway")
        }
    }
    stop_metrics.cancel();
    if let Some(endpoint) = metrics_endpoint
        && let Err(e) = endpoint.await
    {
        tracing::warn!(error = %e, "metrics endpoint task failed");
    }
    tracing::info!("stopped");
    Ok(())
}

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

/// The gauges read at scrape time: jobs by state (a COUNT in the metadata store) and models
/// in memory.
fn scrape_refresh(
    metrics: metrics::Metrics,
    store: store::Store,
    registry: engine::registry::ModelRegistry,
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

//! `relreward-server [--config FILE] [--listen ADDR] [--data-dir DIR] [--role ROLE]`: loads the layered
//! configuration, sets up logging, binds, and hands over to [`relreward_server::run`] until
//! SIGINT or SIGTERM (a second one cuts the shutdown drain short).
//!
//! `relreward-server token create --scopes read[,train,admin] [--name NAME] [--expires WHEN]`
//! prints a new access token once, with the `security.tokens` entry (its salted hash) to put
//! in the configuration; it needs no configuration and starts no server.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use relreward_server::config::{Config, Overrides};
use relreward_server::security::{self, Scope, tokens};

#[derive(Parser, Debug)]
#[command(
    name = "relreward-server",
    version,
    about = "Extracts relative reward functions from pairs of diffusion models and serves them over gRPC."
)]
struct Args {
    /// TOML configuration file (layered over the built-in defaults, under RELREWARD__* env vars).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Address to listen on (overrides server.listen), e.g. 127.0.0.1:50051; port 0 picks one.
    #[arg(long, value_name = "ADDR")]
    listen: Option<String>,
    /// Data directory (overrides storage.data_dir).
    #[arg(long, value_name = "DIR")]
    data_dir: Option<PathBuf>,
    /// serve (the API; jobs go to the queue), work (runs queued jobs) or all (overrides
    /// server.role; serve and work need storage.backend = "shared").
    #[arg(long, value_name = "ROLE")]
    role: Option<String>,
    #[command(subcommand)]
    command: Option<ServerCommand>,
}

#[derive(Subcommand, Debug)]
enum ServerCommand {
    /// Access tokens for `security.tokens`.
    #[command(subcommand)]
    Token(TokenCommand),
}

#[derive(Subcommand, Debug)]
enum TokenCommand {
    /// Print a new token (once) and the configuration entry holding its salted hash.
    Create {
        /// Comma-separated scopes: read, train, admin (admin includes train, train includes read).
        #[arg(long, value_delimiter = ',', required = true, value_name = "SCOPES")]
        scopes: Vec<String>,
        /// Name shown in logs and refusals [default: token-<8 random hex digits>].
        #[arg(long, value_name = "NAME")]
        name: Option<String>,
        /// When the token stops working: an RFC 3339 time (2027-01-31T00:00:00Z) or a lifetime
        /// from now (90d, 12h, 30m). Default: never.
        #[arg(long, value_name = "WHEN")]
        expires: Option<String>,
    },
}

fn main() -> ExitCode {
    let args = Args::parse();
    if let Some(ServerCommand::Token(TokenCommand::Create { scopes, name, expires })) = args.command {
        return token_create(&scopes, name, expires.as_deref());
    }
    let overrides = Overrides { listen: args.listen, data_dir: args.data_dir, role: args.role };
    let config = match Config::load(args.config.as_deref(), &overrides) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("relreward-server: {e}");
            return ExitCode::from(2);
        }
    };
    // Tokens and TLS files are checked before anything is bound (run() loads them again and
    // logs their warnings): a configuration error, exit status 2 like the ones above.
    if let Err(e) = security::Security::load(&config, config.listen_addr()) {
        eprintln!("relreward-server: {e}");
        return ExitCode::from(2);
    }
    // So is a device that is not there (engine.device = cuda on a machine without a GPU).
    if let Err(e) = relreward_server::engine::check_device(&config.engine) {
        eprintln!("relreward-server: {e}");
        return ExitCode::from(2);
    }
    init_tracing(&config);
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().thread_name("relreward-io").build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("relreward-server: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(serve(config)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!(error = format!("{e:#}"), "relreward-server failed");
            eprintln!("relreward-server: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `token create`: prints the token and its configuration entry on stdout.
fn token_create(scopes: &[String], name: Option<String>, expires: Option<&str>) -> ExitCode {
    let fail = |message: String| {
        eprintln!("relreward-server token create: {message}");
        ExitCode::from(2)
    };
    let mut parsed = Vec::new();
    for s in scopes {
        match Scope::parse(s.trim()) {
            Some(scope) if !parsed.contains(&scope) => parsed.push(scope),
            Some(_) => {}
            None => return fail(format!("--scopes: '{s}' is not a scope (read, train, admin)")),
        }
    }
    let expires = match expires.map(|e| tokens::expiry_from_arg(e, std::time::SystemTime::now())).transpose() {
        Ok(e) => e,
        Err(message) => return fail(format!("--expires: {message}")),
    };
    let new = match tokens::generate() {
        Ok(t) => t,
        Err(e) => return fail(format!("cannot read the system's random source: {e}")),
    };
    // The default name borrows 8 hex digits of the (public) salt: random enough to be unique.
    let name = name.unwrap_or_else(|| format!("token-{}", new.hash.split(':').nth(1).map_or("", |salt| &salt[..8])));
    if let Err(message) = tokens::check_name(&name) {
        return fail(format!("--name: {message}"));
    }
    let entry = tokens::config_entry(&name, &new.hash, &parsed, expires.as_deref());
    println!("token: {}", new.token);
    println!("# Shown once: the server keeps only its salted hash. Give the token to its client");
    println!("# (relreward --token, or RELREWARD_TOKEN) and add this entry to security.tokens");
    println!("# in the server configuration (one entry per token in the list):");
    println!("tokens = [{entry}]");
    ExitCode::SUCCESS
}

async fn serve(config: Config) -> anyhow::Result<()> {
    let addr = config.listen_addr();
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {addr} (server.listen): {e}"))?;
    let local = listener.local_addr()?;
    tracing::info!(
        %local,
        role = config.server.role,
        backend = config.storage.backend,
        data_dir = %config.storage.data_dir.display(),
        "relreward-server listening"
    );
    // The signal handlers go in before the line below announces the server: a SIGTERM sent as
    // soon as the line is read (tests do) must start the drain, not meet the default action,
    // which kills the process (seen once under load: a connection reset during the "drain").
    let (first, second) = shutdown_signals();
    // One machine-readable line on stdout, for scripts and tests that start the server on port 0.
    println!("relreward-server listening on {local}");
    relreward_server::run(config, listener, first, second).await
}

/// Two futures: the first SIGINT or SIGTERM (shut down: health NOT_SERVING, the drain, then
/// the grace for calls in flight), and the next one (cut the drain short, e.g. a second Ctrl-C).
fn shutdown_signals() -> (impl Future<Output = ()> + Send, impl Future<Output = ()> + Send) {
    use tokio::signal::unix::{SignalKind, signal};
    let (first_tx, first_rx) = tokio::sync::oneshot::channel::<()>();
    let (second_tx, second_rx) = tokio::sync::oneshot::channel::<()>();
    // Watched from here on, so that a second signal is never missed between the two.
    let interrupt = signal(SignalKind::interrupt());
    let term = signal(SignalKind::terminate());
    tokio::spawn(async move {
        let (mut interrupt, mut term) = match (interrupt, term) {
            (Ok(i), Ok(t)) => (i, t),
            (i, t) => {
                if let Err(e) = i.as_ref().and(t.as_ref()) {
                    tracing::warn!(error = %e, "cannot watch SIGINT/SIGTERM; falling back to Ctrl-C only");
                }
                let _ = tokio::signal::ctrl_c().await;
                let _ = first_tx.send(());
                let _ = tokio::signal::ctrl_c().await;
                let _ = second_tx.send(());
                return;
            }
        };
        for (i, tx) in [first_tx, second_tx].into_iter().enumerate() {
            let which = tokio::select! {
                _ = interrupt.recv() => "SIGINT",
                _ = term.recv() => "SIGTERM",
            };
            if i == 0 {
                tracing::info!("{which} received");
            } else {
                tracing::info!("{which} received again: ending the drain now");
            }
            let _ = tx.send(());
        }
    });
    // A dropped sender (the task gone) counts as the signal: never hang on shutdown.
    (
        async move {
            let _ = first_rx.await;
        },
        async move {
            let _ = second_rx.await;
        },
    )
}

fn init_tracing(config: &Config) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(&config.log.level));
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(ansi);
    if config.log.format == "json" {
        builder.json().init();
    } else {
        builder.init();
    }
}

//! Fault injection for crash tests: a test hook, not a feature.
//!
//! `RELREWARD_FAULT=<point>` makes the process abort (SIGABRT: no destructors, no flushing,
//! no cleanup, as close to `kill -9` as a process can do to itself) the first time execution
//! reaches the named [`point`]; `RELREWARD_FAULT=<point>:<n>` aborts at its n-th arrival
//! instead (e.g. the second checkpoint, so a first one exists). Unset, every point is a
//! no-op costing one atomic load after the first call.
//!
//! Points (grep for `fault::point(`):
//! - `upload.chunk`: a dataset upload's chunk was written to staging (mid-stream).
//! - `upload.before_publish`, `upload.after_publish`: a dataset's staged files are complete /
//!   published but not yet recorded.
//! - `model.before_publish`, `model.after_publish`: the same for a model (upload or a job's
//!   output).
//! - `checkpoint.before_publish`, `checkpoint.after_publish`, `checkpoint.after_record`: a
//!   checkpoint is staged / published but not recorded / recorded while the previous one is
//!   not yet released.

use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

/// The armed point and after how many arrivals it fires.
struct Armed {
    point: String,
    nth: u64,
    arrivals: AtomicU64,
}

fn armed() -> Option<&'static Armed> {
    static ARMED: OnceLock<Option<Armed>> = OnceLock::new();
    ARMED
        .get_or_init(|| {
            let spec = std::env::var("RELREWARD_FAULT").ok().filter(|s| !s.is_empty())?;
            let (point, nth) = match spec.rsplit_once(':') {
                Some((p, n)) => (p.to_owned(), n.parse().unwrap_or(1)),
                None => (spec, 1),
            };
            Some(Armed { point, nth: nth.max(1), arrivals: AtomicU64::new(0) })
        })
        .as_ref()
}

/// Aborts the process here if `RELREWARD_FAULT` names this point (see the module docs).
pub fn point(name: &str) {
    let Some(armed) = armed() else { return };
    if armed.point != name {
        return;
    }
    if armed.arrivals.fetch_add(1, Ordering::SeqCst) + 1 == armed.nth {
        // stderr is unbuffered: the test reads this line from the server log.
        eprintln!("relreward-server: fault injected at {name}; aborting");
        std::process::abort();
    }
}

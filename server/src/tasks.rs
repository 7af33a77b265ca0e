//! [`Tasks`]: a group of the server's background work, spawned so that shutdown can stop it
//! and wait for it. Nothing in the server is detached: every tokio task, blocking task and
//! long-lived worker thread belongs to one group, which [`crate::run`] owns.
//!
//! A group is a [`TaskTracker`] (what is still running) and a [`CancellationToken`] (when to
//! stop), the token a child of the server's shutdown token, so cancelling the server's token
//! reaches every group and a group can be stopped on its own at its point of the shutdown
//! order (`run`: streams when the listener closes, jobs next, sampling after the grace, the
//! metrics endpoint last). Work sees its group's token and ends promptly once it is cancelled;
//! [`Tasks::stop`] cancels, then waits at most a bound, naming the group if something is left.
//!
//! OS threads that must keep their own name (a job thread, a model's serving thread) join a
//! group with [`Tasks::enlist`]: the returned guard counts as one of the group's tasks until
//! the thread drops it.

use std::future::Future;
use std::time::Duration;

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tokio_util::task::task_tracker::TaskTrackerToken;

/// One group of tracked work with its own stop signal (cheap to clone: clones share both).
#[derive(Clone, Debug)]
pub struct Tasks {
    name: &'static str,
    tracker: TaskTracker,
    token: CancellationToken,
}

impl Tasks {
    /// A group named `name` (in log lines) stopped by `token` (a child of the server's
    /// shutdown token, so the server's shutdown reaches it too).
    pub fn new(name: &'static str, token: CancellationToken) -> Self {
        Self { name, tracker: TaskTracker::new(), token }
    }

    /// A group of its own for a unit test: a fresh token, nothing above it.
    pub fn detached_for_tests(name: &'static str) -> Self {
        Self::new(name, CancellationToken::new())
    }

    /// Cancelled when the group must stop: work checks it, or selects on `cancelled()`.
    pub fn token(&self) -> &CancellationToken {
        &self.token
    }

    /// Spawns `future` on the runtime as one of the group's tasks.
    pub fn spawn<F>(&self, future: F) -> JoinHandle<F::Output>
    where
        F: Future + Send + 'static,
        F::Output: Send + 'static,
    {
        self.tracker.spawn(future)
    }

    /// Runs `f` on the runtime's blocking pool as one of the group's tasks.
    pub fn spawn_blocking<F, T>(&self, f: F) -> JoinHandle<T>
    where
        F: FnOnce() -> T + Send + 'static,
        T: Send + 'static,
    {
        self.tracker.spawn_blocking(f)
    }

    /// A guard that counts as one of the group's tasks until dropped: for a named OS thread,
    /// which moves it in and drops it when it ends.
    pub fn enlist(&self) -> TaskTrackerToken {
        self.tracker.token()
    }

    /// Tasks still running.
    pub fn len(&self) -> usize {
        self.tracker.len()
    }

    /// Whether nothing of the group is running.
    pub fn is_empty(&self) -> bool {
        self.tracker.is_empty()
    }

    /// Waits at most `bound` for the group's work to end, without cancelling it (work that
    /// ends by itself, such as calls in their grace period). Returns whether it all ended.
    pub async fn wait(&self, bound: Duration) -> bool {
        self.tracker.close();
        let ended = tokio::time::timeout(bound, self.tracker.wait()).await.is_ok();
        // Reopened, so that work spawned after a timed-out wait (a shutdown that goes on)
        // is still counted by the next wait.
        self.tracker.reopen();
        ended
    }

    /// Cancels the group's token, then waits at most `bound` for its work to end. Returns
    /// whether it all ended; if not, says how much is left (the process exits anyway).
    pub async fn stop(&self, bound: Duration) -> bool {
        self.token.cancel();
        let ended = self.wait(bound).await;
        if !ended {
            tracing::warn!(
                group = self.name,
                left = self.tracker.len(),
                bound_ms = bound.as_millis() as u64,
                "background work did not stop in time; exiting without it"
            );
        }
        ended
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn stop_cancels_waits_and_counts_enlisted_threads() {
        let server = CancellationToken::new();
        let tasks = Tasks::new("test", server.child_token());
        let token = tasks.token().clone();
        tasks.spawn(async move { token.cancelled().await });
        let (token, guard) = (tasks.token().clone(), tasks.enlist());
        let thread = std::thread::spawn(move || {
            while !token.is_cancelled() {
                std::thread::sleep(Duration::from_millis(5));
            }
            drop(guard);
        });
        assert_eq!(tasks.len(), 2);
        assert!(!tasks.wait(Duration::from_millis(20)).await, "nothing ends before the stop");
        assert!(tasks.stop(Duration::from_secs(5)).await);
        assert!(tasks.is_empty() && !server.is_cancelled(), "a group's stop stays in the group");
        thread.join().expect("thread");

        // The server's token reaches every group.
        let other = Tasks::new("other", server.child_token());
        let token = other.token().clone();
        other.spawn(async move { token.cancelled().await });
        server.cancel();
        assert!(other.wait(Duration::from_secs(5)).await);
    }
}

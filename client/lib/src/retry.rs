//! Retrying over a broken connection: how long to keep trying ([`RetryPolicy`]), the delays
//! between attempts ([`Backoff`]) and which failures are worth another attempt
//! ([`is_retryable`]). Both the connection's idempotent calls ([`crate::client`]) and job
//! watching ([`crate::watch`]) use it, so it depends on neither.

use std::time::Duration;

use tonic::{Code, Status};

/// How long to keep trying to reconnect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetryPolicy {
    /// Delay before the first retry; each further one doubles it.
    pub initial_delay: Duration,
    /// Longest delay between two attempts.
    pub max_delay: Duration,
    /// Give up once the stream has been down this long (reset by every event received).
    pub budget: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        Self {
            initial_delay: Duration::from_millis(250),
            max_delay: Duration::from_secs(5),
            budget: Duration::from_secs(60),
        }
    }
}

/// Exponential backoff within [`RetryPolicy::budget`]. Pure: the caller says how long the
/// stream has been down.
#[derive(Debug, Clone)]
pub struct Backoff {
    policy: RetryPolicy,
    attempt: u32,
}

impl Backoff {
    pub fn new(policy: RetryPolicy) -> Self {
        Self { policy, attempt: 0 }
    }

    /// Attempts made since the last reset.
    pub fn attempt(&self) -> u32 {
        self.attempt
    }

    /// The delay before the next attempt, given how long the stream has been down; `None`
    /// once the budget is spent. The last delay is cut so as not to overrun the budget.
    pub fn next_delay(&mut self, down_for: Duration) -> Option<Duration> {
        let left = self.policy.budget.checked_sub(down_for).filter(|d| !d.is_zero())?;
        let doubled = self.policy.initial_delay.saturating_mul(1u32 << self.attempt.min(20));
        self.attempt = self.attempt.saturating_add(1);
        Some(doubled.min(self.policy.max_delay).min(left))
    }

    /// Back to the first delay (after the stream delivered again).
    pub fn reset(&mut self) {
        self.attempt = 0;
    }
}

/// Whether a failed call or broken stream is worth retrying: the server is unavailable
/// (restarting, shutting down) or the transport failed (a status produced locally from a
/// connection error carries that error as its source). Errors the server chose (NOT_FOUND,
/// UNIMPLEMENTED, ...) are final.
pub fn is_retryable(status: &Status) -> bool {
    match status.code() {
        Code::Unavailable => true,
        Code::Unknown | Code::Internal | Code::Cancelled => {
            let message = status.message();
            std::error::Error::source(status).is_some()
                || message.contains("transport error")
                || message.contains("h2 protocol error")
                || message.contains("connection")
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn broken() -> Status {
        Status::from_error(Box::new(std::io::Error::new(std::io::ErrorKind::ConnectionReset, "connection reset")))
    }

    #[test]
    fn backoff_doubles_up_to_the_cap_within_the_budget() {
        let policy = RetryPolicy {
            initial_delay: Duration::from_millis(250),
            max_delay: Duration::from_secs(2),
            budget: Duration::from_secs(10),
        };
        let mut b = Backoff::new(policy);
        let ms = |d: Option<Duration>| d.map(|d| d.as_millis());
        assert_eq!(ms(b.next_delay(Duration::ZERO)), Some(250));
        assert_eq!(ms(b.next_delay(Duration::from_millis(250))), Some(500));
        assert_eq!(ms(b.next_delay(Duration::from_millis(750))), Some(1000));
        assert_eq!(ms(b.next_delay(Duration::from_secs(2))), Some(2000));
        assert_eq!(ms(b.next_delay(Duration::from_secs(4))), Some(2000));
        assert_eq!(b.attempt(), 5);
        // The last delay stops at the budget; then it is spent.
        assert_eq!(ms(b.next_delay(Duration::from_millis(9500))), Some(500));
        assert_eq!(b.next_delay(Duration::from_secs(10)), None);
        assert_eq!(b.next_delay(Duration::from_secs(11)), None);
        b.reset();
        assert_eq!(ms(b.next_delay(Duration::ZERO)), Some(250));
        // Many attempts never overflow.
        for _ in 0..100 {
            assert!(b.next_delay(Duration::ZERO).is_some());
        }
    }

    #[test]
    fn only_connection_failures_are_retried() {
        assert!(is_retryable(&Status::unavailable("the server is shutting down")));
        assert!(is_retryable(&broken()));
        assert!(is_retryable(&Status::unknown("transport error")));
        assert!(is_retryable(&Status::internal("h2 protocol error: error reading a body from connection")));
        assert!(!is_retryable(&Status::unknown("the model exploded")));
        assert!(!is_retryable(&Status::not_found("job 'x' not found")));
        assert!(!is_retryable(&Status::unimplemented("")));
        assert!(!is_retryable(&Status::invalid_argument("from_seq")));
        assert!(!is_retryable(&Status::failed_precondition("")));
    }
}

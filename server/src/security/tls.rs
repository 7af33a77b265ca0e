//! TLS for the gRPC listener from `[security.tls]`: rustls through tonic (`tls-ring`).
//!
//! The files are read and the rustls configuration is built at start, so a missing file, a
//! key that does not match its certificate or a malformed PEM stops the server with the key
//! named, instead of failing every handshake later.

use std::path::Path;
use std::time::Duration;

use tonic::transport::{Certificate, Identity, ServerTlsConfig};

use super::SecurityError;
use crate::config::TlsConfig;

/// A client that has not finished its handshake by then is dropped (a slow or silent peer
/// must not hold a handshake task forever).
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

fn read(key: &'static str, path: &Path) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|e| SecurityError::new(key, format!("cannot read {}: {e}", path.display())))
}

/// The listener's TLS settings, or `None` for plaintext.
pub fn server_config(tls: &TlsConfig) -> Result<Option<ServerTlsConfig>, SecurityError> {
    if !tls.enabled() {
        return Ok(None);
    }
    let cert = read("security.tls.cert", &tls.cert)?;
    let key = read("security.tls.key", &tls.key)?;
    for (name, pem, marker) in [("security.tls.cert", &cert, "CERTIFICATE"), ("security.tls.key", &key, "PRIVATE KEY")]
    {
        if !String::from_utf8_lossy(pem).contains(marker) {
            return Err(SecurityError::new(name, format!("no PEM {marker} block in the file")));
        }
    }
    let mut config = ServerTlsConfig::new().identity(Identity::from_pem(cert, key)).timeout(HANDSHAKE_TIMEOUT);
    if !tls.client_ca.as_os_str().is_empty() {
        let ca = read("security.tls.client_ca", &tls.client_ca)?;
        if !String::from_utf8_lossy(&ca).contains("CERTIFICATE") {
            return Err(SecurityError::new("security.tls.client_ca", "no PEM CERTIFICATE block in the file"));
        }
        // Required, not optional: with a client CA configured, a connection without a
        // certificate it signed fails the handshake.
        config = config.client_ca_root(Certificate::from_pem(ca)).client_auth_optional(false);
    }
    // Build the rustls acceptor now (tonic parses the PEM here) to report errors at start.
    tonic::transport::Server::builder().tls_config(config.clone()).map_err(|e| {
        SecurityError::new(
            "security.tls",
            format!("cannot use the certificate and key: {}", crate::error::error_chain(&e)),
        )
    })?;
    Ok(Some(config))
}

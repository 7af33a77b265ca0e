//! TLS for the listeners from `[security.tls]`: rustls on ring, through tonic (`tls-ring`) for
//! gRPC and through tokio-rustls for the OIP's HTTP listener ([`http_server_config`]), from the
//! same files with the same rules (mutual TLS included).
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

/// The same settings as [`server_config`] for an HTTP/1.1 listener (`crate::oip_http`), or
/// `None` for plaintext. Called after [`server_config`] has accepted the files, so an error
/// here is one rustls finds that tonic did not.
pub fn http_server_config(tls: &TlsConfig) -> Result<Option<std::sync::Arc<rustls::ServerConfig>>, SecurityError> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    if !tls.enabled() {
        return Ok(None);
    }
    let bad = |key: &'static str| move |e: rustls::pki_types::pem::Error| SecurityError::new(key, format!("{e}"));
    let cert = read("security.tls.cert", &tls.cert)?;
    let chain =
        CertificateDer::pem_slice_iter(&cert).collect::<Result<Vec<_>, _>>().map_err(bad("security.tls.cert"))?;
    let key = PrivateKeyDer::from_pem_slice(&read("security.tls.key", &tls.key)?).map_err(bad("security.tls.key"))?;
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| SecurityError::new("security.tls", e.to_string()))?;
    let builder = if tls.client_ca.as_os_str().is_empty() {
        builder.with_no_client_auth()
    } else {
        let ca = read("security.tls.client_ca", &tls.client_ca)?;
        let mut roots = rustls::RootCertStore::empty();
        for c in CertificateDer::pem_slice_iter(&ca) {
            let c = c.map_err(bad("security.tls.client_ca"))?;
            roots.add(c).map_err(|e| SecurityError::new("security.tls.client_ca", e.to_string()))?;
        }
        // Required, as on the gRPC listener.
        let verifier =
            rustls::server::WebPkiClientVerifier::builder_with_provider(std::sync::Arc::new(roots), provider)
                .build()
                .map_err(|e| SecurityError::new("security.tls.client_ca", e.to_string()))?;
        builder.with_client_cert_verifier(verifier)
    };
    let mut config = builder
        .with_single_cert(chain, key)
        .map_err(|e| SecurityError::new("security.tls", format!("cannot use the certificate and key: {e}")))?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Some(std::sync::Arc::new(config)))
}

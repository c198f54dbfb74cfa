//! The gateway's error type: what stops it from starting or serving. Its own module, below everything that
//! returns it, so that no module reaches up to the crate root for it.

use std::net::SocketAddr;

/// Errors that stop the gateway from starting or serving.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("invalid server URL {0}")]
    ServerUrl(String),
    #[error("TLS: {0}")]
    Tls(String),
    #[error("gateway config: {0}")]
    Config(String),
    #[error("gateway server failed: {0}")]
    Serve(String),
}

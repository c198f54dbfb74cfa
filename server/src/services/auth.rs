//! Bearer-token check for every phone2act service when `server.token` is set.

use std::net::SocketAddr;
use tonic::service::Interceptor;
use tonic::{Request, Status};

/// The warning to print when gRPC listens beyond loopback without a token: anyone who can reach the port
/// can then move the arms. `None` when there is nothing to warn about.
pub fn exposure_warning(listen: SocketAddr, has_token: bool) -> Option<String> {
    if has_token || listen.ip().is_loopback() {
        return None;
    }
    Some(format!(
        "gRPC listens on {listen} without a token: anyone who can reach this address can drive the arms. \
         Set server.token (or PHONE2ACT_SERVER__TOKEN), or listen on 127.0.0.1"
    ))
}

/// Refuses calls without `authorization: Bearer <token>` when a token is configured.
#[derive(Clone, Debug)]
pub struct TokenCheck {
    expected: Option<String>,
}

impl TokenCheck {
    /// A check for `token`; `None` lets every call through.
    pub fn new(token: Option<String>) -> Self {
        Self {
            expected: token.map(|t| format!("Bearer {t}")),
        }
    }
}

impl Interceptor for TokenCheck {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        match request.metadata().get("authorization").map(|v| v.to_str()) {
            Some(Ok(got)) if constant_time_eq(got.as_bytes(), expected.as_bytes()) => Ok(request),
            Some(_) => Err(Status::unauthenticated("wrong token")),
            None => Err(Status::unauthenticated("missing authorization: Bearer <token>")),
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_an_exposed_listener_without_a_token_is_warned_about() {
        let any: SocketAddr = "0.0.0.0:50051".parse().unwrap();
        let lan: SocketAddr = "192.168.1.5:50051".parse().unwrap();
        let local: SocketAddr = "127.0.0.1:50051".parse().unwrap();
        let local6: SocketAddr = "[::1]:50051".parse().unwrap();
        assert!(
            exposure_warning(any, false)
                .unwrap()
                .contains("0.0.0.0:50051 without a token")
        );
        assert!(exposure_warning(lan, false).is_some());
        assert!(exposure_warning(any, true).is_none());
        assert!(exposure_warning(local, false).is_none());
        assert!(exposure_warning(local6, false).is_none());
    }
}

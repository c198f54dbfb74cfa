//! The phone gateway: each WebSocket client (the Phone2Act Android app over rosbridge v2, roslibjs/roslibpy,
//! or the zero-install WebXR phone page) becomes a `Teleop.Stream` to the phone2act server.
//!
//! ```no_run
//! # async fn demo() -> Result<(), phone2act_gateway::GatewayError> {
//! use phone2act_gateway::{GatewayConfig, serve};
//! serve(GatewayConfig::default(), "http://127.0.0.1:50051".into(), None, async {
//!     let _ = tokio::signal::ctrl_c().await;
//! })
//! .await
//! # }
//! ```
//!
//! Tests bind port 0 themselves and use [`Gateway::with_listeners`], which also reports the pairing token.

// Every byte here comes from the network: slicing a `str` by byte index panics on a multi-byte character.
#![deny(clippy::string_slice)]

pub mod config;
mod conn;
mod error;
pub mod feedback;
/// A stand-in server for tests and `gateway-bench` only: not in the product (`--features mock`).
#[cfg(feature = "mock")]
pub mod mock_server;
mod native;
pub mod pairing;
mod ros_topics;
pub mod rosbridge;
mod rosbridge_conn;
mod server;
pub mod session;
mod shared;
pub mod takeover;
pub mod tls;
mod upstream;
mod web;
mod web_preview;
mod webrtc;

pub use config::{GatewayConfig, TopicConfig, VideoConfig};
pub use error::GatewayError;
pub use server::{Gateway, GatewayInfo, Listeners};
use std::future::Future;

/// Binds the listeners `config` enables and serves until `shutdown` resolves.
///
/// `server_url` is the phone2act gRPC server (`http://127.0.0.1:50051`); `grpc_token` its bearer token.
/// With `enabled = false` nothing is bound and this just waits for `shutdown`, so a caller can run it
/// unconditionally next to the gRPC server.
pub async fn serve(
    config: GatewayConfig,
    server_url: String,
    grpc_token: Option<String>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), GatewayError> {
    if !config.enabled {
        shutdown.await;
        return Ok(());
    }
    Gateway::bind(config, &server_url, grpc_token.as_deref())
        .await?
        .run(shutdown)
        .await
}

//! Typed async client for the phone2act.v1 API. `Client::connect` opens one HTTP/2 channel; the typed
//! service handles (`system()`, and the raw generated clients for the other services) share it. An optional
//! bearer token is attached to every call.
//!
//! One module per service (`system`, `episodes`, `scene`, `teleop`, `policy`), each adding its handles to
//! [`Client`]; `client` is the connection and `local` the in-process way to a server in the same process.

mod client;
mod episodes;
mod local;
mod policy;
mod scene;
mod system;
mod teleop;

pub use client::{AuthChannel, AuthInterceptor, Client, ConnectOptions};
pub use episodes::EpisodesApi;
pub use local::{LocalIncoming, Transport};
pub use policy::PolicySession;
pub use scene::SceneApi;
pub use system::SystemApi;
pub use teleop::{TeleopEvent, TeleopLink, TeleopOptions, TeleopSession};

/// Button-event constructors (shared with the gateway and the server's tests).
pub use phone2act_proto::buttons;
/// The short name of a recording phase, as status displays show it.
pub use phone2act_proto::convert_episode::phase_name;
pub use phone2act_proto::v1 as proto;

/// Errors from the client.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The URL could not be parsed or the connection could not be made. The reason is the error's
    /// `source()` (print the chain, e.g. anyhow's `{:#}`), not repeated in its own message.
    #[error("cannot connect to {url}")]
    Connect {
        url: String,
        #[source]
        source: tonic::transport::Error,
    },
    /// The token contains characters not allowed in an HTTP header.
    #[error("token is not a valid header value")]
    BadToken,
    /// The server ended a stream or sent something out of protocol.
    #[error("protocol: {0}")]
    Protocol(String),
    /// The session's stream is closed (the server ended it or the connection dropped).
    #[error("session closed")]
    Closed,
    /// The server answered with an error status. Displayed as `Code: message` once; the status is not
    /// also chained as a source, which would print the same message a second time in `{:#}` chains.
    #[error("{:?}: {}", .0.code(), .0.message())]
    Status(tonic::Status),
}

impl From<tonic::Status> for Error {
    fn from(status: tonic::Status) -> Self {
        Self::Status(status)
    }
}

/// The URL to dial for a target given as `host:port`, `http://host:port` or `https://host:port`: a target
/// without a scheme means plaintext HTTP/2, the server's default.
pub fn normalize_url(target: &str) -> String {
    let target = target.trim();
    if target.contains("://") {
        target.to_owned()
    } else {
        format!("http://{target}")
    }
}

/// Result alias for this crate.
pub type Result<T> = std::result::Result<T, Error>;

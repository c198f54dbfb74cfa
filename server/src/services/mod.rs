//! Thin tonic adapters: each service translates wire messages to calls on [`crate::app::App`].

// The two modules that may build a `tonic::Status` (server/clippy.toml refuses it everywhere else).
#[allow(clippy::disallowed_methods)]
pub mod auth;
pub mod bridge;
pub mod cameras;
pub mod convert;
pub mod episodes;
#[allow(clippy::disallowed_methods)]
pub mod error;
pub mod policy;
pub mod scene;
pub mod system;
pub mod teleop;

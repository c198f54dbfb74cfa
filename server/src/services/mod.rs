//! Thin tonic adapters: each service translates wire messages to calls on [`crate::app::App`].

pub mod auth;
pub mod bridge;
pub mod cameras;
pub mod convert;
pub mod episodes;
pub mod error;
pub mod policy;
pub mod scene;
pub mod system;
pub mod teleop;

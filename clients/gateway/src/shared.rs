//! State shared by every socket of the gateway (its config, the upstream client, pairing and take-over
//! holders). Its own module so that the per-protocol handlers and the listener wiring both depend on it
//! instead of on each other.

use crate::config::GatewayConfig;
use crate::pairing::Pairing;
use crate::takeover::Holders;
use crate::upstream::Upstream;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::sync::watch;

/// State shared by every socket.
#[derive(Debug)]
pub(crate) struct Shared {
    pub config: GatewayConfig,
    pub upstream: Upstream,
    pub token: Option<String>,
    pub pairing: Pairing,
    pub holders: Holders,
    /// The port rosbridge really listens on (the page names it for the Phone2Act app), if served.
    pub rosbridge_port: Option<u16>,
    /// The cameras' WebRTC feeds for the pages' live video; its runtime also runs the other camera work.
    pub(crate) video: crate::webrtc::VideoHub,
    /// Run the rosbridge camera images' fetches on the control path's runtime instead of the video's: only
    /// for measuring what the video runtime spares the control path (see [`crate::Gateway`]).
    pub(crate) images_on_control_runtime: bool,
    pub(crate) connections: AtomicU64,
    pub(crate) shutdown: watch::Receiver<bool>,
}

impl Shared {
    /// Where camera work of the sockets runs (the page's preview, rosbridge's image topics): the video
    /// runtime and its own connection to the server, off the control path's thread.
    pub(crate) fn camera_runtime(&self) -> (tokio::runtime::Handle, crate::upstream::Upstream) {
        self.video.background(&self.upstream)
    }

    /// A fresh id for a socket.
    pub(crate) fn next_connection(&self) -> u64 {
        self.connections.fetch_add(1, Ordering::Relaxed)
    }

    /// How long a rosbridge arm holder must be silent before its own address may take the arm over.
    pub(crate) fn takeover_silence(&self) -> Duration {
        Duration::from_millis(self.config.takeover_silence_ms)
    }
}

//! One phone ↔ one arm: the SDK's [`TeleopLink`](phone2act_sdk::TeleopLink), a `Teleop.Stream` fed from its
//! depth-1 latest-wins outbox and kept alive across server restarts. The gateway passes the phone's own seq
//! through, so the phone's feedback echoes it.

use crate::upstream::Upstream;
use tokio::sync::mpsc;

/// What a session reports to its WebSocket connection.
pub type SessionEvent = phone2act_sdk::TeleopEvent;

/// A running teleop session for one arm. Dropping it closes the gRPC stream.
pub type Session = phone2act_sdk::TeleopLink;

/// Starts the session of `arm` on the shared connection; it connects on the first sample.
pub fn start(upstream: &Upstream, arm: &str, events: mpsc::Sender<SessionEvent>) -> Session {
    upstream.client().teleop_link(arm, events)
}

//! Small helpers between the tokio runtime and the synchronous domain: waiting for shutdown, and running
//! blocking work from async code.

use tokio::sync::watch;

/// Resolves once shutdown has begun (a `Send`-friendly wrapper around `watch::Receiver::wait_for`).
pub async fn stopped(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

/// Runs blocking work from async code without stalling the runtime's other tasks where the runtime allows.
pub fn blocking<R>(f: impl FnOnce() -> R) -> R {
    match tokio::runtime::Handle::try_current() {
        Ok(handle) if handle.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(f)
        }
        _ => f(),
    }
}

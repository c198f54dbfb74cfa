//! What the `phone2act` binary's test files share: a served binary that is killed with its test.

use parking_lot::Mutex;
use std::io::{BufRead, BufReader};
use std::process::Child;
use std::sync::Arc;
use std::time::Duration;

/// A `phone2act serve` subprocess and its gRPC URL; killed when dropped.
pub(crate) struct Served {
    pub(crate) child: Child,
    pub(crate) url: String,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Waits up to `wait` for the spawned `serve` (stderr piped) to print its address; its stderr lines go to
/// `log` for as long as it runs.
pub(crate) fn served(mut child: Child, log: Arc<Mutex<Vec<String>>>, wait: Duration) -> Served {
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(addr) = line.strip_prefix("phone2act: gRPC on ") {
                let _ = tx.send(addr.to_owned());
            }
            log.lock().push(line);
        }
    });
    let addr = rx.recv_timeout(wait).expect("server printed its address");
    Served {
        child,
        url: format!("http://{addr}"),
    }
}

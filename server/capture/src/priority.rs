//! Lower CPU priority for threads whose work may wait for the control path's: the live video's threads and a
//! generated camera that nobody records. On Linux nice is per thread, and threads a thread starts inherit it;
//! raising it again needs a privilege, so a thread that must sometimes run at full priority hands the work to
//! a lowered thread instead of lowering itself (as the camera module does).

/// How many nice steps below the control path background work runs: at nice +10 a thread gets about a tenth
/// of the CPU share of a nice 0 thread that wants the same core.
pub const BACKGROUND_NICE: i32 = 10;

/// Lowers the calling thread's CPU priority by `steps` nice steps (at most to 19). Elsewhere than Linux, or if
/// the system refuses, the thread keeps its priority (logged at debug level: the work still gets done).
pub fn lower_current_thread(steps: i32) {
    #[cfg(target_os = "linux")]
    {
        use rustix::process::{getpriority_process, setpriority_process};
        let tid = rustix::thread::gettid();
        let now = getpriority_process(Some(tid)).unwrap_or(0);
        if let Err(e) = setpriority_process(Some(tid), (now + steps).min(19)) {
            tracing::debug!("thread keeps its priority: {e}");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = steps;
}

/// The calling thread's nice value, where the system tells it (Linux).
pub fn current_thread_nice() -> Option<i32> {
    #[cfg(target_os = "linux")]
    {
        rustix::process::getpriority_process(Some(rustix::thread::gettid())).ok()
    }
    #[cfg(not(target_os = "linux"))]
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn a_lowered_thread_and_the_threads_it_starts_run_nicer() {
        let before = current_thread_nice().unwrap();
        let (own, child) = std::thread::spawn(|| {
            lower_current_thread(BACKGROUND_NICE);
            let own = current_thread_nice();
            let child = std::thread::spawn(current_thread_nice).join().unwrap();
            (own, child)
        })
        .join()
        .unwrap();
        let expected = (before + BACKGROUND_NICE).min(19);
        assert_eq!((own, child), (Some(expected), Some(expected)));
        assert_eq!(
            current_thread_nice(),
            Some(before),
            "the caller's own priority is untouched"
        );
    }
}

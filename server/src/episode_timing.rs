//! The shell of `[recorder] episode_time_s` / `reset_time_s`: feeds the core's episode clock (held in
//! [`crate::recording::EpisodeTiming`]) the recorder's state and carries out its steps.

use crate::app::App;
use crate::recording::RecordingError;
use phone2act_clock::monotonic_ns;
use phone2act_core::episode_clock::Step;
use phone2act_dataset::error::RecorderError;
use std::sync::Arc;
use std::time::Duration;

/// How often the clock looks at the recorder besides its changes: the countdown's resolution and how late a
/// reset period may end.
const TIMING_POLL: Duration = Duration::from_millis(50);

/// Runs `[recorder] episode_time_s` / `reset_time_s` until shutdown: feeds the clock the recorder's state and
/// carries out its steps (a save as Stop does it, a scene reset that does not move the arm, the next start).
pub async fn run_episode_timing(app: Arc<App>) {
    let Ok(mut changes) = app.recorder_changes() else {
        return;
    };
    let mut shutdown = app.shutdown_signal();
    loop {
        let Some(status) = app.recorder_status() else {
            return;
        };
        let timing = app.episode_timing();
        if let Some(step) = timing.observe(&status, monotonic_ns()) {
            let worker = Arc::clone(&app);
            let last = timing.last_episode();
            let done = tokio::task::spawn_blocking(move || carry_out(&worker, step, &last)).await;
            if let Ok(Err(e)) = done {
                tracing::warn!(?step, error = %e, "episode timing step failed");
            }
        }
        tokio::select! {
            changed = changes.changed() => if changed.is_err() { return },
            () = tokio::time::sleep(TIMING_POLL) => {}
            () = crate::runtime::stopped(&mut shutdown) => return,
        }
    }
}

fn carry_out(app: &App, step: Step, (task, operator): &(String, String)) -> Result<(), String> {
    match step {
        Step::SaveEpisode => {
            tracing::info!("episode time limit reached: saving");
            // The operator may have stopped it in the meantime: nothing to save is no error.
            match app.with_recorder(|r| r.stop_episode().map_err(RecordingError::from)) {
                Ok(_) | Err(RecordingError::Recorder(RecorderError::NotRecording)) => Ok(()),
                Err(e) => Err(e.to_string()),
            }
        }
        Step::ResetScenes => {
            // Scenes re-draw in place; the arm is not homed (nothing moves a robot the operator did not move).
            for arm in app.arms().iter().filter(|a| a.has_scene()) {
                arm.reset_scene(None, false)
                    .map_err(|e| format!("arm {}: scene reset: {e}", arm.name))?;
            }
            Ok(())
        }
        Step::StartNext => {
            tracing::info!(task = %task, "reset period over: starting the next episode");
            app.with_recorder(|r| r.start_episode_by(task, operator).map_err(RecordingError::from))
                .map(drop)
                .map_err(|e| e.to_string())
        }
    }
}

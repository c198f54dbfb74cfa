//! The running server's state: arms, cameras, the recorder and the shutdown signal. Services hold an
//! `Arc<App>` and read snapshots from it.

use crate::config::{CameraKind, Config};
use phone2act_proto::v1;
use phone2act_recorder::camera::{CaptureThread, FrameSlot, spawn_test_pattern};
use phone2act_recorder::clock::monotonic_ns;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tokio::sync::watch;

/// One configured arm.
#[derive(Debug)]
pub struct ArmRuntime {
    pub name: String,
    pub bridge_kind: &'static str,
    state: Mutex<v1::ArmState>,
}

impl ArmRuntime {
    /// A snapshot of the arm's state.
    pub fn snapshot(&self) -> v1::ArmState {
        let mut state = self
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        if state.feedback_time_ns > 0 {
            state.feedback_age_s = (monotonic_ns() - state.feedback_time_ns) as f64 * 1e-9;
        }
        state
    }
}

/// One configured camera and its capture thread.
#[derive(Debug)]
pub struct CameraRuntime {
    pub config: crate::config::CameraConfig,
    pub slot: Arc<FrameSlot>,
    capture: Mutex<Option<CaptureThread>>,
}

impl CameraRuntime {
    /// Health snapshot.
    pub fn status(&self) -> v1::CameraStatus {
        let now = monotonic_ns();
        let latest = self.slot.latest();
        let age_s = latest
            .as_ref()
            .map_or(f64::INFINITY, |f| (now - f.capture_time_ns) as f64 * 1e-9);
        let freshness_s = 3.0 / self.config.fps;
        v1::CameraStatus {
            camera: self.config.name.clone(),
            kind: self.config.kind.as_str().to_owned(),
            width: self.config.width,
            height: self.config.height,
            fps: self.config.fps,
            live: age_s <= freshness_s,
            frames_captured: self.slot.frames_captured(),
            last_frame_age_s: if age_s.is_finite() { age_s } else { -1.0 },
            measured_fps: 0.0,
            error: String::new(),
        }
    }
}

/// Everything the services share.
#[derive(Debug)]
pub struct App {
    pub config: Config,
    pub started: Instant,
    pub arms: Vec<ArmRuntime>,
    pub cameras: Vec<CameraRuntime>,
    shutdown_tx: watch::Sender<bool>,
}

/// Errors starting the app.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    #[error("camera {camera}: {message}")]
    Camera { camera: String, message: String },
}

impl App {
    /// Starts camera threads and arm bridges for `config`.
    pub fn start(config: Config) -> Result<Self, AppError> {
        let arms = config
            .arms
            .iter()
            .map(|arm| ArmRuntime {
                name: arm.name.clone(),
                bridge_kind: arm.bridge.as_str(),
                state: Mutex::new(v1::ArmState {
                    arm: arm.name.clone(),
                    bridge_kind: arm.bridge.as_str().to_owned(),
                    health: v1::BridgeHealth::Connecting as i32,
                    owner: v1::ControlSource::None as i32,
                    ..v1::ArmState::default()
                }),
            })
            .collect();
        let mut cameras = Vec::new();
        for cam in &config.cameras {
            let slot = Arc::new(FrameSlot::default());
            let capture = match cam.kind {
                CameraKind::TestPattern => Some(
                    spawn_test_pattern(&cam.name, cam.width, cam.height, cam.fps, Arc::clone(&slot))
                        .map_err(|e| AppError::Camera {
                            camera: cam.name.clone(),
                            message: e.to_string(),
                        })?,
                ),
                CameraKind::V4l2 | CameraKind::SimRender | CameraKind::Remote => None,
            };
            cameras.push(CameraRuntime {
                config: cam.clone(),
                slot,
                capture: Mutex::new(capture),
            });
        }
        let (shutdown_tx, _) = watch::channel(false);
        Ok(Self {
            config,
            started: Instant::now(),
            arms,
            cameras,
            shutdown_tx,
        })
    }

    /// Looks up an arm by name.
    pub fn arm(&self, name: &str) -> Option<&ArmRuntime> {
        self.arms.iter().find(|a| a.name == name)
    }

    /// A full status snapshot.
    pub fn status(&self, sequence: u64) -> v1::SystemStatus {
        v1::SystemStatus {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            server_time_ns: monotonic_ns(),
            uptime_s: self.started.elapsed().as_secs_f64(),
            arms: self.arms.iter().map(ArmRuntime::snapshot).collect(),
            cameras: self.cameras.iter().map(CameraRuntime::status).collect(),
            recording: Some(self.recording_status()),
            sequence,
        }
    }

    /// The recorder's state.
    pub fn recording_status(&self) -> v1::RecordingStatus {
        v1::RecordingStatus {
            phase: v1::RecordingPhase::Idle as i32,
            dataset_root: self.config.recorder.root.display().to_string(),
            dataset_format: self.config.recorder.format.as_str().to_owned(),
            fps: self.config.recorder.fps,
            ..v1::RecordingStatus::default()
        }
    }

    /// A receiver that turns `true` when shutdown begins; streaming RPCs end on it.
    pub fn shutdown_signal(&self) -> watch::Receiver<bool> {
        self.shutdown_tx.subscribe()
    }

    /// Tells every stream to end.
    pub fn begin_shutdown(&self) {
        self.shutdown_tx.send_replace(true);
    }

    /// Stops capture threads and bridges.
    pub fn stop(&self) {
        self.begin_shutdown();
        for cam in &self.cameras {
            if let Some(capture) = cam
                .capture
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .take()
            {
                capture.stop();
            }
        }
    }
}

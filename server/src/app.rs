//! The running server's state: arm controllers, cameras, the recorder, open sessions and the shutdown
//! signal. Services hold an `Arc<App>`.

use crate::arm::ArmController;
use crate::config::{BridgeKind, CameraKind, Config};
use crate::services::policy::PolicySessionState;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use phone2act_bridges::Bridge;
use phone2act_proto::v1;
use phone2act_recorder::camera::{CaptureThread, FrameSlot, spawn_generated, spawn_test_pattern};
use phone2act_recorder::clock::monotonic_ns;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use tokio::sync::watch;

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
        let age_s = latest.as_ref().map_or(f64::INFINITY, |f| (now - f.capture_time_ns) as f64 * 1e-9);
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
pub struct App {
    pub config: Config,
    pub started: Instant,
    pub arms: Vec<Arc<ArmController>>,
    pub cameras: Vec<CameraRuntime>,
    /// Remote bridges by arm name, for `Bridge.Attach`.
    pub remote_bridges: HashMap<String, Arc<dyn Bridge>>,
    sessions: AtomicU64,
    observations: AtomicU64,
    policies: Mutex<HashMap<u64, Arc<PolicySessionState>>>,
    shutdown_tx: watch::Sender<bool>,
}

impl std::fmt::Debug for App {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("App").field("arms", &self.arms).field("cameras", &self.cameras).finish_non_exhaustive()
    }
}

/// Errors starting the app.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    #[error("camera {camera}: {message}")]
    Camera { camera: String, message: String },
    #[error("arm {arm}: {message}")]
    Arm { arm: String, message: String },
}

/// Where an arm holds before its bridge reports a pose: the SO-101 workspace centre, gripper down.
fn fallback_pose() -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(0.25, 0.0, 0.15), UnitQuaternion::identity())
}

impl App {
    /// Starts bridges, arm controllers and camera threads for `config`.
    pub fn start(config: Config) -> Result<Self, AppError> {
        let mut arms = Vec::new();
        let remote_bridges = HashMap::new();
        let mut sims: HashMap<String, Arc<phone2act_bridges::sim::SimBridge>> = HashMap::new();
        for arm in &config.arms {
            let arm_err = |message: String| AppError::Arm { arm: arm.name.clone(), message };
            let bridge: Arc<dyn Bridge> = match arm.bridge {
                BridgeKind::Sim => {
                    let sim = phone2act_bridges::sim::SimBridge::start(arm.sim.clone().unwrap_or_default())
                        .map_err(|e| arm_err(e.to_string()))?;
                    sims.insert(arm.name.clone(), Arc::clone(&sim));
                    sim
                }
                BridgeKind::Remote | BridgeKind::Dobot | BridgeKind::So101 => {
                    return Err(arm_err(format!("bridge {:?} is not wired into the server yet", arm.bridge.as_str())));
                }
            };
            wait_for_feedback(bridge.as_ref(), Duration::from_millis(500));
            let controller = ArmController::new(
                &arm.name,
                arm.bridge.as_str(),
                bridge,
                &arm.teleop,
                &arm.chunk,
                arm.action_mode,
                fallback_pose(),
            )
            .map_err(|e| arm_err(e.to_string()))?;
            arms.push(Arc::new(controller));
        }
        let mut cameras = Vec::new();
        for cam in &config.cameras {
            let cam_err = |message: String| AppError::Camera { camera: cam.name.clone(), message };
            let slot = Arc::new(FrameSlot::default());
            let capture = match cam.kind {
                CameraKind::TestPattern => Some(
                    spawn_test_pattern(&cam.name, cam.width, cam.height, cam.fps, Arc::clone(&slot))
                        .map_err(|e| cam_err(e.to_string()))?,
                ),
                CameraKind::SimRender => {
                    let sim = match &cam.arm {
                        Some(name) => sims.get(name).cloned(),
                        None => sims.values().next().cloned(),
                    }
                    .ok_or_else(|| cam_err("kind \"sim_render\" needs a simulated arm (set `arm`)".to_owned()))?;
                    let (w, h) = (cam.width, cam.height);
                    Some(
                        spawn_generated(
                            &cam.name,
                            w,
                            h,
                            cam.fps,
                            move |_seq, out| sim.render_rgb(w, h, out),
                            Arc::clone(&slot),
                        )
                        .map_err(|e| cam_err(e.to_string()))?,
                    )
                }
                CameraKind::V4l2 => return Err(cam_err("v4l2 capture is not wired yet".to_owned())),
                CameraKind::Remote => None,
            };
            cameras.push(CameraRuntime { config: cam.clone(), slot, capture: Mutex::new(capture) });
        }
        let (shutdown_tx, _) = watch::channel(false);
        Ok(Self {
            config,
            started: Instant::now(),
            arms,
            cameras,
            remote_bridges,
            sessions: AtomicU64::new(1),
            observations: AtomicU64::new(1),
            policies: Mutex::new(HashMap::new()),
            shutdown_tx,
        })
    }

    /// Looks up an arm by name.
    pub fn arm(&self, name: &str) -> Option<Arc<ArmController>> {
        self.arms.iter().find(|a| a.name == name).cloned()
    }

    /// Configured arm names in order.
    pub fn arm_names(&self) -> Vec<String> {
        self.arms.iter().map(|a| a.name.clone()).collect()
    }

    /// A fresh session id (teleop and policy share the counter).
    pub fn next_session_id(&self) -> u64 {
        self.sessions.fetch_add(1, Ordering::Relaxed)
    }

    /// A fresh observation id (never 0: 0 means "no observation" in chunks).
    pub fn next_observation_id(&self) -> u64 {
        self.observations.fetch_add(1, Ordering::Relaxed)
    }

    pub(crate) fn register_policy(&self, session: Arc<PolicySessionState>) {
        self.policies.lock().unwrap_or_else(PoisonError::into_inner).insert(session.id, session);
    }

    pub(crate) fn unregister_policy(&self, id: u64) {
        self.policies.lock().unwrap_or_else(PoisonError::into_inner).remove(&id);
    }

    pub(crate) fn policy_session(&self, id: u64) -> Option<Arc<PolicySessionState>> {
        self.policies.lock().unwrap_or_else(PoisonError::into_inner).get(&id).cloned()
    }

    /// A full status snapshot.
    pub fn status(&self, sequence: u64) -> v1::SystemStatus {
        v1::SystemStatus {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            server_time_ns: monotonic_ns(),
            uptime_s: self.started.elapsed().as_secs_f64(),
            arms: self.arms.iter().map(|a| a.snapshot()).collect(),
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

    /// The task of the episode in progress.
    pub fn current_task(&self) -> String {
        String::new()
    }

    /// Applies a record button from a phone.
    pub fn record_command(&self, command: &v1::RecordCommand) -> Result<(), String> {
        Err(format!("recording is not available yet (command {})", command.kind))
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
            if let Some(capture) = cam.capture.lock().unwrap_or_else(PoisonError::into_inner).take() {
                capture.stop();
            }
        }
        for arm in &self.arms {
            arm.bridge.shutdown();
        }
    }
}

fn wait_for_feedback(bridge: &dyn Bridge, timeout: Duration) {
    let deadline = Instant::now() + timeout;
    while bridge.feedback().is_none() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Resolves once shutdown has begun (a `Send`-friendly wrapper around `watch::Receiver::wait_for`).
pub async fn stopped(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

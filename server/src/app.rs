//! The running server's state: arm controllers, cameras, the recorder, open sessions and the shutdown
//! signal. Services hold an `Arc<App>`.

use crate::arm::ArmController;
use crate::config::{BridgeKind, CameraConfig, CameraKind, Config};
use crate::recording::RecordingError;
use crate::runtime::blocking;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use parking_lot::{Mutex, RwLock};
use phone2act_bridges::Bridge;
use phone2act_bridges::remote::RemoteBridge;
use phone2act_capture::camera::{CaptureThread, FrameSlot, spawn_generated, spawn_test_pattern};
use phone2act_clock::monotonic_ns;
use phone2act_proto::convert_episode::RecordAction;
use phone2act_recorder::recorder::{Recorder, RecorderStatus};
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// One configured camera and its capture thread.
#[derive(Debug)]
pub struct CameraRuntime {
    config: CameraConfig,
    slot: Arc<FrameSlot>,
    capture: Mutex<Option<CaptureThread>>,
}

/// How a camera is doing right now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraHealth {
    /// A frame arrived within three frame periods, or the camera is a generated one parked for want of
    /// readers (it draws on the next read).
    pub live: bool,
    pub frames_captured: u64,
    /// Age of the newest frame; `None` before the first.
    pub last_frame_age_s: Option<f64>,
}

impl CameraRuntime {
    /// The camera's configuration.
    pub fn config(&self) -> &CameraConfig {
        &self.config
    }

    /// Where its newest frame is.
    pub fn slot(&self) -> &Arc<FrameSlot> {
        &self.slot
    }

    /// Health snapshot.
    pub fn health(&self) -> CameraHealth {
        let now = monotonic_ns();
        // A peek, not a read: a status watcher must not keep an unwatched camera drawing.
        let age_s = self.slot.peek().map(|f| (now - f.capture_time_ns) as f64 * 1e-9);
        let freshness_s = 3.0 / self.config.fps;
        CameraHealth {
            // A parked generated camera is idle, not dead: the next read draws a frame.
            live: age_s.is_some_and(|a| a <= freshness_s) || (age_s.is_some() && self.slot.parked()),
            frames_captured: self.slot.frames_captured(),
            last_frame_age_s: age_s,
        }
    }
}

/// Everything the services share.
pub struct App {
    config: Config,
    started: Instant,
    arms: Vec<Arc<ArmController>>,
    cameras: Vec<CameraRuntime>,
    /// Remote bridges by arm name, for `Bridge.Attach`.
    remote_bridges: HashMap<String, Arc<RemoteBridge>>,
    sessions: AtomicU64,
    /// Read-locked for every use; write-locked only to close it at shutdown.
    recorder: RwLock<Option<Recorder>>,
    shutdown_tx: watch::Sender<bool>,
    /// The recorder's status version, published by one thread for every `Episodes.Watch` stream.
    recorder_version: std::sync::OnceLock<watch::Receiver<u64>>,
    /// `[storage]`: uploads every committed episode.
    uploader: Option<Arc<phone2act_storage::Uploader>>,
    /// `[recorder] episode_time_s` / `reset_time_s`.
    episode_timing: crate::recording::EpisodeTiming,
}

impl std::fmt::Debug for App {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("App")
            .field("arms", &self.arms)
            .field("cameras", &self.cameras)
            .finish_non_exhaustive()
    }
}

/// Errors starting the app.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    #[error("camera {camera}: {message}")]
    Camera { camera: String, message: String },
    #[error("arm {arm}: {message}")]
    Arm { arm: String, message: String },
    #[error("recorder: {0}")]
    Recorder(#[from] RecordingError),
    #[error("storage: {0}")]
    Storage(#[from] phone2act_storage::StorageError),
}

/// A name that is not configured.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LookupError {
    #[error("unknown arm {arm:?}; configured arms: {configured}")]
    UnknownArm { arm: String, configured: String },
    #[error("unknown camera {0:?}")]
    UnknownCamera(String),
    #[error("no camera {0:?} with kind = \"remote\" is configured")]
    NotRemoteCamera(String),
    #[error("arm {arm:?} is not configured with bridge = \"remote\" (remote arms: {remote})")]
    NotRemoteArm { arm: String, remote: String },
}

/// Where an arm holds before its bridge reports a pose: the SO-101 workspace centre, gripper down.
fn fallback_pose() -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(0.25, 0.0, 0.15), UnitQuaternion::identity())
}

impl App {
    /// Starts bridges, arm controllers and camera threads for `config`.
    pub fn start(config: Config) -> Result<Self, AppError> {
        let mut arms = Vec::new();
        let mut remote_bridges = HashMap::new();
        let mut sims: HashMap<String, Arc<phone2act_bridges::sim::SimBridge>> = HashMap::new();
        for arm in &config.arms {
            let arm_err = |message: String| AppError::Arm {
                arm: arm.name.clone(),
                message,
            };
            let joint_speeds = arm
                .joint_speeds_rad_s()
                .map_err(|e| arm_err(format!("joint_limits: {e}")))?;
            let bridge: Arc<dyn Bridge> = match arm.bridge {
                BridgeKind::Sim => {
                    let sim = phone2act_bridges::sim::SimBridge::start_with_clock(
                        arm.sim.clone().unwrap_or_default(),
                        monotonic_ns,
                    )
                    .map_err(|e| arm_err(e.to_string()))?;
                    sims.insert(arm.name.clone(), Arc::clone(&sim));
                    sim
                }
                BridgeKind::Remote => {
                    let joints = arm
                        .remote
                        .as_ref()
                        .map(|r| r.joint_names.clone())
                        .unwrap_or_default();
                    let remote = phone2act_bridges::remote::RemoteBridge::with_joint_names(&arm.name, joints);
                    // The remote robot moves its own joints: the limits are checked on its feedback.
                    if !joint_speeds.is_empty() {
                        remote
                            .watch_joint_speeds(joint_speeds.clone())
                            .map_err(|e| arm_err(e.to_string()))?;
                    }
                    remote_bridges.insert(arm.name.clone(), Arc::clone(&remote));
                    remote
                }
                BridgeKind::Dobot => {
                    let cfg = arm
                        .dobot
                        .clone()
                        .ok_or_else(|| arm_err("bridge \"dobot\" needs an [arms.dobot] table".into()))?;
                    phone2act_bridges::dobot::DobotBridge::start_with_clock(cfg, monotonic_ns)
                        .map_err(|e| arm_err(e.to_string()))?
                }
                BridgeKind::So101 => {
                    let mut cfg = arm
                        .so101
                        .clone()
                        .ok_or_else(|| arm_err("bridge \"so101\" needs an [arms.so101] table".into()))?;
                    // The servos ramp at the same limits the server's commands keep.
                    cfg.max_velocity_rad_s.clone_from(&joint_speeds);
                    phone2act_bridges::so101::So101Bridge::start_with_clock(cfg, monotonic_ns)
                        .map_err(|e| arm_err(e.to_string()))?
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
            // Arms whose kinematics the server knows (SO-101, CR5) get their joints solved and rate-limited
            // here; remote bridges solve their own (docs/joint-limits.md).
            let stage = match arm.bridge {
                BridgeKind::Sim | BridgeKind::So101 => {
                    let weight = match arm.bridge {
                        BridgeKind::Sim => arm.sim.as_ref().map_or(1.0, |c| c.ik_orientation_weight),
                        _ => arm.so101.as_ref().map_or(1.0, |c| c.ik_orientation_weight),
                    };
                    Some(
                        phone2act_core::So101JointStage::new(joint_speeds, weight)
                            .map(phone2act_core::ArmJointStage::So101),
                    )
                }
                BridgeKind::Dobot => Some(
                    phone2act_core::Cr5JointStage::new(joint_speeds).map(phone2act_core::ArmJointStage::Cr5),
                ),
                BridgeKind::Remote => None,
            };
            let controller = match stage {
                Some(stage) => {
                    let mut stage = stage.map_err(|e| arm_err(e.to_string()))?;
                    if let Some(accelerations) = arm
                        .joint_limits
                        .resolve_acceleration(stage.joints())
                        .map_err(|e| arm_err(format!("joint_limits: {e}")))?
                    {
                        stage = stage
                            .with_max_acceleration_rad_s2(accelerations)
                            .map_err(|e| arm_err(format!("joint_limits: {e}")))?;
                    }
                    controller
                        .with_joint_stage(stage)
                        .map_err(|e| arm_err(e.to_string()))?
                }
                None => controller,
            };
            let controller = match arm.dataset_layout {
                crate::config::DatasetLayout::Phone2act => controller,
                crate::config::DatasetLayout::LerobotSo101 => {
                    let defaults = phone2act_bridges::so101::So101Config::new("", "");
                    let so101 = arm.so101.as_ref().unwrap_or(&defaults);
                    controller
                        .with_lerobot_so101(phone2act_core::LerobotSo101Units {
                            gripper_open_pct: so101.gripper_open_pct,
                            gripper_closed_pct: so101.gripper_closed_pct,
                        })
                        .map_err(|e| arm_err(e.to_string()))?
                }
            };
            let controller = match &config.flight_log {
                Some(flight) => controller
                    .with_flight_log(&flight.dir, flight.max_bytes, &arm.teleop, &arm.chunk)
                    .map_err(|e| arm_err(e.to_string()))?,
                None => controller,
            };
            arms.push(Arc::new(controller));
        }
        let mut cameras = Vec::new();
        for cam in &config.cameras {
            let cam_err = |message: String| AppError::Camera {
                camera: cam.name.clone(),
                message,
            };
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
                    .ok_or_else(|| {
                        cam_err("kind \"sim_render\" needs a simulated arm (set `arm`)".to_owned())
                    })?;
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
                CameraKind::V4l2 => {
                    let device = cam.device.as_deref().unwrap_or_default();
                    let av = phone2act_capture::av::device::AvCaptureConfig::v4l2(
                        device,
                        cam.width,
                        cam.height,
                        cam.fps.round() as u32,
                        cam.mjpeg,
                    );
                    Some(
                        phone2act_capture::av::device::spawn_av_capture(&cam.name, av, Arc::clone(&slot))
                            .map_err(|e| cam_err(format!("{device}: {e}")))?,
                    )
                }
                CameraKind::Remote => None,
            };
            cameras.push(CameraRuntime {
                config: cam.clone(),
                slot,
                capture: Mutex::new(capture),
            });
        }
        let mut spec = crate::recording::dataset_spec(&config, &arms)?;
        let station_id = crate::upload::station_id(&config)?;
        if let (Some(id), Some(p)) = (&station_id, spec.provenance.as_object_mut()) {
            p.insert("station_id".into(), id.clone().into());
        }
        let source = Arc::new(crate::recording::ArmsSource { arms: arms.clone() });
        let slots = cameras
            .iter()
            .map(|c| (c.config.name.clone(), Arc::clone(&c.slot)))
            .collect();
        let recorder = Recorder::open(spec, source, slots).map_err(RecordingError::from)?;
        recorder.set_frame_limit(config.recorder.frame_limit());
        recorder.set_highlight(config.recorder.highlight().map_err(RecordingError::Config)?);
        let episode_timing = crate::recording::EpisodeTiming::new(
            config.recorder.episode_limits().map_err(RecordingError::Config)?,
        );
        // After the recorder's open (which finishes an interrupted commit) and before anything can commit.
        let uploader = match &station_id {
            Some(id) => crate::upload::start(&config, id)?,
            None => None,
        };
        if let Some(u) = &uploader {
            recorder.set_commit_hook(Arc::new(crate::upload::UploadHook(Arc::clone(u))));
        }
        let (shutdown_tx, _) = watch::channel(false);
        Ok(Self {
            recorder: RwLock::new(Some(recorder)),
            config,
            started: Instant::now(),
            arms,
            cameras,
            remote_bridges,
            sessions: AtomicU64::new(1),
            shutdown_tx,
            recorder_version: std::sync::OnceLock::new(),
            uploader,
            episode_timing,
        })
    }

    /// The uploader, when `[storage]` is configured.
    pub fn uploader(&self) -> Option<&phone2act_storage::Uploader> {
        self.uploader.as_deref()
    }

    /// The configuration the server runs.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// When the server started.
    pub fn started(&self) -> Instant {
        self.started
    }

    /// Every arm, in configured order.
    pub fn arms(&self) -> &[Arc<ArmController>] {
        &self.arms
    }

    /// Every camera, in configured order.
    pub fn cameras(&self) -> &[CameraRuntime] {
        &self.cameras
    }

    /// Looks up an arm by name.
    pub fn arm(&self, name: &str) -> Option<Arc<ArmController>> {
        self.arms.iter().find(|a| a.name == name).cloned()
    }

    /// Looks up an arm by name; the error lists the configured ones.
    pub fn find_arm(&self, name: &str) -> Result<Arc<ArmController>, LookupError> {
        self.arm(name).ok_or_else(|| LookupError::UnknownArm {
            arm: name.to_owned(),
            configured: self.arm_names().join(", "),
        })
    }

    /// Looks up a camera by name.
    pub fn find_camera(&self, name: &str) -> Result<&CameraRuntime, LookupError> {
        self.cameras
            .iter()
            .find(|c| c.config.name == name)
            .ok_or_else(|| LookupError::UnknownCamera(name.to_owned()))
    }

    /// The camera `name` that takes pushed frames (`kind = "remote"`).
    pub fn find_remote_camera(&self, name: &str) -> Result<&CameraRuntime, LookupError> {
        self.cameras
            .iter()
            .find(|c| c.config.name == name && c.config.kind == CameraKind::Remote)
            .ok_or_else(|| LookupError::NotRemoteCamera(name.to_owned()))
    }

    /// The remote bridge of arm `name` (`bridge = "remote"`), for `Bridge.Attach`.
    pub fn find_remote_bridge(&self, name: &str) -> Result<Arc<RemoteBridge>, LookupError> {
        self.remote_bridges.get(name).cloned().ok_or_else(|| {
            let mut remote: Vec<&str> = self.remote_bridges.keys().map(String::as_str).collect();
            remote.sort_unstable();
            LookupError::NotRemoteArm {
                arm: name.to_owned(),
                remote: if remote.is_empty() {
                    "none".to_owned()
                } else {
                    remote.join(", ")
                },
            }
        })
    }

    /// Configured arm names in order.
    pub fn arm_names(&self) -> Vec<String> {
        self.arms.iter().map(|a| a.name.clone()).collect()
    }

    /// A fresh session id (teleop and policy share the counter).
    pub fn next_session_id(&self) -> u64 {
        self.sessions.fetch_add(1, Ordering::Relaxed)
    }

    /// Runs `f` on the recorder; [`RecordingError::Closed`] once it is closed.
    pub fn with_recorder<R>(
        &self,
        f: impl FnOnce(&Recorder) -> Result<R, RecordingError>,
    ) -> Result<R, RecordingError> {
        let guard = self.recorder.read();
        match guard.as_ref() {
            Some(recorder) => f(recorder),
            None => Err(RecordingError::Closed),
        }
    }

    /// The episode time limit and reset period (see `episode_timing::run_episode_timing`).
    pub fn episode_timing(&self) -> &crate::recording::EpisodeTiming {
        &self.episode_timing
    }

    /// The recorder's state; `None` once it is closed.
    pub fn recorder_status(&self) -> Option<RecorderStatus> {
        self.with_recorder(|r| Ok(r.status())).ok()
    }

    /// The task of the episode in progress.
    pub fn current_task(&self) -> String {
        self.recorder_status().map(|s| s.task).unwrap_or_default()
    }

    /// Applies a record button from a phone. Saving takes milliseconds (the video is already encoded), so
    /// it runs inline on a blocking-capable worker.
    pub fn record_action(&self, action: RecordAction<'_>) -> Result<(), RecordingError> {
        blocking(|| {
            self.with_recorder(|r| {
                match action {
                    RecordAction::Start { task } => r.start_episode(task).map(drop),
                    RecordAction::Stop { success } => r.stop_episode_with(success).map(drop),
                    RecordAction::Discard => r.discard_episode().map(drop),
                    RecordAction::SaveHighlight { task, success } => {
                        r.save_highlight(task, "", false, success).map(drop)
                    }
                }
                .map_err(RecordingError::from)
            })
        })
    }

    /// A receiver that turns `true` when shutdown begins; streaming RPCs end on it.
    pub fn shutdown_signal(&self) -> watch::Receiver<bool> {
        self.shutdown_tx.subscribe()
    }

    /// Changes whenever the recorder's status does. One thread waits on the recorder's condition variable
    /// for all watchers (started with the first), so a watch stream costs a task, not an OS thread.
    pub fn recorder_changes(self: &Arc<Self>) -> Result<watch::Receiver<u64>, RecordingError> {
        if let Some(rx) = self.recorder_version.get() {
            return Ok(rx.clone());
        }
        let (tx, rx) = watch::channel(0u64);
        let mut spawned = Ok(());
        let rx = self.recorder_version.get_or_init(|| {
            let app = Arc::clone(self);
            spawned = std::thread::Builder::new()
                .name("recorder-watch".into())
                .spawn(move || {
                    let mut since = 0u64;
                    // Ends at shutdown (the recorder closes) or when no watcher is left to tell.
                    while !*app.shutdown_tx.borrow() && !tx.is_closed() {
                        let Ok(status) =
                            app.with_recorder(|r| Ok(r.watch(since, Duration::from_millis(500))))
                        else {
                            break;
                        };
                        if status.version != since {
                            since = status.version;
                            tx.send_replace(since);
                        }
                    }
                })
                .map(drop);
            rx
        });
        spawned.map_err(RecordingError::WatchThread)?;
        Ok(rx.clone())
    }

    /// Tells every stream to end.
    pub fn begin_shutdown(&self) {
        self.shutdown_tx.send_replace(true);
    }

    /// Stops capture threads and bridges.
    pub fn stop(&self) {
        self.begin_shutdown();
        for cam in &self.cameras {
            if let Some(capture) = cam.capture.lock().take() {
                capture.stop();
            }
        }
        if let Some(recorder) = self.recorder.write().take() {
            // A graceful stop keeps the episode in progress: saving is as cheap as closing files.
            if matches!(
                recorder.status().phase,
                phone2act_recorder::recorder::Phase::Recording | phone2act_recorder::recorder::Phase::Paused
            ) {
                match recorder.stop_episode() {
                    Ok(ep) => tracing::info!(
                        episode = ep.index,
                        frames = ep.length_frames,
                        "episode saved at shutdown"
                    ),
                    Err(e) => tracing::warn!("episode in progress not saved at shutdown: {e}"),
                }
            }
            if let Err(e) = recorder.close() {
                tracing::warn!("closing the recorder: {e}");
            }
        }
        // What is not remote yet stays in the upload journal for the next start.
        if let Some(u) = &self.uploader {
            u.shutdown();
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

//! `phone2act.v1.Bridge`: out-of-process bridges. The stream is a thin adapter over
//! [`phone2act_bridges::remote::RemoteBridge`]: commands (latest wins) and control requests go down, feedback
//! and health reports come up. A dedicated thread waits on the remote bridge's condition variable so the
//! async runtime never blocks.

use crate::app::App;
use crate::services::convert;
use crate::services::error::{self, RequestError, check_len};
use phone2act_bridges::remote::{AttachHandle, Downstream};
use phone2act_proto::v1;
use phone2act_proto::v1::bridge_server::Bridge;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

/// The Bridge service adapter.
#[derive(Debug, Clone)]
pub struct BridgeService {
    app: Arc<App>,
}

impl BridgeService {
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

type DownStream = Pin<Box<dyn Stream<Item = Result<v1::BridgeDownstream, Status>> + Send>>;

fn down(message: v1::bridge_downstream::Message) -> v1::BridgeDownstream {
    v1::BridgeDownstream {
        message: Some(message),
    }
}

/// More joints than any arm has; the bound keeps a hello (and the error naming its joints) small.
const MAX_JOINTS: usize = 64;
/// Longest joint, arm or bridge name accepted.
const MAX_NAME_BYTES: usize = 128;

/// Refuses a hello whose sizes are out of bounds, with a short message.
fn check_hello(hello: &v1::BridgeHello) -> Result<(), RequestError> {
    if hello.joint_names.len() > MAX_JOINTS {
        return Err(RequestError::Refused(format!(
            "{} joint names, the limit is {MAX_JOINTS}",
            hello.joint_names.len()
        )));
    }
    check_len("arm", &hello.arm, MAX_NAME_BYTES)?;
    check_len("bridge_name", &hello.bridge_name, MAX_NAME_BYTES)?;
    hello
        .joint_names
        .iter()
        .try_for_each(|n| check_len("a joint name", n, MAX_NAME_BYTES))
}

/// A scene report from the bridge: stored as the arm's scene, and the answer to a reset if it names one.
fn publish_scene(handle: &AttachHandle, report: &v1::BridgeScene) -> Result<(), String> {
    let state = report.state.as_ref().ok_or("BridgeScene has no state")?;
    let scene = crate::services::scene::scene_from_proto(state)?;
    let error = (!report.error.is_empty()).then(|| report.error.clone());
    handle
        .publish_scene(scene, report.reset_request_id, error)
        .map_err(|e| e.to_string())
}

/// What the server does with an attaching bridge's joints.
struct JointSetup {
    /// The stage that solves and limits its joints (it declared a model), or none.
    stage: Option<phone2act_core::ArmJointStage>,
    /// The speeds its measured joints are watched against.
    watch_rad_s: Vec<f64>,
    enforced: bool,
    /// The same in words, for the welcome and the log.
    note: String,
}

/// The joint stage of the model `hello` declares (refused with the reason if malformed), or, without one, the
/// arm's configured speeds to watch.
fn joint_setup(app: &App, hello: &v1::BridgeHello) -> Result<JointSetup, RequestError> {
    let config = app
        .config()
        .arms
        .iter()
        .find(|a| a.name == hello.arm)
        .ok_or_else(|| RequestError::Internal(format!("arm {:?} has no configuration", hello.arm)))?;
    let Some(model) = &hello.joint_model else {
        let watch_rad_s = config
            .joint_limits
            .resolve(
                hello.joint_names.len(),
                phone2act_core::joint_motion::REMOTE_DEFAULT_MAX_VELOCITY_RAD_S,
            )
            .map_err(|e| RequestError::Refused(format!("the arm's joint_limits: {e}")))?;
        let note = format!(
            "no joint model declared: the bridge solves its own joints from the pose targets; the server only \
             watches their measured speeds (limit {:.2} rad/s)",
            watch_rad_s.iter().copied().fold(f64::INFINITY, f64::min)
        );
        return Ok(JointSetup {
            stage: None,
            watch_rad_s,
            enforced: false,
            note,
        });
    };
    let refused = |e: String| RequestError::Refused(format!("joint_model refused: {e}"));
    let declared = convert::declared_model(model).map_err(refused)?;
    let weight = if hello.supports_orientation { 1.0 } else { 0.0 };
    let stage = phone2act_core::joint_model::declared_stage(
        &declared,
        &hello.joint_names,
        &config.joint_limits,
        weight,
    )
    .map_err(|e| refused(e.to_string()))?;
    let watch_rad_s = stage.max_velocity_rad_s().to_vec();
    let note = format!(
        "joint model declared ({} joints): the server solves every target and limits each joint's step to {} rad/s; \
         commands carry joint_targets_rad",
        stage.joints(),
        watch_rad_s
            .iter()
            .map(|v| format!("{v:.2}"))
            .collect::<Vec<_>>()
            .join("/")
    );
    Ok(JointSetup {
        stage: Some(stage),
        watch_rad_s,
        enforced: true,
        note,
    })
}

#[tonic::async_trait]
impl Bridge for BridgeService {
    type AttachStream = DownStream;

    async fn attach(
        &self,
        request: Request<Streaming<v1::BridgeUpstream>>,
    ) -> Result<Response<Self::AttachStream>, Status> {
        let mut inbound = request.into_inner();
        let hello = match inbound.message().await? {
            Some(v1::BridgeUpstream {
                message: Some(v1::bridge_upstream::Message::Hello(h)),
            }) => h,
            Some(_) => return Err(RequestError::NoHello("the first message must be BridgeHello").into()),
            None => return Err(RequestError::NoHello("the stream ended before BridgeHello").into()),
        };
        check_hello(&hello)?;
        let remote = self.app.find_remote_bridge(&hello.arm)?;
        let arm = self.app.find_arm(&hello.arm)?;
        let joints = joint_setup(&self.app, &hello)?;
        let handle = Arc::new(
            remote
                .attach(hello.joint_names.clone(), hello.supports_orientation)
                .map_err(|e| error::remote(&e))?,
        );
        if hello.has_scene {
            handle.declare_scene().map_err(|e| error::remote(&e))?;
        }
        // Put in place after the attach, which clears the feedback: the new stage starts from this robot's first
        // measured joints, and nothing is commanded before them.
        arm.replace_joint_stage(joints.stage);
        if let Err(e) = remote.watch_joint_speeds(joints.watch_rad_s) {
            tracing::warn!(arm = %hello.arm, error = %e, "joint speed watch off");
        }
        // Debug formatting escapes control characters: a bridge name cannot forge log lines.
        tracing::info!(arm = %hello.arm, bridge = ?hello.bridge_name, has_scene = hello.has_scene,
            joint_limits = %joints.note, "remote bridge attached");
        let (tx, rx) = tokio::sync::mpsc::channel::<Result<v1::BridgeDownstream, Status>>(4);
        tx.try_send(Ok(down(v1::bridge_downstream::Message::Welcome(
            v1::BridgeWelcome {
                arm: hello.arm.clone(),
                expected_feedback_hz: 50.0,
                joint_targets: joints.enforced,
                joint_limits: joints.note,
            },
        ))))
        .map_err(|_| RequestError::Internal("stream queue".to_owned()))?;
        // The model is checked against the robot on the first feedback of the attachment.
        let mut model_checked = !joints.enforced;

        let down_handle = Arc::clone(&handle);
        let down_tx = tx.clone();
        std::thread::Builder::new()
            .name(format!("bridge-attach-{}", hello.arm))
            .spawn(move || {
                loop {
                    if down_tx.is_closed() {
                        break;
                    }
                    let message = match down_handle.next(Duration::from_millis(100)) {
                        Ok(Some(Downstream::Command(c))) => {
                            v1::bridge_downstream::Message::Command(convert::bridge_command(&c))
                        }
                        Ok(Some(Downstream::Control(c))) => {
                            v1::bridge_downstream::Message::Control(convert::bridge_control(c))
                        }
                        Ok(Some(Downstream::SceneReset(r))) => {
                            v1::bridge_downstream::Message::SceneReset(v1::BridgeSceneReset {
                                request_id: r.request_id,
                                seed: r.seed,
                                home_arm: r.home_arm,
                            })
                        }
                        Ok(None) => continue,
                        Err(e) => {
                            let _ = down_tx.blocking_send(Err(error::remote(&e)));
                            break;
                        }
                    };
                    if down_tx.blocking_send(Ok(down(message))).is_err() {
                        break;
                    }
                }
            })
            .map_err(|e| RequestError::Internal(format!("cannot start bridge thread: {e}")))?;

        let mut shutdown = self.app.shutdown_signal();
        let up_tx = tx;
        tokio::spawn(async move {
            loop {
                let msg = tokio::select! {
                    msg = inbound.message() => msg,
                    () = crate::runtime::stopped(&mut shutdown) => break,
                };
                match msg {
                    Ok(Some(v1::BridgeUpstream {
                        message: Some(message),
                    })) => {
                        let result = match message {
                            v1::bridge_upstream::Message::Feedback(fb) => convert::bridge_feedback(&fb)
                                .and_then(|f| {
                                    if !model_checked {
                                        arm.check_joint_model(&f).map_err(|e| e.to_string())?;
                                        model_checked = true;
                                    }
                                    handle.publish_feedback(f).map_err(|e| e.to_string())
                                }),
                            v1::bridge_upstream::Message::Status(report) => handle
                                .report_health(convert::bridge_health(report))
                                .map_err(|e| e.to_string()),
                            v1::bridge_upstream::Message::Scene(report) => publish_scene(&handle, &report),
                            v1::bridge_upstream::Message::Hello(_) => {
                                Err(RequestError::HelloTwice("BridgeHello").to_string())
                            }
                        };
                        if let Err(e) = result {
                            // A bridge that measures nonsense must hear it, not be ignored while the arm shows
                            // READY: the stream ends with the reason, and the arm holds until it attaches again.
                            tracing::warn!(error = %e, "remote bridge message refused; ending its stream");
                            let _ = up_tx
                                .send(Err(RequestError::Refused(format!(
                                    "refused: {e}; the arm holds until the bridge attaches again"
                                ))
                                .into()))
                                .await;
                            break;
                        }
                    }
                    Ok(Some(_)) => {}
                    Ok(None) | Err(_) => break,
                }
            }
            handle.detach();
            tracing::info!("remote bridge detached");
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }
}

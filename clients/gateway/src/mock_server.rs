//! A small in-process stand-in for the phone2act server (Teleop and System only) that records every sample it
//! receives with its arrival time. It is a real tonic server on a real socket; the gateway's tests use it to
//! check the translation in isolation, and `gateway-bench` uses it to timestamp arrivals on the same
//! monotonic clock as the sender.
//!
//! Semantics are deliberately simple: the clutch and gripper toggle flags, the pose of the last sample is
//! echoed as the "measured" end effector, unknown arms are refused with NOT_FOUND.

use parking_lot::Mutex;
use phone2act_proto::v1::system_server::{System, SystemServer};
use phone2act_proto::v1::teleop_server::{Teleop, TeleopServer};
use phone2act_proto::v1::{
    ArmState, DatasetInfo, GetDatasetInfoRequest, GetStatusRequest, ListArmsRequest, ListArmsResponse,
    ListCamerasRequest, ListCamerasResponse, PhoneSample, RecordingPhase, RecordingStatus, SystemStatus,
    TeleopFeedback, WatchStatusRequest, button_event, clutch_command, gripper_command, record_command,
};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

/// One sample as it arrived.
#[derive(Debug, Clone)]
pub struct Received {
    pub arm: String,
    pub sample: PhoneSample,
    /// Arrival time on the mock's clock: nanoseconds since the `epoch` passed to [`MockServer::start`].
    pub arrival_ns: i64,
}

#[derive(Debug, Default)]
struct State {
    received: Vec<Received>,
    arms: HashMap<String, ArmState>,
    recording: RecordingStatus,
    streams_opened: u64,
    /// Set on drop: open streams fail like a killed process's would, instead of draining gracefully.
    killed: bool,
}

#[derive(Clone, Debug)]
struct Mock {
    state: Arc<Mutex<State>>,
    epoch: Instant,
    record_samples: bool,
}

/// A running mock server.
#[derive(Debug)]
pub struct MockServer {
    pub addr: SocketAddr,
    state: Arc<Mutex<State>>,
    mock: Mock,
    stop: watch::Sender<bool>,
}

impl MockServer {
    /// Serves Teleop and System for `arms` on 127.0.0.1 with an ephemeral port.
    pub async fn start(arms: &[&str], epoch: Instant, record_samples: bool) -> std::io::Result<Self> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        Self::start_on(listener, arms, epoch, record_samples)
    }

    /// Serves on a listener the caller bound.
    pub fn start_on(
        listener: tokio::net::TcpListener,
        arms: &[&str],
        epoch: Instant,
        record_samples: bool,
    ) -> std::io::Result<Self> {
        let addr = listener.local_addr()?;
        let mut state = State {
            recording: idle(),
            ..State::default()
        };
        for arm in arms {
            state.arms.insert(
                (*arm).to_owned(),
                ArmState {
                    arm: (*arm).to_owned(),
                    ..ArmState::default()
                },
            );
        }
        let state = Arc::new(Mutex::new(state));
        let mock = Mock {
            state: state.clone(),
            epoch,
            record_samples,
        };
        let (stop, _) = watch::channel(false);
        let server = Self {
            addr,
            state,
            mock,
            stop,
        };
        // As in the real server: `Server::tcp_nodelay` does not reach a listener the caller bound, and without
        // NODELAY each feedback message waits for the client's next packet to carry the ACK.
        server.serve(tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)));
        Ok(server)
    }

    /// Also serves the calls of an SDK [`phone2act_sdk::Client::in_process`] client, as `phone2act serve`
    /// does for its embedded gateway: the same services, called in-process.
    pub fn serve_in_process(&self, incoming: phone2act_sdk::LocalIncoming) {
        let mut stopped = self.stop.subscribe();
        let routes = tonic::service::Routes::new(TeleopServer::new(self.mock.clone()))
            .add_service(SystemServer::new(self.mock.clone()))
            .prepare();
        incoming.serve(routes, async move {
            let _ = stopped.wait_for(|stop| *stop).await;
        });
    }

    fn serve<S, IO>(&self, incoming: S)
    where
        S: tokio_stream::Stream<Item = std::io::Result<IO>> + Send + 'static,
        IO: tokio::io::AsyncRead
            + tokio::io::AsyncWrite
            + tonic::transport::server::Connected
            + Unpin
            + Send
            + 'static,
    {
        let mut stopped = self.stop.subscribe();
        tokio::spawn(
            tonic::transport::Server::builder()
                .add_service(TeleopServer::new(self.mock.clone()))
                .add_service(SystemServer::new(self.mock.clone()))
                .serve_with_incoming_shutdown(incoming, async move {
                    let _ = stopped.wait_for(|stop| *stop).await;
                }),
        );
    }

    /// `http://addr`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Every sample received so far.
    pub fn received(&self) -> Vec<Received> {
        self.state.lock().received.clone()
    }

    /// The current state of `arm`.
    pub fn arm(&self, arm: &str) -> Option<ArmState> {
        self.state.lock().arms.get(arm).cloned()
    }

    /// The recorder state (driven by RecordCommand buttons).
    pub fn recording(&self) -> RecordingStatus {
        self.state.lock().recording.clone()
    }

    /// Teleop streams opened since start.
    pub fn streams_opened(&self) -> u64 {
        self.state.lock().streams_opened
    }

    /// Polls `check` until it holds or `timeout` passes.
    pub async fn wait_for(&self, timeout: Duration, mut check: impl FnMut(&Self) -> bool) -> bool {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if check(self) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        check(self)
    }
}

impl Drop for MockServer {
    fn drop(&mut self) {
        self.state.lock().killed = true;
        self.stop.send_replace(true);
    }
}

fn idle() -> RecordingStatus {
    RecordingStatus {
        phase: RecordingPhase::Idle.into(),
        ..RecordingStatus::default()
    }
}

impl Mock {
    fn apply(&self, arm: &str, sample: &PhoneSample, arrival_ns: i64) -> TeleopFeedback {
        let mut state = self.state.lock();
        if self.record_samples {
            state.received.push(Received {
                arm: arm.to_owned(),
                sample: sample.clone(),
                arrival_ns,
            });
        }
        let mut recording = state.recording.clone();
        for button in &sample.buttons {
            if let Some(button_event::Event::Record(r)) = &button.event {
                match r.kind() {
                    record_command::Kind::Start => {
                        recording.phase = RecordingPhase::Recording.into();
                        recording.task.clone_from(&r.task);
                    }
                    record_command::Kind::Stop | record_command::Kind::SaveHighlight => {
                        recording = RecordingStatus {
                            episodes_saved: recording.episodes_saved + 1,
                            ..idle()
                        };
                        recording.episode_index = recording.episodes_saved;
                    }
                    record_command::Kind::Discard => {
                        recording = RecordingStatus {
                            episodes_saved: recording.episodes_saved,
                            ..idle()
                        };
                    }
                    record_command::Kind::Unspecified => {}
                }
            }
        }
        state.recording = recording.clone();
        let entry = state.arms.get_mut(arm).expect("arm checked at stream start");
        for button in &sample.buttons {
            match &button.event {
                Some(button_event::Event::Clutch(c)) => match c.kind() {
                    clutch_command::Kind::Toggle => entry.engaged = !entry.engaged,
                    clutch_command::Kind::Engage => entry.engaged = true,
                    clutch_command::Kind::Disengage => entry.engaged = false,
                    clutch_command::Kind::Unspecified => {}
                },
                Some(button_event::Event::Gripper(g)) => match g.kind() {
                    gripper_command::Kind::Toggle => {
                        entry.gripper_target = if entry.gripper_target > 0.5 { 0.0 } else { 1.0 };
                    }
                    gripper_command::Kind::Set => entry.gripper_target = g.position,
                    gripper_command::Kind::Unspecified => {}
                },
                _ => {}
            }
        }
        if let Some(pose) = &sample.tracking_from_phone {
            entry.robot_from_ee = Some(*pose);
            if entry.engaged {
                entry.robot_from_target = Some(*pose);
                entry.commands_sent += 1;
            }
        }
        TeleopFeedback {
            echoed_seq: sample.seq,
            echoed_capture_time_ns: sample.capture_time_ns,
            server_receive_time_ns: arrival_ns,
            server_send_time_ns: self.epoch.elapsed().as_nanos() as i64,
            arm_state: Some(entry.clone()),
            recording: Some(recording),
            error: String::new(),
            superseded_samples: 0,
        }
    }
}

type FeedbackStream = Pin<Box<dyn Stream<Item = Result<TeleopFeedback, Status>> + Send>>;
type StatusStream = Pin<Box<dyn Stream<Item = Result<SystemStatus, Status>> + Send>>;

#[tonic::async_trait]
impl Teleop for Mock {
    type StreamStream = FeedbackStream;

    async fn stream(
        &self,
        request: Request<Streaming<PhoneSample>>,
    ) -> Result<Response<FeedbackStream>, Status> {
        let mut inbound = request.into_inner();
        let first = inbound
            .message()
            .await?
            .ok_or_else(|| Status::invalid_argument("empty stream"))?;
        let arrival_ns = self.epoch.elapsed().as_nanos() as i64;
        let arm = first.arm.clone();
        {
            let mut state = self.state.lock();
            if !state.arms.contains_key(&arm) {
                return Err(Status::not_found(format!("unknown arm '{arm}'")));
            }
            state.streams_opened += 1;
        }
        let (tx, rx) = mpsc::channel(16);
        let mock = self.clone();
        tokio::spawn(async move {
            let _ = tx.try_send(Ok(mock.apply(&arm, &first, arrival_ns)));
            while let Ok(Some(sample)) = inbound.message().await {
                if mock.state.lock().killed {
                    let _ = tx.try_send(Err(Status::unavailable("mock server stopped")));
                    return;
                }
                let arrival_ns = mock.epoch.elapsed().as_nanos() as i64;
                let feedback = mock.apply(&arm, &sample, arrival_ns);
                let _ = tx.try_send(Ok(feedback));
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

#[tonic::async_trait]
impl System for Mock {
    type WatchStatusStream = StatusStream;

    async fn list_arms(&self, _: Request<ListArmsRequest>) -> Result<Response<ListArmsResponse>, Status> {
        let state = self.state.lock();
        let mut arms: Vec<ArmState> = state.arms.values().cloned().collect();
        arms.sort_by(|a, b| a.arm.cmp(&b.arm));
        Ok(Response::new(ListArmsResponse { arms }))
    }

    async fn list_cameras(
        &self,
        _: Request<ListCamerasRequest>,
    ) -> Result<Response<ListCamerasResponse>, Status> {
        Ok(Response::new(ListCamerasResponse::default()))
    }

    async fn get_status(&self, _: Request<GetStatusRequest>) -> Result<Response<SystemStatus>, Status> {
        Ok(Response::new(self.snapshot(0)))
    }

    async fn watch_status(
        &self,
        request: Request<WatchStatusRequest>,
    ) -> Result<Response<StatusStream>, Status> {
        let interval = Duration::from_secs_f64(request.into_inner().interval_s.clamp(0.01, 10.0));
        let (tx, rx) = mpsc::channel(4);
        let mock = self.clone();
        tokio::spawn(async move {
            let mut sequence = 0;
            loop {
                sequence += 1;
                if tx.send(Ok(mock.snapshot(sequence))).await.is_err() {
                    return;
                }
                tokio::time::sleep(interval).await;
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn get_dataset_info(
        &self,
        _: Request<GetDatasetInfoRequest>,
    ) -> Result<Response<DatasetInfo>, Status> {
        Err(Status::unimplemented("mock server has no dataset"))
    }
}

impl Mock {
    fn snapshot(&self, sequence: u64) -> SystemStatus {
        let state = self.state.lock();
        let mut arms: Vec<ArmState> = state.arms.values().cloned().collect();
        arms.sort_by(|a, b| a.arm.cmp(&b.arm));
        SystemStatus {
            version: "mock".into(),
            server_time_ns: self.epoch.elapsed().as_nanos() as i64,
            arms,
            recording: Some(state.recording.clone()),
            sequence,
            ..SystemStatus::default()
        }
    }
}

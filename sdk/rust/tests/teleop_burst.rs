//! A burst of `TeleopSession::send` over a real socket to a Teleop server that records what arrives: the
//! newest pose gets through and so does every button event, in order (latest wins, buttons survive).

use phone2act_proto::v1::teleop_server::{Teleop, TeleopServer};
use phone2act_proto::v1::{self, PhoneSample, TeleopFeedback};
use phone2act_sdk::{Client, TeleopOptions, buttons};
use std::pin::Pin;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

/// Hands every sample it receives, hello included, to the test; ends the feedback stream with the request.
struct Recorder {
    received: mpsc::Sender<Vec<PhoneSample>>,
}

type Feedback = Pin<Box<dyn Stream<Item = Result<TeleopFeedback, Status>> + Send>>;

#[tonic::async_trait]
impl Teleop for Recorder {
    type StreamStream = Feedback;

    async fn stream(&self, request: Request<Streaming<PhoneSample>>) -> Result<Response<Feedback>, Status> {
        let mut inbound = request.into_inner();
        let hello = inbound
            .message()
            .await?
            .ok_or_else(|| Status::invalid_argument("no hello"))?;
        let received = self.received.clone();
        tokio::spawn(async move {
            let mut all = vec![hello];
            while let Ok(Some(sample)) = inbound.message().await {
                all.push(sample);
            }
            let _ = received.send(all).await;
        });
        Ok(Response::new(Box::pin(tokio_stream::empty())))
    }
}

fn pose_x(sample: &PhoneSample) -> Option<f64> {
    sample
        .tracking_from_phone
        .as_ref()
        .map(|p| p.position_m.as_ref().unwrap().x)
}

// Single-threaded on purpose: the burst is synchronous code, so the request stream cannot take anything until it
// ends, and every sample after the first is folded. That makes the fold deterministic, not a race.
#[tokio::test]
async fn a_burst_keeps_the_newest_pose_and_every_button() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (tx, mut rx) = mpsc::channel(1);
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(TeleopServer::new(Recorder { received: tx }))
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let client = Client::connect(&format!("http://{addr}"), None).await.unwrap();
    let mut session = client.teleop("left", TeleopOptions::default()).await.unwrap();

    let mut sent_buttons = Vec::new();
    let mut alone = Vec::new();
    for i in 0..100u32 {
        let buttons = match i % 4 {
            0 => vec![buttons::clutch_engage()],
            1 => vec![],
            2 => vec![
                buttons::gripper_set(f64::from(i) / 100.0),
                buttons::clutch_disengage(),
            ],
            _ => vec![buttons::record_stop()],
        };
        sent_buttons.extend(buttons.iter().cloned());
        // Every third sample carries no pose, like a button press between two frames of the phone's tracking.
        let pose = (i % 3 != 1).then(|| v1::Pose::from_parts([f64::from(i), 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]));
        alone.push(
            session
                .send(PhoneSample {
                    tracking_from_phone: pose,
                    tracking: v1::TrackingState::Tracking as i32,
                    buttons,
                    ..PhoneSample::default()
                })
                .unwrap(),
        );
    }
    assert!(alone[0], "the first sample of the burst found the outbox empty");
    assert!(
        alone[1..].iter().all(|a| !a),
        "the rest were folded while it waited"
    );
    assert_eq!(session.superseded(), 99);
    drop(session);

    let received = rx.recv().await.expect("the server saw the stream end");
    assert_eq!(received[0].arm, "left");
    let last = received.last().unwrap();
    assert_eq!(last.seq, 100);
    // Sample 99 (i = 99) has a pose: i % 3 == 0.
    assert_eq!(pose_x(last), Some(99.0));
    let got_buttons: Vec<v1::ButtonEvent> = received[1..].iter().flat_map(|s| s.buttons.clone()).collect();
    assert_eq!(got_buttons.len(), 100);
    assert_eq!(got_buttons, sent_buttons);
}

//! The gateway's side of the gRPC connection to the phone2act server: one SDK client (one HTTP/2 channel with
//! the server's bearer token) shared by every phone.
//!
//! The standalone gateway dials lazily, because it may start before the server and must survive the
//! server's restarts; the gateway `phone2act serve` embeds reaches its server in-process.

use phone2act_proto::v1::policy_client::PolicyClient;
use phone2act_proto::v1::system_client::SystemClient;
use phone2act_proto::v1::{CameraFrame, GetObservationRequest, ImageEncoding, ListCamerasRequest};
use phone2act_sdk::{AuthChannel, Client, ConnectOptions};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::error::GatewayError;

/// A camera frame and when it was captured on this gateway's wall clock.
#[derive(Debug)]
pub(crate) struct TimedFrame {
    pub frame: CameraFrame,
    /// Capture time (Unix, nanoseconds): the frame's age at the server when it answered, counted back from
    /// the middle of the call (the two machines' clocks need not agree).
    pub capture_unix_ns: i64,
}

/// `t` as Unix nanoseconds.
pub(crate) fn unix_ns(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// The shared connection to the server.
#[derive(Clone, Debug)]
pub struct Upstream {
    client: Client,
    /// How to dial the server again (`None` for an in-process server, whose calls run on the caller's thread).
    dial: Option<(String, ConnectOptions)>,
}

impl Upstream {
    /// A lazily connecting channel to `server_url` (`http://host:port`).
    pub fn new(server_url: &str, grpc_token: Option<&str>) -> Result<Self, GatewayError> {
        let options = ConnectOptions {
            token: grpc_token.map(str::to_owned),
            connect_timeout_s: 3.0,
            ..ConnectOptions::default()
        };
        let client = Client::connect_lazy(server_url, &options).map_err(|e| {
            // The SDK keeps the reason in the error's source; say it on the one line a user sees.
            let reason = std::error::Error::source(&e).map_or_else(|| e.to_string(), ToString::to_string);
            GatewayError::ServerUrl(format!("{server_url}: {reason}"))
        })?;
        Ok(Self {
            client,
            dial: Some((server_url.to_owned(), options)),
        })
    }

    /// An already made client (the embedded gateway's in-process one).
    pub fn from_client(client: Client) -> Self {
        Self { client, dial: None }
    }

    /// A connection of its own to the same server, its I/O on the runtime this is called in (the live video's
    /// bulk frames then never share the control path's connection or thread). An in-process upstream is
    /// shared: its calls already run on the calling thread.
    pub(crate) fn separate(&self) -> Self {
        match &self.dial {
            Some((url, options)) => match Client::connect_lazy(url, options) {
                Ok(client) => Self {
                    client,
                    dial: self.dial.clone(),
                },
                // The same URL and options made the first connection; keep sharing it if that ever changes.
                Err(_) => self.clone(),
            },
            None => self.clone(),
        }
    }

    /// The shared SDK client (teleop sessions are its [`phone2act_sdk::TeleopLink`]s).
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// A System client on the shared channel.
    pub fn system(&self) -> SystemClient<AuthChannel> {
        self.client.system_raw()
    }

    /// A Policy client on the shared channel (read-only use: `GetObservation` for camera images).
    pub fn policy(&self) -> PolicyClient<AuthChannel> {
        self.client.policy_raw()
    }

    /// The newest frame of `camera` as a JPEG, through `Policy.GetObservation` (read-only: it takes no
    /// control). `None` while the server has no frame of it (the call skips camera names it does not know,
    /// so callers that must tell "unknown" from "not yet" ask [`Self::camera_names`]). Shared by the
    /// rosbridge image topics and the phone page's preview.
    pub async fn camera_jpeg(&self, camera: &str) -> Result<Option<Vec<u8>>, tonic::Status> {
        Ok(self
            .camera_frame(camera, ImageEncoding::Jpeg)
            .await?
            .map(|t| t.frame.data))
    }

    /// The newest frame of `camera` in `encoding`, with its capture time on this gateway's clock; `None`
    /// while the server has no frame of it.
    pub(crate) async fn camera_frame(
        &self,
        camera: &str,
        encoding: ImageEncoding,
    ) -> Result<Option<TimedFrame>, tonic::Status> {
        let request = GetObservationRequest {
            arms: Vec::new(),
            image_encoding: encoding.into(),
            cameras: vec![camera.to_owned()],
        };
        let sent_at = SystemTime::now();
        let started = Instant::now();
        // A raw frame of a large camera exceeds tonic's 4 MiB default (1920x1080 RGB is 6.2 MB); the largest
        // camera the server takes, 7680x4320, is 99.5 MB.
        let observation = self
            .policy()
            .max_decoding_message_size(128 << 20)
            .get_observation(request)
            .await?
            .into_inner();
        let rpc: Duration = started.elapsed();
        Ok(observation
            .frames
            .into_iter()
            .find(|f| f.camera == camera && !f.data.is_empty())
            .map(|frame| {
                let age_ns = (observation.timestamp_ns - frame.capture_time_ns).max(0);
                TimedFrame {
                    capture_unix_ns: unix_ns(sent_at + rpc / 2) - age_ns,
                    frame,
                }
            }))
    }

    /// The names of the server's cameras.
    pub async fn camera_names(&self) -> Result<Vec<String>, tonic::Status> {
        let cameras = self
            .system()
            .list_cameras(ListCamerasRequest {})
            .await?
            .into_inner();
        Ok(cameras.cameras.into_iter().map(|c| c.camera).collect())
    }
}

//! `phone2act.v1.Cameras`: remote cameras push frames into a configured camera's latest-frame slot.

use crate::app::App;
use crate::services::error::RequestError;
use phone2act_capture::camera::Frame;
use phone2act_capture::jpeg::JpegError;
use phone2act_clock::monotonic_ns;
use phone2act_proto::convert_camera::{FrameError, PushedPixels, pushed_pixels};
use phone2act_proto::v1;
use phone2act_proto::v1::cameras_server::Cameras;
use std::sync::Arc;
use tonic::{Request, Response, Status, Streaming};

/// The Cameras service adapter.
#[derive(Debug, Clone)]
pub struct CamerasService {
    app: Arc<App>,
}

impl CamerasService {
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

/// Why a pushed frame was refused.
#[derive(Debug, thiserror::Error)]
enum PushError {
    #[error(transparent)]
    Frame(#[from] FrameError),
    #[error(transparent)]
    Jpeg(#[from] JpegError),
    #[error("JPEG is {got_width}x{got_height}, camera {camera:?} is configured for {width}x{height}")]
    JpegSize {
        camera: String,
        got_width: u32,
        got_height: u32,
        width: u32,
        height: u32,
    },
}

/// Checks and decodes one pushed frame for a camera configured at `width`×`height`.
fn decode(frame: &v1::CameraFrame, width: u32, height: u32) -> Result<Vec<u8>, PushError> {
    match pushed_pixels(frame, width, height)? {
        PushedPixels::Rgb8(rgb) => Ok(rgb.to_vec()),
        PushedPixels::Jpeg(jpeg) => {
            let decoded = phone2act_capture::jpeg::decode_jpeg(jpeg)?;
            if decoded.width != width || decoded.height != height {
                return Err(PushError::JpegSize {
                    camera: frame.camera.clone(),
                    got_width: decoded.width,
                    got_height: decoded.height,
                    width,
                    height,
                });
            }
            Ok(Arc::try_unwrap(decoded.rgb).unwrap_or_else(|shared| shared.as_ref().clone()))
        }
    }
}

#[tonic::async_trait]
impl Cameras for CamerasService {
    async fn push(
        &self,
        request: Request<Streaming<v1::CameraFrame>>,
    ) -> Result<Response<v1::PushSummary>, Status> {
        let mut inbound = request.into_inner();
        let mut bound = None;
        let mut summary = v1::PushSummary::default();
        while let Some(frame) = inbound.message().await? {
            let cam = if let Some(cam) = bound {
                if frame.camera != summary.camera {
                    return Err(RequestError::Refused(format!(
                        "this stream is bound to camera {:?}, got a frame for {:?}",
                        summary.camera, frame.camera
                    ))
                    .into());
                }
                cam
            } else {
                let cam = self.app.find_remote_camera(&frame.camera)?;
                bound = Some(cam);
                summary.camera.clone_from(&frame.camera);
                cam
            };
            let (width, height) = (cam.config().width, cam.config().height);
            let seq = frame.frame_seq;
            let result = crate::runtime::blocking(|| decode(&frame, width, height));
            match result {
                Ok(rgb) => {
                    cam.slot().publish(Frame {
                        width,
                        height,
                        rgb: Arc::new(rgb),
                        capture_time_ns: monotonic_ns(),
                        seq,
                    });
                    summary.frames_accepted += 1;
                }
                Err(e) => {
                    // Any bad frame ends the stream with the reason: a sender whose frames are being thrown
                    // away must hear it, not get an OK with a counter at the end.
                    tracing::debug!(camera = %summary.camera, error = %e, "pushed frame refused");
                    return Err(RequestError::Refused(format!(
                        "frame {} refused after {} accepted: {e}",
                        summary.frames_accepted + 1,
                        summary.frames_accepted
                    ))
                    .into());
                }
            }
        }
        Ok(Response::new(summary))
    }
}

//! `phone2act.v1.Cameras`: remote cameras push frames into a configured camera's latest-frame slot.

use crate::app::App;
use phone2act_clock::monotonic_ns;
use phone2act_proto::v1;
use phone2act_proto::v1::cameras_server::Cameras;
use phone2act_recorder::camera::Frame;
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

/// Checks and decodes one pushed frame for a camera configured at `width`×`height`.
fn decode(frame: &v1::CameraFrame, width: u32, height: u32) -> Result<Vec<u8>, String> {
    if frame.width != width || frame.height != height {
        return Err(format!(
            "frame is {}x{}, camera {:?} is configured for {width}x{height}",
            frame.width, frame.height, frame.camera
        ));
    }
    match v1::ImageEncoding::try_from(frame.encoding) {
        Ok(v1::ImageEncoding::Rgb8) => {
            let expected = width as usize * height as usize * 3;
            if frame.data.len() != expected {
                return Err(format!(
                    "RGB8 frame has {} bytes, expected {expected}",
                    frame.data.len()
                ));
            }
            Ok(frame.data.clone())
        }
        Ok(v1::ImageEncoding::Jpeg) => {
            let decoded = phone2act_recorder::jpeg::decode_jpeg(&frame.data).map_err(|e| e.to_string())?;
            if decoded.width != width || decoded.height != height {
                return Err(format!(
                    "JPEG is {}x{}, camera {:?} is configured for {width}x{height}",
                    decoded.width, decoded.height, frame.camera
                ));
            }
            Ok(Arc::try_unwrap(decoded.rgb).unwrap_or_else(|shared| shared.as_ref().clone()))
        }
        _ => Err(format!("unsupported image encoding {}", frame.encoding)),
    }
}

#[tonic::async_trait]
impl Cameras for CamerasService {
    async fn push(
        &self,
        request: Request<Streaming<v1::CameraFrame>>,
    ) -> Result<Response<v1::PushSummary>, Status> {
        let mut inbound = request.into_inner();
        let mut bound: Option<usize> = None;
        let mut summary = v1::PushSummary::default();
        while let Some(frame) = inbound.message().await? {
            let index = if let Some(i) = bound {
                if frame.camera != self.app.cameras[i].config.name {
                    return Err(Status::invalid_argument(format!(
                        "this stream is bound to camera {:?}, got a frame for {:?}",
                        summary.camera, frame.camera
                    )));
                }
                i
            } else {
                let i = self
                    .app
                    .cameras
                    .iter()
                    .position(|c| {
                        c.config.name == frame.camera && c.config.kind == crate::config::CameraKind::Remote
                    })
                    .ok_or_else(|| {
                        Status::not_found(format!(
                            "no camera {:?} with kind = \"remote\" is configured",
                            frame.camera
                        ))
                    })?;
                bound = Some(i);
                summary.camera.clone_from(&frame.camera);
                i
            };
            let cam = &self.app.cameras[index];
            let (width, height) = (cam.config.width, cam.config.height);
            let seq = frame.frame_seq;
            let result = crate::app::blocking(|| decode(&frame, width, height));
            match result {
                Ok(rgb) => {
                    cam.slot.publish(Frame {
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
                    return Err(Status::invalid_argument(format!(
                        "frame {} refused after {} accepted: {e}",
                        summary.frames_accepted + 1,
                        summary.frames_accepted
                    )));
                }
            }
        }
        Ok(Response::new(summary))
    }
}

//! `phone2act.v1.System`: arms, cameras, status snapshots and the status watch stream.

use crate::app::App;
use crate::services::convert::{camera_status, system_status};
use phone2act_proto::convert_arm::arm_state_to_proto;
use phone2act_proto::v1;
use phone2act_proto::v1::system_server::System;
use std::pin::Pin;
use std::sync::Arc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// The System service adapter.
#[derive(Debug, Clone)]
pub struct SystemService {
    app: Arc<App>,
}

impl SystemService {
    /// A service over `app`.
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

type StatusStream = Pin<Box<dyn Stream<Item = Result<v1::SystemStatus, Status>> + Send>>;

#[tonic::async_trait]
impl System for SystemService {
    async fn list_arms(
        &self,
        _: Request<v1::ListArmsRequest>,
    ) -> Result<Response<v1::ListArmsResponse>, Status> {
        Ok(Response::new(v1::ListArmsResponse {
            arms: self
                .app
                .arms()
                .iter()
                .map(|a| arm_state_to_proto(&a.snapshot()))
                .collect(),
        }))
    }

    async fn list_cameras(
        &self,
        _: Request<v1::ListCamerasRequest>,
    ) -> Result<Response<v1::ListCamerasResponse>, Status> {
        Ok(Response::new(v1::ListCamerasResponse {
            cameras: self.app.cameras().iter().map(camera_status).collect(),
        }))
    }

    async fn get_status(
        &self,
        _: Request<v1::GetStatusRequest>,
    ) -> Result<Response<v1::SystemStatus>, Status> {
        Ok(Response::new(system_status(&self.app, 0)))
    }

    type WatchStatusStream = StatusStream;

    async fn watch_status(
        &self,
        request: Request<v1::WatchStatusRequest>,
    ) -> Result<Response<Self::WatchStatusStream>, Status> {
        let interval = super::error::watch_interval(request.into_inner().interval_s, 0.1)?;
        let app = Arc::clone(&self.app);
        // Bounded: one snapshot in flight; a slow client simply sees fewer snapshots.
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        let mut shutdown = app.shutdown_signal();
        tokio::spawn(async move {
            let mut ticker = tokio::time::interval(interval);
            ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            let mut sequence = 0u64;
            loop {
                tokio::select! {
                    _ = ticker.tick() => {}
                    () = crate::runtime::stopped(&mut shutdown) => break,
                    () = tx.closed() => break,
                }
                if tx.send(Ok(system_status(&app, sequence))).await.is_err() {
                    break;
                }
                sequence += 1;
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }

    async fn get_dataset_info(
        &self,
        _: Request<v1::GetDatasetInfoRequest>,
    ) -> Result<Response<v1::DatasetInfo>, Status> {
        let rec = &self.app.config().recorder;
        Ok(Response::new(v1::DatasetInfo {
            root: rec.root.display().to_string(),
            format: rec.format.codebase_version().to_owned(),
            fps: rec.fps,
            robot_type: rec.robot_type.clone(),
            video_codec: rec.effective_video_codec().to_owned(),
            ..v1::DatasetInfo::default()
        }))
    }
}

//! `phone2act.v1.Episodes`: start, stop (save), discard, re-record, list, status and watch. The recorder
//! does file I/O, so calls run on blocking-capable workers.

use crate::app::App;
use crate::recording::RecordingError;
use crate::runtime::blocking;
use crate::services::convert::{
    current_recording_status, episode, episode_with_upload, recording_status, storage_status,
};
use crate::services::error::RequestError;
use phone2act_proto::convert_episode::outcome_success;
use phone2act_proto::v1;
use phone2act_proto::v1::episodes_server::Episodes;
use phone2act_recorder::Highlight;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Instant;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// The Episodes service adapter.
#[derive(Debug, Clone)]
pub struct EpisodesService {
    app: Arc<App>,
}

impl EpisodesService {
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }
}

/// Longest operator name kept in provenance.
const MAX_OPERATOR_BYTES: usize = 128;

fn check_operator(operator: &str) -> Result<(), Status> {
    if operator.len() > MAX_OPERATOR_BYTES {
        return Err(RequestError::TooLong {
            field: "operator",
            len: operator.len(),
            limit: MAX_OPERATOR_BYTES,
        }
        .into());
    }
    Ok(())
}

type StatusStream = Pin<Box<dyn Stream<Item = Result<v1::RecordingStatus, Status>> + Send>>;

#[tonic::async_trait]
impl Episodes for EpisodesService {
    async fn start(
        &self,
        request: Request<v1::StartEpisodeRequest>,
    ) -> Result<Response<v1::StartEpisodeResponse>, Status> {
        let v1::StartEpisodeRequest { task, operator } = request.into_inner();
        check_operator(&operator)?;
        let app = &self.app;
        let status = blocking(|| {
            app.with_recorder(|r| r.start_episode_by(&task, &operator).map_err(RecordingError::from))
        })?;
        Ok(Response::new(v1::StartEpisodeResponse {
            status: Some(recording_status(&status, app.config())),
        }))
    }

    async fn stop(
        &self,
        request: Request<v1::StopEpisodeRequest>,
    ) -> Result<Response<v1::StopEpisodeResponse>, Status> {
        let started = Instant::now();
        // An unknown outcome (a newer client's) is refused before anything stops: the episode keeps recording.
        let success = outcome_success(request.into_inner().outcome)
            .map_err(|e| RequestError::Refused(format!("outcome: {e}")))?;
        let app = &self.app;
        let summary =
            blocking(|| app.with_recorder(|r| r.stop_episode_with(success).map_err(RecordingError::from)))?;
        Ok(Response::new(v1::StopEpisodeResponse {
            episode: Some(episode(&summary)),
            save_latency_s: started.elapsed().as_secs_f64(),
        }))
    }

    async fn discard(
        &self,
        _: Request<v1::DiscardEpisodeRequest>,
    ) -> Result<Response<v1::DiscardEpisodeResponse>, Status> {
        let app = &self.app;
        let frames = blocking(|| app.with_recorder(|r| r.discard_episode().map_err(RecordingError::from)))?;
        Ok(Response::new(v1::DiscardEpisodeResponse {
            frames_discarded: frames,
        }))
    }

    async fn rerecord(
        &self,
        request: Request<v1::RerecordEpisodeRequest>,
    ) -> Result<Response<v1::StartEpisodeResponse>, Status> {
        let task = request.into_inner().task;
        let app = &self.app;
        let task = if task.is_empty() {
            None
        } else {
            Some(task.as_str())
        };
        let status = blocking(|| app.with_recorder(|r| r.rerecord(task).map_err(RecordingError::from)))?;
        Ok(Response::new(v1::StartEpisodeResponse {
            status: Some(recording_status(&status, app.config())),
        }))
    }

    async fn list(
        &self,
        _: Request<v1::ListEpisodesRequest>,
    ) -> Result<Response<v1::ListEpisodesResponse>, Status> {
        let episodes = self.app.with_recorder(|r| Ok(r.episodes()))?;
        let uploader = self.app.uploader();
        Ok(Response::new(v1::ListEpisodesResponse {
            episodes: episodes
                .iter()
                .map(|e| episode_with_upload(e, uploader))
                .collect(),
            dataset_root: self.app.config().recorder.root.display().to_string(),
            storage: uploader.map(storage_status),
        }))
    }

    async fn status(
        &self,
        _: Request<v1::EpisodeStatusRequest>,
    ) -> Result<Response<v1::RecordingStatus>, Status> {
        Ok(Response::new(current_recording_status(&self.app)))
    }

    async fn save_highlight(
        &self,
        request: Request<v1::SaveHighlightRequest>,
    ) -> Result<Response<v1::SaveHighlightResponse>, Status> {
        let started = Instant::now();
        let v1::SaveHighlightRequest {
            task,
            operator,
            keep_recording,
            outcome,
        } = request.into_inner();
        check_operator(&operator)?;
        // An unknown outcome is refused before anything is taken from the ring.
        let success = outcome_success(outcome).map_err(|e| RequestError::Refused(format!("outcome: {e}")))?;
        let app = &self.app;
        let done = blocking(|| {
            app.with_recorder(|r| {
                r.save_highlight(&task, &operator, keep_recording, success)
                    .map_err(RecordingError::from)
            })
        })?;
        let episode = match done {
            Highlight::Saved(summary) => Some(episode(&summary)),
            Highlight::Recording(_) => None,
        };
        Ok(Response::new(v1::SaveHighlightResponse {
            save_latency_s: if episode.is_some() {
                started.elapsed().as_secs_f64()
            } else {
                0.0
            },
            episode,
            status: Some(current_recording_status(app)),
        }))
    }

    type WatchStream = StatusStream;

    async fn watch(
        &self,
        request: Request<v1::WatchEpisodesRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let interval = super::error::watch_interval(request.into_inner().interval_s, 0.5)?;
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        let app = Arc::clone(&self.app);
        let mut shutdown = app.shutdown_signal();
        let mut changes = app.recorder_changes()?;
        tokio::spawn(async move {
            loop {
                let status = current_recording_status(&app);
                if tx.send(Ok(status)).await.is_err() {
                    break;
                }
                tokio::select! {
                    changed = changes.changed() => if changed.is_err() { break },
                    () = tokio::time::sleep(interval) => {}
                    () = tx.closed() => break,
                    () = crate::runtime::stopped(&mut shutdown) => break,
                }
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }
}

//! The Episodes service: start, stop, discard, save the last seconds, list, watch.

use crate::{AuthChannel, Client, Error, Result};
use phone2act_proto::v1;
use phone2act_proto::v1::episodes_client::EpisodesClient;

impl Client {
    /// The Episodes service: start, stop, discard, list, watch.
    pub fn episodes(&self) -> EpisodesApi {
        EpisodesApi {
            inner: self.episodes_raw(),
        }
    }

    /// The raw generated Episodes client.
    pub fn episodes_raw(&self) -> EpisodesClient<AuthChannel> {
        EpisodesClient::with_interceptor(self.transport(), self.auth())
    }
}

/// Typed access to the Episodes service.
#[derive(Clone, Debug)]
pub struct EpisodesApi {
    inner: EpisodesClient<AuthChannel>,
}

impl EpisodesApi {
    /// Starts recording an episode with `task`.
    pub async fn start(&mut self, task: &str) -> Result<v1::RecordingStatus> {
        self.start_by(task, "").await
    }

    /// Starts recording an episode with `task` by `operator` (kept in the episode's provenance).
    pub async fn start_by(&mut self, task: &str, operator: &str) -> Result<v1::RecordingStatus> {
        let response = self
            .inner
            .start(v1::StartEpisodeRequest {
                task: task.to_owned(),
                operator: operator.to_owned(),
            })
            .await?;
        response
            .into_inner()
            .status
            .ok_or_else(|| Error::Protocol("Start answered without status".into()))
    }

    /// Stops and saves the episode in progress; returns once it is committed.
    pub async fn stop(&mut self) -> Result<v1::StopEpisodeResponse> {
        self.stop_with(v1::EpisodeOutcome::Unspecified).await
    }

    /// Stops and saves the episode in progress with the operator's outcome (kept in its provenance and, in a
    /// dataset that records `next.success`, as its last frame's value); returns once it is committed.
    pub async fn stop_with(&mut self, outcome: v1::EpisodeOutcome) -> Result<v1::StopEpisodeResponse> {
        Ok(self
            .inner
            .stop(v1::StopEpisodeRequest {
                outcome: outcome.into(),
            })
            .await?
            .into_inner())
    }

    /// Throws away the episode in progress; returns the number of frames dropped.
    pub async fn discard(&mut self) -> Result<u64> {
        Ok(self
            .inner
            .discard(v1::DiscardEpisodeRequest {})
            .await?
            .into_inner()
            .frames_discarded)
    }

    /// Discards the episode in progress (if any) and starts again; an empty task keeps the previous one.
    pub async fn rerecord(&mut self, task: &str) -> Result<v1::RecordingStatus> {
        let response = self
            .inner
            .rerecord(v1::RerecordEpisodeRequest {
                task: task.to_owned(),
            })
            .await?;
        response
            .into_inner()
            .status
            .ok_or_else(|| Error::Protocol("Rerecord answered without status".into()))
    }

    /// Saves the last seconds the recorder kept while idle (`[recorder] highlight_s`, LeRobot's `highlight`) as
    /// an episode of `task`, with the operator's outcome; returns once it is committed (`episode` is set).
    pub async fn save_highlight(
        &mut self,
        task: &str,
        outcome: v1::EpisodeOutcome,
    ) -> Result<v1::SaveHighlightResponse> {
        self.save_highlight_with(v1::SaveHighlightRequest {
            task: task.to_owned(),
            outcome: outcome.into(),
            ..v1::SaveHighlightRequest::default()
        })
        .await
    }

    /// [`EpisodesApi::save_highlight`] with every field of the request: `operator`, and `keep_recording` (the
    /// kept seconds begin the episode in progress, which records on until [`EpisodesApi::stop`]).
    pub async fn save_highlight_with(
        &mut self,
        request: v1::SaveHighlightRequest,
    ) -> Result<v1::SaveHighlightResponse> {
        Ok(self.inner.save_highlight(request).await?.into_inner())
    }

    /// Saved episodes.
    pub async fn list(&mut self) -> Result<v1::ListEpisodesResponse> {
        Ok(self.inner.list(v1::ListEpisodesRequest {}).await?.into_inner())
    }

    /// The recorder's state.
    pub async fn status(&mut self) -> Result<v1::RecordingStatus> {
        Ok(self.inner.status(v1::EpisodeStatusRequest {}).await?.into_inner())
    }

    /// Recorder state on every change and at least every `interval_s`.
    pub async fn watch(&mut self, interval_s: f64) -> Result<tonic::Streaming<v1::RecordingStatus>> {
        Ok(self
            .inner
            .watch(v1::WatchEpisodesRequest { interval_s })
            .await?
            .into_inner())
    }
}

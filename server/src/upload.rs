//! `[storage]` wiring: the station id, the uploader of the recorder's dataset (fleet layout
//! `<prefix>/<station_id>/`), and the commit hook that queues every committed episode for it.

use crate::config::Config;
use phone2act_dataset::EpisodeSummary;
use phone2act_recorder::recorder::CommitHook;
use phone2act_storage::remote::RemoteOptions;
use phone2act_storage::{Credentials, Remote, StorageError, StorageUrl, Uploader};
use std::sync::Arc;

/// The station id of `config` (configured, or generated once beside the dataset); `None` without storage.
pub fn station_id(config: &Config) -> Result<Option<String>, StorageError> {
    config
        .storage
        .as_ref()
        .map(|s| s.station_id(&config.recorder.root))
        .transpose()
}

/// Starts the uploader for `config`'s dataset. Call after the recorder opened it, before serving.
pub fn start(config: &Config, station_id: &str) -> Result<Option<Arc<Uploader>>, StorageError> {
    let Some(storage) = &config.storage else {
        return Ok(None);
    };
    let url = StorageUrl::parse(&storage.url)
        .map_err(StorageError::Config)?
        .join(station_id);
    let credentials = Credentials::resolve_with_file(
        storage.profile.as_deref(),
        storage.credentials_file.as_deref(),
        &|k| std::env::var(k).ok(),
    )?;
    let remote = Remote::new(
        &url,
        &RemoteOptions {
            endpoint: storage.endpoint.clone(),
            region: storage.region.clone(),
            credentials,
            request_timeout: storage
                .request_timeout_s
                .filter(|s| s.is_finite() && *s > 0.0)
                .map(std::time::Duration::from_secs_f64),
            ..RemoteOptions::default()
        },
    )?;
    tracing::info!(%url, station_id, "storage: uploading committed episodes");
    Ok(Some(Arc::new(Uploader::start(
        &config.recorder.root,
        remote,
        station_id,
        storage.max_upload_bytes_per_s,
        storage.retain_local,
    )?)))
}

/// Queues each committed episode's files, in commit order, for upload.
pub struct UploadHook(pub Arc<Uploader>);

impl CommitHook for UploadHook {
    fn committed(&self, episode: &EpisodeSummary, files: &[String]) {
        self.0.committed(episode.index, files);
    }
}

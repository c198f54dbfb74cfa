//! An episode being recorded: the dataset's writer of its rows and events ([`EpisodeWriter`]) and one video
//! encoder per camera, started, saved and thrown away together.

use crate::av::EncoderThread;
use phone2act_dataset::dataset::{Dataset, EpisodeSummary, EpisodeWriter};
use phone2act_dataset::error::RecorderError;
use phone2act_dataset::spec::CameraSpec;
use std::ops::{Deref, DerefMut};

/// An episode's rows and events (through `Deref`) and its cameras' encoders, in `spec.cameras` order.
pub struct Episode {
    rows: EpisodeWriter,
    pub(crate) encoders: Vec<EncoderThread>,
}

impl Deref for Episode {
    type Target = EpisodeWriter;
    fn deref(&self) -> &EpisodeWriter {
        &self.rows
    }
}

impl DerefMut for Episode {
    fn deref_mut(&mut self) -> &mut EpisodeWriter {
        &mut self.rows
    }
}

impl Episode {
    /// Starts episode `total_episodes` of `ds` with a new encoder per camera.
    pub fn begin(ds: &mut Dataset, task: &str, queue_frames: usize) -> Result<Self, RecorderError> {
        let rows = ds.begin_episode(task)?;
        let (spec, video) = (ds.spec(), ds.video_settings());
        let encoders: Result<Vec<EncoderThread>, RecorderError> = spec
            .cameras
            .iter()
            .map(|c| {
                EncoderThread::spawn(
                    &c.name,
                    rows.video_path(&c.key()),
                    c.width,
                    c.height,
                    spec.fps,
                    video.clone(),
                    queue_frames,
                )
            })
            .collect();
        match encoders {
            Ok(encoders) => Ok(Episode { rows, encoders }),
            Err(e) => {
                ds.abort_episode(rows);
                Err(e)
            }
        }
    }

    /// Starts episode `total_episodes` of `ds` with the video the ring encoders keep from their frame
    /// `first_frame` (see [`EncoderThread::spawn_ring`]), one per camera in `spec.cameras` order. The encoders
    /// are taken only when the episode starts; on an error they stay in `ring`.
    pub fn begin_from_ring(
        ds: &mut Dataset,
        task: &str,
        ring: &mut Vec<EncoderThread>,
        first_frame: u64,
    ) -> Result<Self, RecorderError> {
        let keys: Vec<String> = ds.spec().cameras.iter().map(CameraSpec::key).collect();
        if ring.len() != keys.len() {
            return Err(RecorderError::InvalidSpec(format!(
                "{} ring encoders for {} cameras",
                ring.len(),
                keys.len()
            )));
        }
        let rows = ds.begin_episode(task)?;
        for (encoder, key) in ring.iter_mut().zip(&keys) {
            encoder.attach(rows.video_path(key), first_frame);
        }
        Ok(Episode {
            rows,
            encoders: std::mem::take(ring),
        })
    }

    /// Saves the episode into `ds` (see [`Dataset::commit_episode`]). The encoders are told to finish first,
    /// so they flush while the parquet file closes.
    pub fn commit(self, ds: &mut Dataset, summary: EpisodeSummary) -> Result<EpisodeSummary, RecorderError> {
        let Episode { rows, encoders } = self;
        let frames = rows.frames();
        // An encoder that never received a frame must not be flushed (SVT-AV1 hangs): the dataset refuses an
        // episode without frames before it asks for the videos, and dropping them then is enough.
        if frames > 0 {
            for e in &encoders {
                e.request_finish(frames);
            }
        }
        ds.commit_episode(rows, summary, || {
            // Every encoder is joined before the first error is returned, so none is left running.
            let reports: Vec<_> = encoders.into_iter().map(EncoderThread::join).collect();
            reports.into_iter().collect()
        })
    }

    /// Throws the episode away: its encoders stop before its staging files go.
    pub fn abort(self, ds: &mut Dataset) {
        let Episode { rows, encoders } = self;
        drop(encoders);
        ds.abort_episode(rows);
    }

    /// Video frames dropped so far, all cameras.
    pub fn dropped(&self) -> u64 {
        self.encoders.iter().map(EncoderThread::dropped).sum()
    }

    /// The name of a camera whose encoder has failed, if any.
    pub fn failed_camera(&self) -> Option<String> {
        self.encoders
            .iter()
            .find(|e| e.failed())
            .map(|e| e.camera().to_owned())
    }
}

//! `phone2act dataset push DIR URL` and `phone2act dataset pull URL DIR`: a dataset to and from
//! S3-compatible object storage (see docs/fleet.md).

use phone2act_storage::remote::RemoteOptions;
use phone2act_storage::{Credentials, Remote, StorageUrl};
use std::path::Path;

/// Where the remote is and how to reach it; credentials come from the `AWS_*` variables or the profile.
#[derive(clap::Args, Debug)]
pub(crate) struct RemoteArgs {
    /// S3-compatible endpoint (MinIO, R2, ...), e.g. http://127.0.0.1:9000; requests are then path-style.
    #[arg(long, env = "AWS_ENDPOINT_URL")]
    endpoint: Option<String>,
    #[arg(long, env = "AWS_REGION")]
    region: Option<String>,
    /// Profile of the shared credentials file, used when AWS_ACCESS_KEY_ID is not set.
    #[arg(long)]
    profile: Option<String>,
    /// Upload bandwidth cap.
    #[arg(long)]
    max_upload_bytes_per_s: Option<u64>,
}

fn remote(url: &str, args: &RemoteArgs) -> anyhow::Result<Remote> {
    let url = StorageUrl::parse(url).map_err(anyhow::Error::msg)?;
    let credentials = Credentials::resolve(args.profile.as_deref(), &|k| std::env::var(k).ok())?;
    Ok(Remote::new(
        &url,
        &RemoteOptions {
            endpoint: args.endpoint.clone(),
            region: args.region.clone(),
            credentials,
            ..RemoteOptions::default()
        },
    )?)
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?)
}

/// Pushes `dir` to `url`; returns the line to print.
pub(crate) fn push(dir: &Path, url: &str, args: &RemoteArgs) -> anyhow::Result<String> {
    let remote = remote(url, args)?;
    let t0 = std::time::Instant::now();
    let r = runtime()?.block_on(phone2act_storage::push(dir, &remote, args.max_upload_bytes_per_s))?;
    let s = t0.elapsed().as_secs_f64();
    Ok(format!(
        "pushed {} to {url}: {} episodes remote (was {}), {} objects put ({} bytes, {:.1} MB/s), {} already there",
        dir.display(),
        r.episodes_after,
        r.episodes_before,
        r.objects_put,
        r.bytes_put,
        r.bytes_put as f64 / s.max(1e-9) / 1e6,
        r.objects_skipped
    ))
}

/// Pulls `url` into `dir`; returns the line to print.
pub(crate) fn pull(url: &str, dir: &Path, args: &RemoteArgs) -> anyhow::Result<String> {
    let remote = remote(url, args)?;
    let episodes = runtime()?.block_on(phone2act_storage::pull(&remote, dir))?;
    Ok(format!(
        "pulled {url} into {}: {episodes} episodes",
        dir.display()
    ))
}

/// The file sizes of a merged or compacted dataset.
#[derive(clap::Args, Debug)]
pub(crate) struct SizeArgs {
    /// Largest data file, in MB (lerobot's default).
    #[arg(long, default_value_t = phone2act_dataset::dataset::DEFAULT_DATA_FILE_SIZE_MB)]
    data_file_size_mb: f64,
    /// Largest video file, in MB (lerobot's default).
    #[arg(long, default_value_t = phone2act_dataset::dataset::DEFAULT_VIDEO_FILE_SIZE_MB)]
    video_file_size_mb: f64,
}

fn is_url(s: &str) -> bool {
    s.starts_with("s3://")
}

/// Removes a scratch directory when dropped (also when the merge fails).
struct Scratch(std::path::PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A dataset on disk: the directory given, or a scratch copy of a URL (removed when dropped).
pub(crate) struct LocalCopy {
    path: std::path::PathBuf,
    _scratch: Option<Scratch>,
}

impl LocalCopy {
    pub(crate) fn path(&self) -> &Path {
        &self.path
    }
}

/// `path_or_url` as a directory: a URL is pulled (one committed state, see `phone2act_storage::pull`) into
/// a scratch directory under the system's temporary directory.
pub(crate) fn local_copy(path_or_url: &str, args: &RemoteArgs) -> anyhow::Result<LocalCopy> {
    use anyhow::Context as _;
    if !is_url(path_or_url) {
        return Ok(LocalCopy {
            path: path_or_url.into(),
            _scratch: None,
        });
    }
    let scratch = Scratch(std::env::temp_dir().join(format!(
        "phone2act-dataset-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos())
    )));
    let dir = scratch.0.join("dataset");
    let remote = remote(path_or_url, args)?;
    runtime()?
        .block_on(phone2act_storage::pull(&remote, &dir))
        .with_context(|| format!("downloading {path_or_url}"))?;
    Ok(LocalCopy {
        path: dir,
        _scratch: Some(scratch),
    })
}

/// Merges `sources` (directories or URLs, pulled first) into `out` (a new directory, or a URL the merged
/// dataset is pushed to); returns the line to print.
pub(crate) fn merge(
    sources: &[String],
    out: &str,
    sizes: &SizeArgs,
    args: &RemoteArgs,
) -> anyhow::Result<String> {
    use anyhow::Context as _;
    let t0 = std::time::Instant::now();
    let local_out = (!is_url(out)).then(|| std::path::PathBuf::from(out));
    // Downloads go next to a local output (the same file system, so a large merge does not fill a small
    // /tmp); for an output in storage, under the system's temporary directory (TMPDIR).
    let scratch_parent = match local_out.as_deref().and_then(Path::parent) {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        Some(_) => std::path::PathBuf::from("."),
        None => std::env::temp_dir(),
    };
    let scratch = Scratch(scratch_parent.join(format!(".phone2act-merge-{}", std::process::id())));
    let mut inputs = Vec::new();
    for (i, src) in sources.iter().enumerate() {
        let root = if is_url(src) {
            let dir = scratch.0.join(format!("in-{i}"));
            let remote = remote(src, args)?;
            runtime()?
                .block_on(phone2act_storage::pull(&remote, &dir))
                .with_context(|| format!("pulling {src}"))?;
            dir
        } else {
            std::path::PathBuf::from(src)
        };
        inputs.push(phone2act_dataset::dataset::MergeInput {
            root,
            label: src.clone(),
        });
    }
    let dest = local_out.clone().unwrap_or_else(|| scratch.0.join("out"));
    let opts = phone2act_dataset::dataset::MergeOptions {
        data_file_size_mb: sizes.data_file_size_mb,
        video_file_size_mb: sizes.video_file_size_mb,
    };
    let r = phone2act_dataset::dataset::merge(&inputs, &dest, &opts)?;
    if local_out.is_none() {
        let remote = remote(out, args)?;
        runtime()?
            .block_on(phone2act_storage::push(
                &dest,
                &remote,
                args.max_upload_bytes_per_s,
            ))
            .with_context(|| format!("pushing the merged dataset to {out}"))?;
    }
    Ok(format!(
        "merged {} dataset(s) into {out}: {} episodes, {} frames, {} tasks; {} files in, {} files out ({:.1} s)",
        sources.len(),
        r.episodes,
        r.frames,
        r.tasks,
        r.files_in,
        r.files_out,
        t0.elapsed().as_secs_f64()
    ))
}

/// `storage: s3://... (station st-...): 12 uploaded, 1 pending; last error: ...`
pub(crate) fn storage_line(s: &phone2act_sdk::proto::StorageStatus) -> String {
    let mut line = format!(
        "storage: {} (station {}): {} episodes uploaded, {} pending, {} objects put ({} bytes)",
        s.url, s.station_id, s.episodes_uploaded, s.episodes_pending, s.objects_put, s.bytes_put
    );
    if !s.last_error.is_empty() {
        line.push_str("; last error: ");
        line.push_str(&s.last_error);
    }
    line
}

/// `  [uploaded]`, `  [failed: reason]`, ... after an episode line; empty when storage is off.
pub(crate) fn upload_suffix(ep: &phone2act_sdk::proto::EpisodeInfo) -> String {
    use phone2act_sdk::proto::UploadState;
    let mut s = match ep.upload_state() {
        UploadState::Unspecified => String::new(),
        UploadState::Pending => "  [pending]".into(),
        UploadState::Uploading => "  [uploading]".into(),
        UploadState::Uploaded => "  [uploaded]".into(),
        UploadState::Failed => format!("  [failed: {}]", ep.upload_error),
    };
    if !ep.operator.is_empty() {
        s = format!("  by {}{s}", ep.operator);
    }
    s
}

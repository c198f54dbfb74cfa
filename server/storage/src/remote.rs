//! One remote dataset location (`s3://bucket/prefix`) over object_store: put a file (one PUT, or a streamed
//! multipart upload past [`PART_BYTES`]) with its sha256 as user metadata, ask whether an object is already
//! there intact, list, and download.

use crate::config::{Credentials, StorageUrl};
use crate::{StorageError, hex};
use bytes::Bytes;
use futures_util::StreamExt;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path as ObjectPath;
use object_store::{
    Attribute, Attributes, BackoffConfig, ClientOptions, GetOptions, ObjectStore, ObjectStoreExt,
    PutMultipartOptions, PutOptions, PutPayload, RetryConfig,
};
use std::io::Read;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Files up to this size go in one PUT (read whole: the uploader's memory bound); larger ones are uploaded
/// in parts of this size (S3's minimum part is 5 MiB).
pub const PART_BYTES: usize = 8 << 20;
/// The user metadata key holding the object's sha256 (`x-amz-meta-sha256`).
pub const SHA256_META: &str = "sha256";

/// Where and how to connect.
#[derive(Clone, Debug, Default)]
pub struct RemoteOptions {
    pub endpoint: Option<String>,
    pub region: Option<String>,
    pub credentials: Option<Credentials>,
    /// Per-request timeout (a stalled connection fails and is retried rather than hanging).
    pub request_timeout: Option<Duration>,
    /// object_store's own retries of one request (transient errors); the uploader retries on top.
    pub max_retries: Option<usize>,
}

/// A remote dataset root.
pub struct Remote {
    store: Arc<AmazonS3>,
    url: StorageUrl,
}

impl std::fmt::Debug for Remote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Not the store: its builder holds the secret.
        f.debug_struct("Remote")
            .field("url", &self.url.to_string())
            .finish_non_exhaustive()
    }
}

/// Object metadata as far as "already there and intact" needs it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RemoteObject {
    pub size_bytes: u64,
    pub sha256: Option<String>,
}

/// Paces uploads to `bytes_per_s`: every chunk waits until the bytes sent so far are due. Credit from idle
/// time is capped at one second so a burst after a pause stays near the cap. Shared by concurrent transfers
/// (a push sends several objects at once), so the cap holds for their sum.
#[derive(Debug)]
pub struct RateLimiter {
    bytes_per_s: Option<u64>,
    state: parking_lot::Mutex<RateState>,
}

#[derive(Debug)]
struct RateState {
    start: Instant,
    sent_bytes: u64,
}

impl RateLimiter {
    pub fn new(bytes_per_s: Option<u64>) -> Self {
        RateLimiter {
            bytes_per_s,
            state: parking_lot::Mutex::new(RateState {
                start: Instant::now(),
                sent_bytes: 0,
            }),
        }
    }

    pub async fn take(&self, n_bytes: u64) {
        let Some(rate) = self.bytes_per_s else { return };
        let wait_s = {
            // Never held across the sleep.
            let mut st = self.state.lock();
            let elapsed_s = st.start.elapsed().as_secs_f64();
            let due_s = st.sent_bytes as f64 / rate as f64;
            if elapsed_s > due_s + 1.0 {
                let now = Instant::now();
                st.start = now.checked_sub(Duration::from_secs(1)).unwrap_or(now);
                st.sent_bytes = rate;
            }
            st.sent_bytes += n_bytes;
            st.sent_bytes as f64 / rate as f64 - st.start.elapsed().as_secs_f64()
        };
        if wait_s > 0.0 {
            tokio::time::sleep(Duration::from_secs_f64(wait_s)).await;
        }
    }
}

/// rustls needs a process-wide crypto provider when reqwest is built without one: ring, already in the tree.
fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// An object_store error as an operator reads it: S3's own message, plus what to check for the usual
/// causes (the error text holds the URL and S3's reply, never the signing secret).
pub fn describe(e: &object_store::Error) -> String {
    let mut text = e.to_string();
    let mut src = std::error::Error::source(e);
    while let Some(s) = src {
        let t = s.to_string();
        if !text.contains(&t) {
            text.push_str(": ");
            text.push_str(&t);
        }
        src = s.source();
    }
    // S3 answers with an XML body: keep its error code, not the markup (request ids, host ids).
    if let Some(start) = text.find("<?xml") {
        let code = text[start..]
            .split_once("<Code>")
            .and_then(|(_, r)| r.split_once("</Code>"))
            .map(|(c, _)| c.to_owned());
        text.truncate(start);
        if let Some(code) = code {
            text.push_str(&code);
        }
    }
    let hint = if text.contains("NoSuchBucket") {
        Some("the bucket does not exist: create it, or fix storage.url")
    } else if text.contains("InvalidAccessKeyId")
        || text.contains("SignatureDoesNotMatch")
        || text.contains("AccessDenied")
        || text.contains("403")
    {
        Some("access denied: check AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (or the profile)")
    } else if text.contains("error sending request") || text.contains("Connection refused") {
        Some("the storage endpoint is unreachable")
    } else {
        None
    };
    match hint {
        Some(h) => format!("{h} ({text})"),
        None => text,
    }
}

impl Remote {
    pub fn new(url: &StorageUrl, opts: &RemoteOptions) -> Result<Self, StorageError> {
        install_crypto_provider();
        let mut b = AmazonS3Builder::new()
            .with_bucket_name(&url.bucket)
            .with_region(opts.region.as_deref().unwrap_or("us-east-1"))
            .with_retry(RetryConfig {
                backoff: BackoffConfig {
                    init_backoff: Duration::from_millis(100),
                    max_backoff: Duration::from_secs(2),
                    base: 2.0,
                },
                max_retries: opts.max_retries.unwrap_or(3),
                retry_timeout: Duration::from_secs(30),
            })
            .with_client_options(
                ClientOptions::new()
                    .with_timeout(opts.request_timeout.unwrap_or(Duration::from_mins(2)))
                    .with_connect_timeout(Duration::from_secs(10))
                    .with_allow_http(opts.endpoint.as_deref().is_some_and(|e| e.starts_with("http://"))),
            );
        if let Some(ep) = &opts.endpoint {
            // Path-style (bucket in the path) is what MinIO, moto and most on-premise S3 expect.
            b = b.with_endpoint(ep).with_virtual_hosted_style_request(false);
        }
        if let Some(c) = &opts.credentials {
            b = b.with_access_key_id(&c.key_id).with_secret_access_key(&c.secret);
            if let Some(t) = &c.token {
                b = b.with_token(t);
            }
        }
        let store = b.build().map_err(|e| StorageError::Remote {
            url: url.to_string(),
            detail: describe(&e),
        })?;
        Ok(Remote {
            store: Arc::new(store),
            url: url.clone(),
        })
    }

    pub fn url(&self) -> &StorageUrl {
        &self.url
    }

    fn path(&self, rel: &str) -> ObjectPath {
        if self.url.prefix.is_empty() {
            ObjectPath::from(rel)
        } else {
            ObjectPath::from(format!("{}/{rel}", self.url.prefix))
        }
    }

    fn err(&self, rel: &str, e: &object_store::Error) -> StorageError {
        StorageError::Remote {
            url: format!("{}/{rel}", self.url),
            detail: describe(e),
        }
    }

    /// The object at `rel`, or `None` if there is none.
    pub async fn head(&self, rel: &str) -> Result<Option<RemoteObject>, StorageError> {
        let opts = GetOptions {
            head: true,
            ..GetOptions::default()
        };
        match self.store.get_opts(&self.path(rel), opts).await {
            Ok(r) => Ok(Some(RemoteObject {
                size_bytes: r.meta.size,
                sha256: r
                    .attributes
                    .get(&Attribute::Metadata(SHA256_META.into()))
                    .map(|v| v.as_ref().to_owned()),
            })),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.err(rel, &e)),
        }
    }

    /// Whether `rel` is already remote with this size and sha256. An object without the sha256 metadata (put
    /// by another tool) is downloaded and hashed rather than trusted.
    pub async fn intact(&self, rel: &str, size_bytes: u64, sha256: &str) -> Result<bool, StorageError> {
        match self.head(rel).await? {
            None => Ok(false),
            Some(o) if o.size_bytes != size_bytes => Ok(false),
            Some(RemoteObject { sha256: Some(s), .. }) => Ok(s == sha256),
            Some(_) => Ok(self.sha256_of(rel).await?.as_deref() == Some(sha256)),
        }
    }

    /// sha256 of the remote object's bytes (streamed), or `None` if there is none.
    pub async fn sha256_of(&self, rel: &str) -> Result<Option<String>, StorageError> {
        let r = match self.store.get(&self.path(rel)).await {
            Ok(r) => r,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.err(rel, &e)),
        };
        let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
        let mut s = r.into_stream();
        while let Some(chunk) = s.next().await {
            ctx.update(&chunk.map_err(|e| self.err(rel, &e))?);
        }
        Ok(Some(hex(ctx.finish().as_ref())))
    }

    /// Uploads `local` as `rel`, paced by `limiter`. The object appears whole or not at all.
    pub async fn put_file(
        &self,
        rel: &str,
        local: &Path,
        sha256: &str,
        limiter: &RateLimiter,
    ) -> Result<(), StorageError> {
        let mut attributes = Attributes::new();
        attributes.insert(Attribute::Metadata(SHA256_META.into()), sha256.to_owned().into());
        let mut f = std::fs::File::open(local).map_err(|e| StorageError::io(local, e))?;
        let first = read_part(&mut f, local)?;
        if first.len() < PART_BYTES {
            limiter.take(first.len() as u64).await;
            let opts = PutOptions {
                attributes,
                ..PutOptions::default()
            };
            self.store
                .put_opts(&self.path(rel), PutPayload::from(first), opts)
                .await
                .map_err(|e| self.err(rel, &e))?;
            return Ok(());
        }
        let opts = PutMultipartOptions {
            attributes,
            ..PutMultipartOptions::default()
        };
        let mut upload = self
            .store
            .put_multipart_opts(&self.path(rel), opts)
            .await
            .map_err(|e| self.err(rel, &e))?;
        let mut part = first;
        let r: Result<(), StorageError> = async {
            loop {
                limiter.take(part.len() as u64).await;
                upload
                    .put_part(PutPayload::from(part))
                    .await
                    .map_err(|e| self.err(rel, &e))?;
                part = read_part(&mut f, local)?;
                if part.is_empty() {
                    break;
                }
            }
            upload.complete().await.map_err(|e| self.err(rel, &e))?;
            Ok(())
        }
        .await;
        if r.is_err() {
            // Parts of an unfinished multipart upload are invisible to readers; abort frees them.
            let _ = upload.abort().await;
        }
        r
    }

    /// Uploads `bytes` as `rel` (small metadata), with their sha256.
    pub async fn put_bytes(&self, rel: &str, bytes: Vec<u8>) -> Result<(), StorageError> {
        let sha = hex(ring::digest::digest(&ring::digest::SHA256, &bytes).as_ref());
        let mut attributes = Attributes::new();
        attributes.insert(Attribute::Metadata(SHA256_META.into()), sha.into());
        let opts = PutOptions {
            attributes,
            ..PutOptions::default()
        };
        self.store
            .put_opts(&self.path(rel), PutPayload::from(bytes), opts)
            .await
            .map_err(|e| self.err(rel, &e))?;
        Ok(())
    }

    /// The whole object (small metadata files), or `None` if there is none.
    pub async fn get_bytes(&self, rel: &str) -> Result<Option<Bytes>, StorageError> {
        match self.store.get(&self.path(rel)).await {
            Ok(r) => Ok(Some(r.bytes().await.map_err(|e| self.err(rel, &e))?)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.err(rel, &e)),
        }
    }

    /// Streams the object into `dest` (through a temp file beside it, renamed when complete).
    pub async fn get_to_file(&self, rel: &str, dest: &Path) -> Result<u64, StorageError> {
        use std::io::Write;
        let r = self
            .store
            .get(&self.path(rel))
            .await
            .map_err(|e| self.err(rel, &e))?;
        let dir = dest.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(dir).map_err(|e| StorageError::io(dir, e))?;
        let tmp = dir.join(format!(
            ".{}.part",
            dest.file_name().and_then(|n| n.to_str()).unwrap_or("download")
        ));
        let mut f = std::fs::File::create(&tmp).map_err(|e| StorageError::io(&tmp, e))?;
        let mut n = 0u64;
        let mut s = r.into_stream();
        while let Some(chunk) = s.next().await {
            let chunk = chunk.map_err(|e| self.err(rel, &e))?;
            n += chunk.len() as u64;
            f.write_all(&chunk).map_err(|e| StorageError::io(&tmp, e))?;
        }
        f.sync_all().map_err(|e| StorageError::io(&tmp, e))?;
        std::fs::rename(&tmp, dest).map_err(|e| StorageError::io(dest, e))?;
        Ok(n)
    }

    /// Every object under the dataset root: `(path relative to it, size)`, sorted by path.
    pub async fn list(&self) -> Result<Vec<(String, u64)>, StorageError> {
        let prefix = (!self.url.prefix.is_empty()).then(|| ObjectPath::from(self.url.prefix.as_str()));
        let mut s = self.store.list(prefix.as_ref());
        let mut out = Vec::new();
        let strip = if self.url.prefix.is_empty() {
            String::new()
        } else {
            format!("{}/", self.url.prefix)
        };
        while let Some(m) = s.next().await {
            let m = m.map_err(|e| self.err("", &e))?;
            let full = m.location.to_string();
            if let Some(rel) = full.strip_prefix(&strip) {
                out.push((rel.to_owned(), m.size));
            }
        }
        out.sort();
        Ok(out)
    }
}

/// Reads up to [`PART_BYTES`] (fewer only at the end of the file).
fn read_part(f: &mut std::fs::File, path: &Path) -> Result<Vec<u8>, StorageError> {
    let mut buf = vec![0u8; PART_BYTES];
    let mut n = 0;
    while n < PART_BYTES {
        let k = f.read(&mut buf[n..]).map_err(|e| StorageError::io(path, e))?;
        if k == 0 {
            break;
        }
        n += k;
    }
    buf.truncate(n);
    Ok(buf)
}

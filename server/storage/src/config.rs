//! The `[storage]` table of the server config, the `s3://bucket/prefix` URL, credentials (from the usual
//! `AWS_*` variables or a profile of the shared credentials file; never from the config file, so a config
//! printed by `serve --check` or recorded in provenance holds no secret), and the station id.

use crate::StorageError;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

/// The file beside the dataset (inside its root, hidden from lerobot) that keeps the generated station id.
pub const STATION_ID_FILE: &str = ".phone2act-station-id";

/// `[storage]`: where committed episodes are uploaded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StorageConfig {
    /// `s3://bucket/prefix`; the station's dataset goes to `<prefix>/<station_id>/`.
    pub url: String,
    /// An S3-compatible endpoint (MinIO, R2, moto, ...); `http://` is allowed (loopback, private networks).
    /// Requests are path-style whenever an endpoint is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub endpoint: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<String>,
    /// A profile of `~/.aws/credentials` (or `AWS_SHARED_CREDENTIALS_FILE`), used when `AWS_ACCESS_KEY_ID`
    /// is not set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<String>,
    /// An AWS shared credentials file to read `profile` (default `default`) from, instead of the
    /// environment: a station's own key file, kept out of the config (which never holds a secret).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub credentials_file: Option<PathBuf>,
    /// Upload bandwidth cap; unlimited when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_upload_bytes_per_s: Option<u64>,
    /// How long one request may take before it is abandoned and retried (a stalled connection, a relay that
    /// stopped forwarding); default 120 s, long enough for an 8 MiB part over a slow uplink.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub request_timeout_s: Option<f64>,
    /// Keep the local copy of uploaded episodes (default). With `false`, an episode's data and video files are
    /// removed from the station's disk once the storage holds them intact (checked again just before the
    /// removal: same size, same sha256); the metadata stays, so the station keeps recording into the same
    /// dataset, and the whole dataset is the remote copy (`dataset pull`).
    #[serde(default = "default_true")]
    pub retain_local: bool,
    /// This station's name in the fleet layout; default: a stable id generated once and kept in
    /// [`STATION_ID_FILE`] inside the dataset root.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub station_id: Option<String>,
}

fn default_true() -> bool {
    true
}

impl StorageConfig {
    /// `url` with every other key at its default.
    pub fn new(url: impl Into<String>) -> Self {
        StorageConfig {
            url: url.into(),
            endpoint: None,
            region: None,
            profile: None,
            credentials_file: None,
            max_upload_bytes_per_s: None,
            request_timeout_s: None,
            retain_local: true,
            station_id: None,
        }
    }

    /// What is wrong with the table, if anything (checked at load, before anything starts).
    pub fn validate(&self) -> Result<(), String> {
        StorageUrl::parse(&self.url).map_err(|e| format!("storage.url: {e}"))?;
        if let Some(ep) = &self.endpoint
            && !(ep.starts_with("http://") || ep.starts_with("https://"))
        {
            return Err(format!(
                "storage.endpoint must start with http:// or https://, got {ep:?}"
            ));
        }
        if self.max_upload_bytes_per_s == Some(0) {
            return Err("storage.max_upload_bytes_per_s must be > 0 (leave it out for no cap)".into());
        }
        if let Some(t) = self.request_timeout_s
            && !(t.is_finite() && t > 0.0)
        {
            return Err(format!(
                "storage.request_timeout_s = {t}: must be a positive number of seconds"
            ));
        }
        if let Some(id) = &self.station_id {
            check_station_id(id).map_err(|e| format!("storage.station_id: {e}"))?;
        }
        Ok(())
    }

    /// The station id: the configured one, or the one generated for this dataset (created on first use).
    pub fn station_id(&self, dataset_root: &Path) -> Result<String, StorageError> {
        match &self.station_id {
            Some(id) => Ok(id.clone()),
            None => station_id_for(dataset_root),
        }
    }
}

/// A station id is one path segment of the fleet layout.
pub fn check_station_id(id: &str) -> Result<(), String> {
    if id.is_empty() || id.len() > 64 {
        return Err(format!("must be 1 to 64 characters, got {}", id.len()));
    }
    if !id
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.')
        || id.starts_with('.')
    {
        return Err(format!(
            "{id:?}: only letters, digits, '-', '_' and '.' (not first) are allowed"
        ));
    }
    Ok(())
}

/// The dataset's generated station id, created (random, `st-` + 12 hex digits) and stored atomically the
/// first time, so it survives restarts and stays with the dataset.
pub fn station_id_for(dataset_root: &Path) -> Result<String, StorageError> {
    let path = dataset_root.join(STATION_ID_FILE);
    if let Ok(text) = std::fs::read_to_string(&path) {
        let id = text.trim().to_owned();
        if check_station_id(&id).is_ok() {
            return Ok(id);
        }
    }
    let mut bytes = [0u8; 6];
    ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut bytes)
        .map_err(|_| StorageError::Start("no system randomness for the station id".into()))?;
    let id = format!("st-{}", crate::hex(&bytes));
    std::fs::create_dir_all(dataset_root).map_err(|e| StorageError::io(dataset_root, e))?;
    crate::journal::write_atomic(&path, format!("{id}\n").as_bytes())?;
    Ok(id)
}

/// `s3://bucket/prefix`, split.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StorageUrl {
    pub bucket: String,
    /// Without leading or trailing `/`; empty for the bucket's root.
    pub prefix: String,
}

impl StorageUrl {
    pub fn parse(url: &str) -> Result<Self, String> {
        let rest = url
            .strip_prefix("s3://")
            .ok_or_else(|| format!("{url:?} is not an s3://bucket/prefix URL"))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.is_empty() {
            return Err(format!("{url:?} names no bucket"));
        }
        let prefix = prefix.trim_matches('/').to_owned();
        if prefix.split('/').any(|s| s == ".." || s == ".") {
            return Err(format!("{url:?}: '.' and '..' are not prefix segments"));
        }
        Ok(StorageUrl {
            bucket: bucket.to_owned(),
            prefix,
        })
    }

    /// This URL with `segment` appended to the prefix (a station's dataset in the fleet layout).
    #[must_use]
    pub fn join(&self, segment: &str) -> StorageUrl {
        let prefix = if self.prefix.is_empty() {
            segment.to_owned()
        } else {
            format!("{}/{segment}", self.prefix)
        };
        StorageUrl {
            bucket: self.bucket.clone(),
            prefix,
        }
    }

    pub fn is_url(s: &str) -> bool {
        s.starts_with("s3://")
    }
}

impl fmt::Display for StorageUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.prefix.is_empty() {
            write!(f, "s3://{}", self.bucket)
        } else {
            write!(f, "s3://{}/{}", self.bucket, self.prefix)
        }
    }
}

/// AWS credentials. `Debug` shows the key id only: the secret and session token never reach a log line.
#[derive(Clone)]
pub struct Credentials {
    pub key_id: String,
    pub(crate) secret: String,
    pub(crate) token: Option<String>,
}

impl fmt::Debug for Credentials {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Credentials")
            .field("key_id", &self.key_id)
            .field("secret", &"<redacted>")
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .finish()
    }
}

impl Credentials {
    /// `AWS_ACCESS_KEY_ID`/`AWS_SECRET_ACCESS_KEY`/`AWS_SESSION_TOKEN` when set, else `profile` (or
    /// `AWS_PROFILE`) from the shared credentials file; `None` leaves object_store's own chain (instance
    /// metadata, web identity) to find them.
    pub fn resolve(
        profile: Option<&str>,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Result<Option<Credentials>, StorageError> {
        Self::resolve_with_file(profile, None, env)
    }

    /// Like [`Credentials::resolve`]; an explicit `credentials_file` comes first.
    pub fn resolve_with_file(
        profile: Option<&str>,
        credentials_file: Option<&Path>,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Result<Option<Credentials>, StorageError> {
        if let Some(file) = credentials_file {
            return read_profile(file, profile.unwrap_or("default")).map(Some);
        }
        if let Some(key_id) = env("AWS_ACCESS_KEY_ID").filter(|s| !s.is_empty()) {
            let secret = env("AWS_SECRET_ACCESS_KEY").ok_or_else(|| {
                StorageError::Config("AWS_ACCESS_KEY_ID is set but AWS_SECRET_ACCESS_KEY is not".into())
            })?;
            return Ok(Some(Credentials {
                key_id,
                secret,
                token: env("AWS_SESSION_TOKEN").filter(|s| !s.is_empty()),
            }));
        }
        let profile = profile.map(str::to_owned).or_else(|| env("AWS_PROFILE"));
        let Some(profile) = profile else {
            return Ok(None);
        };
        let file = env("AWS_SHARED_CREDENTIALS_FILE")
            .map(PathBuf::from)
            .or_else(|| env("HOME").map(|h| PathBuf::from(h).join(".aws/credentials")))
            .ok_or_else(|| StorageError::Config("no credentials file (HOME is not set)".into()))?;
        read_profile(&file, &profile).map(Some)
    }
}

fn read_profile(file: &Path, profile: &str) -> Result<Credentials, StorageError> {
    let text = std::fs::read_to_string(file).map_err(|e| StorageError::io(file, e))?;
    profile_credentials(&text, profile).ok_or_else(|| {
        StorageError::Config(format!(
            "profile {profile:?} in {} has no aws_access_key_id and aws_secret_access_key",
            file.display()
        ))
    })
}

/// The `[profile]` section of an AWS shared credentials file (INI).
fn profile_credentials(text: &str, profile: &str) -> Option<Credentials> {
    let mut in_section = false;
    let (mut key_id, mut secret, mut token) = (None, None, None);
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('#') || line.starts_with(';') || line.is_empty() {
            continue;
        }
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            let name = name.trim();
            in_section = name == profile || name.strip_prefix("profile ").map(str::trim) == Some(profile);
            continue;
        }
        if !in_section {
            continue;
        }
        if let Some((k, v)) = line.split_once('=') {
            let v = v.trim().to_owned();
            match k.trim() {
                "aws_access_key_id" => key_id = Some(v),
                "aws_secret_access_key" => secret = Some(v),
                "aws_session_token" => token = Some(v),
                _ => {}
            }
        }
    }
    Some(Credentials {
        key_id: key_id?,
        secret: secret?,
        token,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_split_into_bucket_and_prefix() {
        let u = StorageUrl::parse("s3://fleet/lab/a/").unwrap();
        assert_eq!((u.bucket.as_str(), u.prefix.as_str()), ("fleet", "lab/a"));
        assert_eq!(u.join("st-1").to_string(), "s3://fleet/lab/a/st-1");
        assert_eq!(
            StorageUrl::parse("s3://b").unwrap().join("x").to_string(),
            "s3://b/x"
        );
        assert!(StorageUrl::parse("https://b/x").is_err());
        assert!(StorageUrl::parse("s3:///x").is_err());
        assert!(StorageUrl::parse("s3://b/../x").is_err());
    }

    #[test]
    fn credentials_come_from_env_then_profile_and_never_print_the_secret() {
        let env = |k: &str| match k {
            "AWS_ACCESS_KEY_ID" => Some("AKID".to_owned()),
            "AWS_SECRET_ACCESS_KEY" => Some("s3cr3t-value".to_owned()),
            _ => None,
        };
        let c = Credentials::resolve(None, &env).unwrap().unwrap();
        assert_eq!(c.key_id, "AKID");
        assert!(!format!("{c:?}").contains("s3cr3t"));

        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("credentials");
        std::fs::write(
            &file,
            "[default]\naws_access_key_id = D\naws_secret_access_key = d\n[lab]\naws_access_key_id=L\naws_secret_access_key=l\n",
        )
        .unwrap();
        let f = file.to_string_lossy().into_owned();
        let env = move |k: &str| (k == "AWS_SHARED_CREDENTIALS_FILE").then(|| f.clone());
        let c = Credentials::resolve(Some("lab"), &env).unwrap().unwrap();
        assert_eq!((c.key_id.as_str(), c.secret.as_str()), ("L", "l"));
        assert!(Credentials::resolve(Some("nope"), &env).is_err());
        assert!(Credentials::resolve(None, &|_| None).unwrap().is_none());
    }

    #[test]
    fn the_generated_station_id_is_stable() {
        let dir = tempfile::tempdir().unwrap();
        let a = station_id_for(dir.path()).unwrap();
        assert!(a.starts_with("st-") && check_station_id(&a).is_ok());
        assert_eq!(station_id_for(dir.path()).unwrap(), a);
        assert!(check_station_id("a/b").is_err());
        assert!(check_station_id(".x").is_err());
    }
}

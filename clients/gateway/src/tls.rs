//! HTTPS material for the phone page: a given certificate and key, or a self-signed certificate generated on
//! first start and kept in `cert_dir` (so the phone's "proceed anyway" is needed once), plus the pairing
//! token, the LAN address to print and the QR code that carries both.
//!
//! WebXR only exists in a secure context, which on a LAN means HTTPS; a browser can only open `wss://` from
//! an HTTPS page, so the page and its socket share this one TLS server.

use crate::config::GatewayConfig;
use crate::error::GatewayError;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::net::{IpAddr, Ipv4Addr, SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::sync::Arc;

const CERT_FILE: &str = "gateway-cert.pem";
const KEY_FILE: &str = "gateway-key.pem";
const TOKEN_FILE: &str = "pairing-token";

/// Where generated material is kept when the config does not say.
pub fn default_cert_dir() -> PathBuf {
    if let Some(data) = std::env::var_os("XDG_DATA_HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(data).join("phone2act/gateway");
    }
    if let Some(home) = std::env::var_os("HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(home).join(".local/share/phone2act/gateway");
    }
    PathBuf::from(".phone2act-gateway")
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> GatewayError {
    GatewayError::Tls(format!("{}: {e}", path.display()))
}

fn write_private(path: &Path, contents: &str) -> Result<(), GatewayError> {
    use std::io::Write;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options.open(path).map_err(|e| io_err(path, e))?;
    file.write_all(contents.as_bytes()).map_err(|e| io_err(path, e))
}

/// The certificate and key in use and whether they were generated just now.
#[derive(Debug)]
pub struct TlsMaterial {
    pub certs: Vec<CertificateDer<'static>>,
    pub key: PrivateKeyDer<'static>,
    pub cert_path: PathBuf,
    pub generated: bool,
}

/// Loads `cert_file`/`key_file`, or the kept generated pair, or generates one valid for `hosts`.
pub fn load_or_generate(
    config: &GatewayConfig,
    cert_dir: &Path,
    hosts: &[String],
) -> Result<TlsMaterial, GatewayError> {
    let (cert_path, key_path) = match (&config.cert_file, &config.key_file) {
        (Some(c), Some(k)) => (c.clone(), k.clone()),
        (None, None) => (cert_dir.join(CERT_FILE), cert_dir.join(KEY_FILE)),
        _ => {
            return Err(GatewayError::Tls(
                "cert_file and key_file must be given together".into(),
            ));
        }
    };
    let mut generated = false;
    if !cert_path.exists() || !key_path.exists() {
        if config.cert_file.is_some() {
            return Err(GatewayError::Tls(format!(
                "{} or {} does not exist",
                cert_path.display(),
                key_path.display()
            )));
        }
        std::fs::create_dir_all(cert_dir).map_err(|e| io_err(cert_dir, e))?;
        let (cert_pem, key_pem) = generate_self_signed(hosts)?;
        write_private(&key_path, &key_pem)?;
        std::fs::write(&cert_path, cert_pem).map_err(|e| io_err(&cert_path, e))?;
        generated = true;
        tracing::info!(cert = %cert_path.display(), "generated a self-signed certificate");
    }
    let certs = CertificateDer::pem_file_iter(&cert_path)
        .map_err(|e| io_err(&cert_path, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| io_err(&cert_path, e))?;
    if certs.is_empty() {
        return Err(io_err(&cert_path, "no certificate in file"));
    }
    let key = PrivateKeyDer::from_pem_file(&key_path).map_err(|e| io_err(&key_path, e))?;
    Ok(TlsMaterial {
        certs,
        key,
        cert_path,
        generated,
    })
}

/// A self-signed certificate for `hosts` (names and IP addresses) plus localhost; returns (cert, key) PEM.
pub fn generate_self_signed(hosts: &[String]) -> Result<(String, String), GatewayError> {
    let mut names: Vec<String> = vec!["localhost".into(), "127.0.0.1".into(), "::1".into()];
    for host in hosts {
        if !names.contains(host) {
            names.push(host.clone());
        }
    }
    let mut params = rcgen::CertificateParams::new(names).map_err(|e| GatewayError::Tls(e.to_string()))?;
    params.distinguished_name = rcgen::DistinguishedName::new();
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "phone2act gateway");
    // Long enough to never bother an operator; browsers do not apply the 398-day rule to certificates the
    // user accepted by hand.
    let now = std::time::SystemTime::now();
    params.not_before = (now - std::time::Duration::from_hours(24)).into();
    params.not_after = (now + std::time::Duration::from_hours(10 * 365 * 24)).into();
    let key = rcgen::KeyPair::generate().map_err(|e| GatewayError::Tls(e.to_string()))?;
    let cert = params
        .self_signed(&key)
        .map_err(|e| GatewayError::Tls(e.to_string()))?;
    Ok((cert.pem(), key.serialize_pem()))
}

/// A rustls server config on the ring provider (aws-lc is not built), HTTP/1.1 only: browsers open
/// WebSockets over HTTP/1.1, and one protocol keeps the page and its socket on the same path.
pub fn server_config(material: TlsMaterial) -> Result<Arc<rustls::ServerConfig>, GatewayError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| GatewayError::Tls(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(material.certs, material.key)
        .map_err(|e| GatewayError::Tls(format!("{}: {e}", material.cert_path.display())))?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(config))
}

/// The configured token, the kept one, or a new one written to `cert_dir`. `None` when not required.
pub fn pairing_token(config: &GatewayConfig, cert_dir: &Path) -> Result<Option<String>, GatewayError> {
    if !config.require_token {
        return Ok(None);
    }
    if let Some(token) = config.token.as_ref().filter(|t| !t.is_empty()) {
        return Ok(Some(token.clone()));
    }
    let path = cert_dir.join(TOKEN_FILE);
    if let Ok(kept) = std::fs::read_to_string(&path) {
        let kept = kept.trim();
        if !kept.is_empty() {
            return Ok(Some(kept.to_owned()));
        }
    }
    std::fs::create_dir_all(cert_dir).map_err(|e| io_err(cert_dir, e))?;
    let token = random_token()?;
    write_private(&path, &token)?;
    Ok(Some(token))
}

/// 16 characters from a 62-letter alphabet (~95 bits): short enough to type, long enough not to guess.
pub fn random_token() -> Result<String, GatewayError> {
    const ALPHABET: &[u8] = b"ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz23456789";
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)
        .map_err(|e| GatewayError::Tls(format!("no randomness for the token: {e}")))?;
    Ok(bytes
        .iter()
        .map(|b| ALPHABET[usize::from(*b) % ALPHABET.len()] as char)
        .collect())
}

/// Compares without an early exit, so the time taken does not reveal how much of a guess was right.
pub fn token_matches(expected: &str, got: &str) -> bool {
    expected.len() == got.len()
        && expected
            .bytes()
            .zip(got.bytes())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
}

/// The address a phone on the LAN should use: the listen address if specific, else the interface with the
/// default route (found by "connecting" a UDP socket, which sends nothing).
pub fn lan_host(listen: SocketAddr) -> String {
    if !listen.ip().is_unspecified() {
        return listen.ip().to_string();
    }
    let routed = UdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0))
        .and_then(|s| s.connect((Ipv4Addr::new(192, 0, 2, 1), 9)).map(|()| s))
        .and_then(|s| s.local_addr())
        .map(|a| a.ip());
    match routed {
        Ok(ip) if !ip.is_unspecified() => ip.to_string(),
        _ => IpAddr::V4(Ipv4Addr::LOCALHOST).to_string(),
    }
}

/// The page URL with the token (if any).
pub fn page_url(host: &str, port: u16, token: Option<&str>) -> String {
    let host = if host.contains(':') && !host.starts_with('[') {
        format!("[{host}]")
    } else {
        host.to_owned()
    };
    match token {
        Some(t) => format!("https://{host}:{port}/?token={t}"),
        None => format!("https://{host}:{port}/"),
    }
}

/// A QR code for `text` drawn with Unicode half blocks (two modules per character row).
pub fn qr_text(text: &str) -> Result<String, GatewayError> {
    let code =
        qrcode::QrCode::new(text.as_bytes()).map_err(|e| GatewayError::Tls(format!("QR code: {e}")))?;
    Ok(code
        .render::<qrcode::render::unicode::Dense1x2>()
        .dark_color(qrcode::render::unicode::Dense1x2::Light)
        .light_color(qrcode::render::unicode::Dense1x2::Dark)
        .quiet_zone(true)
        .build())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_material_is_kept_and_reused() {
        let dir = tempfile::tempdir().unwrap();
        let config = GatewayConfig::default();
        let first = load_or_generate(&config, dir.path(), &["192.168.1.20".into()]).unwrap();
        assert!(first.generated);
        let second = load_or_generate(&config, dir.path(), &["10.0.0.1".into()]).unwrap();
        assert!(!second.generated);
        assert_eq!(first.certs, second.certs, "certificate changed between starts");
        server_config(second).unwrap();
        let t1 = pairing_token(&config, dir.path()).unwrap().unwrap();
        let t2 = pairing_token(&config, dir.path()).unwrap().unwrap();
        assert_eq!(t1, t2);
        assert_eq!(t1.len(), 16);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join(KEY_FILE))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o077, 0, "private key readable by others: {mode:o}");
        }
    }

    #[test]
    fn half_given_cert_and_key_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let config = GatewayConfig {
            cert_file: Some(dir.path().join("c.pem")),
            ..GatewayConfig::default()
        };
        assert!(load_or_generate(&config, dir.path(), &[]).is_err());
        let config = GatewayConfig {
            cert_file: Some(dir.path().join("c.pem")),
            key_file: Some(dir.path().join("k.pem")),
            ..GatewayConfig::default()
        };
        assert!(
            load_or_generate(&config, dir.path(), &[])
                .unwrap_err()
                .to_string()
                .contains("does not exist")
        );
    }

    #[test]
    fn tokens_compare_exactly_and_urls_carry_them() {
        assert!(token_matches("abc", "abc"));
        assert!(!token_matches("abc", "abd"));
        assert!(!token_matches("abc", "ab"));
        assert_eq!(
            page_url("10.0.0.5", 8443, Some("T0k")),
            "https://10.0.0.5:8443/?token=T0k"
        );
        assert_eq!(page_url("fe80::1", 8443, None), "https://[fe80::1]:8443/");
        assert_ne!(random_token().unwrap(), random_token().unwrap());
        let qr = qr_text("https://10.0.0.5:8443/?token=T0k").unwrap();
        assert!(qr.lines().count() > 10);
    }
}

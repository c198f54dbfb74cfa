//! `phone2act-gateway`: the phone gateway on its own, in front of a phone2act server on another machine (or
//! the same one). `phone2act serve` embeds the same gateway; this binary is for running it elsewhere.

use anyhow::{Context, Result};
use clap::Parser;
use phone2act_gateway::GatewayConfig;
use std::net::SocketAddr;
use std::path::PathBuf;

// Command-line switches, each independent.
#[allow(clippy::struct_excessive_bools)]
#[derive(Parser, Debug)]
#[command(
    version,
    about = "WebSocket (rosbridge v2 + phone page) to gRPC gateway for phone2act"
)]
struct Args {
    /// The phone2act gRPC server.
    #[arg(long, env = "PHONE2ACT_SERVER", default_value = "http://127.0.0.1:50051")]
    server: String,
    /// Bearer token of the gRPC server (its `server.token`).
    #[arg(long, env = "PHONE2ACT_TOKEN")]
    grpc_token: Option<String>,
    /// A TOML file with the `[gateway]` table (the same keys as in the server config); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// rosbridge listen address (plain ws).
    #[arg(long)]
    rosbridge_listen: Option<SocketAddr>,
    /// HTTPS listen address (phone page and wss).
    #[arg(long)]
    https_listen: Option<SocketAddr>,
    /// Do not serve rosbridge.
    #[arg(long)]
    no_rosbridge: bool,
    /// Do not serve the HTTPS page.
    #[arg(long)]
    no_https: bool,
    /// Directory for the generated certificate and pairing token.
    #[arg(long)]
    cert_dir: Option<PathBuf>,
    /// Certificate chain (PEM) to use instead of a generated one.
    #[arg(long, requires = "key_file")]
    cert_file: Option<PathBuf>,
    /// Private key (PEM) for --cert-file.
    #[arg(long, requires = "cert_file")]
    key_file: Option<PathBuf>,
    /// Pairing token (default: generated once and kept in the cert dir).
    #[arg(long, env = "PHONE2ACT_PAIRING_TOKEN")]
    token: Option<String>,
    /// Accept phone-page sockets without a token (only on a network you trust).
    #[arg(long)]
    no_token: bool,
    /// Host or address printed in the URL and QR code.
    #[arg(long)]
    public_host: Option<String>,
    /// Arm for topics without a namespace and for the page's first connection.
    #[arg(long)]
    default_arm: Option<String>,
    /// Do not print the QR code.
    #[arg(long)]
    no_qr: bool,
}

fn load(args: &Args) -> Result<GatewayConfig> {
    let mut config = match &args.config {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            // Accept a whole server config too: only its [gateway] table matters here.
            let value: toml::Table =
                toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
            match value.get("gateway") {
                Some(table) => table
                    .clone()
                    .try_into()
                    .with_context(|| format!("{}: [gateway]", path.display()))?,
                None => GatewayConfig::default(),
            }
        }
        None => GatewayConfig::default(),
    };
    if let Some(a) = args.rosbridge_listen {
        config.rosbridge_listen = a;
    }
    if let Some(a) = args.https_listen {
        config.https_listen = a;
    }
    config.rosbridge &= !args.no_rosbridge;
    config.https &= !args.no_https;
    if args.cert_dir.is_some() {
        config.cert_dir.clone_from(&args.cert_dir);
    }
    if args.cert_file.is_some() {
        config.cert_file.clone_from(&args.cert_file);
        config.key_file.clone_from(&args.key_file);
    }
    if args.token.is_some() {
        config.token.clone_from(&args.token);
    }
    if args.no_token {
        config.require_token = false;
    }
    if args.public_host.is_some() {
        config.public_host.clone_from(&args.public_host);
    }
    if let Some(arm) = &args.default_arm {
        config.default_arm.clone_from(arm);
    }
    config.print_qr &= !args.no_qr;
    Ok(config)
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let args = Args::parse();
    let config = load(&args)?;
    if args.grpc_token.is_some()
        && let Some(warning) = config.local_trust_warning()
    {
        tracing::warn!("{warning}");
    }
    // One thread: the gateway is light I/O for a handful of phones, and keeping a message's whole path
    // (socket read → slot → HTTP/2 write) on one thread avoids cross-thread wake-ups, which cost more
    // latency than anything the gateway computes.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        phone2act_gateway::serve(
            config,
            args.server.clone(),
            args.grpc_token.clone(),
            stop_signal(),
        )
        .await
        .context("gateway")
    })
}

/// Ctrl-C or SIGTERM (what `kill` and service managers send).
async fn stop_signal() {
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            () = async { match term.as_mut() { Some(t) => { t.recv().await; } None => std::future::pending().await } } => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

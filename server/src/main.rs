//! `phone2act`: the command-line entry point. `phone2act serve` runs the server (the embedded default when
//! no `--config` is given).

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use phone2act_server::{Config, bind, run};
use std::net::SocketAddr;
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "phone2act",
    version,
    about = "Phone-to-robot teleoperation and LeRobot recording server"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the server.
    Serve {
        /// TOML configuration file; without it the embedded default runs (simulated arm `main`, synthetic
        /// camera, datasets under ./datasets/).
        #[arg(long, env = "PHONE2ACT_CONFIG")]
        config: Option<PathBuf>,
        /// gRPC listen address (overrides `server.listen`).
        #[arg(long)]
        listen: Option<SocketAddr>,
        /// Print the effective configuration and exit.
        #[arg(long)]
        check: bool,
    },
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("PHONE2ACT_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    match real_main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("phone2act: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn real_main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Serve {
            config,
            listen,
            check,
        } => {
            let mut config = match &config {
                Some(path) => Config::load(path)?,
                None => Config::embedded_default()?,
            };
            if let Some(listen) = listen {
                config.server.listen = listen;
            }
            if check {
                println!("{config:#?}");
                return Ok(());
            }
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .thread_name("phone2act-rt")
                .build()
                .context("cannot start the async runtime")?;
            runtime.block_on(async move {
                let listener = bind(config.server.listen).await?;
                eprintln!("phone2act: gRPC on {}", listener.local_addr()?);
                run(config, listener, shutdown_signal()).await?;
                anyhow::Ok(())
            })
        }
    }
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {}
        () = term => {}
    }
    tracing::info!("shutdown requested");
}

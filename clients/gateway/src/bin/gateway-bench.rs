//! Measures the gateway's added latency: WebSocket message sent by a phone → sample received by the gRPC
//! server, for N phones at a fixed rate, over rosbridge (`ws://`) and the page protocol (`wss://`).
//!
//! The server is the in-process mock (a real tonic server on a loopback socket) so that arrival times are
//! read on the same monotonic clock the phones stamp their messages with. A direct gRPC stream (no gateway)
//! is measured the same way as a baseline, so the gateway's own share can be read off. Each gateway path is
//! measured twice: standalone (own thread and runtime, gRPC over loopback TCP, as `phone2act-gateway`) and
//! embedded (on the server's runtime, gRPC in-process through `Client::in_process`, as `phone2act serve`).
//!
//! The paths take turns: each one's time is split into `--rounds` slices, measured one after another path's, so
//! that a stall of a shared machine falls on every path alike instead of on whichever path it happened to meet
//! (on 2 shared cores such stalls decided whether a path's p99 met its target; `--rounds 1` measures each path
//! in one piece).
//!
//! `cargo run --release -p phone2act-gateway --features mock --bin gateway-bench -- --phones 2 --rate-hz 60 --seconds 20`

use anyhow::{Context, Result};
use clap::Parser;
use futures_util::SinkExt;
use phone2act_gateway::mock_server::MockServer;
use phone2act_gateway::{Gateway, GatewayConfig, Listeners};
use phone2act_proto::v1::{PhoneSample, Pose, TrackingState};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;

#[derive(Parser, Debug)]
#[command(about = "Gateway latency: WebSocket message in → sample at the gRPC server")]
struct Args {
    /// Simultaneous phones (each drives its own arm).
    #[arg(long, default_value_t = 2)]
    phones: usize,
    /// Messages per second per phone.
    #[arg(long, default_value_t = 60.0)]
    rate_hz: f64,
    /// Measured duration per path, over all rounds (each slice after a 1 s warm-up).
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Slices per path, the paths taking turns.
    #[arg(long, default_value_t = 5)]
    rounds: usize,
    /// Also print each slice's row (to see which slice a path's tail came from).
    #[arg(long)]
    per_slice: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Path {
    Rosbridge,
    Page,
    DirectGrpc,
}

/// Where the gateway runs and how it reaches the server.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Gw {
    /// The standalone `phone2act-gateway`: its own thread and runtime, gRPC over loopback TCP.
    Standalone,
    /// Embedded as in `phone2act serve`: on the server's runtime, gRPC in-process (no socket).
    Embedded,
}

fn percentile(sorted: &[i64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let idx = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[idx] as f64 / 1000.0
}

/// One table row: count and p50/p90/p99/max of `ns` in microseconds; returns p50 and p99.
fn print_row(name: &str, mut ns: Vec<i64>) -> (f64, f64) {
    ns.sort_unstable();
    println!(
        "{name:<28} {:>7} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
        ns.len(),
        percentile(&ns, 0.50),
        percentile(&ns, 0.90),
        percentile(&ns, 0.99),
        percentile(&ns, 1.0)
    );
    (percentile(&ns, 0.50), percentile(&ns, 0.99))
}

/// The paths measured, in the order they take turns.
const PATHS: [(Path, Gw); 5] = [
    (Path::DirectGrpc, Gw::Standalone),
    (Path::Rosbridge, Gw::Standalone),
    (Path::Page, Gw::Standalone),
    (Path::Rosbridge, Gw::Embedded),
    (Path::Page, Gw::Embedded),
];

fn path_name(path: Path, gw: Gw) -> &'static str {
    match (path, gw) {
        (Path::DirectGrpc, _) => "direct gRPC (no gateway)",
        (Path::Rosbridge, Gw::Standalone) => "rosbridge → gateway → TCP",
        (Path::Page, Gw::Standalone) => "page wss → gateway → TCP",
        (Path::Rosbridge, Gw::Embedded) => "rosbridge → embedded gateway",
        (Path::Page, Gw::Embedded) => "page wss → embedded gateway",
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.rounds > 0, "--rounds must be at least 1");
    println!(
        "gateway-bench: {} phones x {} Hz, {} s per path in {} rounds, release={}, {} CPUs",
        args.phones,
        args.rate_hz,
        args.seconds,
        args.rounds,
        !cfg!(debug_assertions),
        std::thread::available_parallelism().map_or(0, std::num::NonZero::get)
    );
    let slice_s = args.seconds / args.rounds as f64;
    let mut latencies = vec![Vec::new(); PATHS.len()];
    let mut round_trips = vec![Vec::new(); PATHS.len()];
    for _ in 0..args.rounds {
        for (i, (path, gw)) in PATHS.into_iter().enumerate() {
            let (lat, rtt) = run(path, gw, &args, slice_s)?;
            if args.per_slice {
                print_row(path_name(path, gw), lat.clone());
            }
            latencies[i].extend(lat);
            round_trips[i].extend(rtt);
        }
    }
    println!(
        "{:<28} {:>7} {:>9} {:>9} {:>9} {:>9}",
        "path", "samples", "p50 µs", "p90 µs", "p99 µs", "max µs"
    );
    let mut p50_p99 = Vec::new();
    for ((path, gw), lat) in PATHS.into_iter().zip(latencies) {
        p50_p99.push(print_row(path_name(path, gw), lat));
    }
    // What the phone page shows as its latency: sample sent → its feedback back at the phone.
    for ((path, gw), rtt) in PATHS.into_iter().zip(round_trips) {
        let name = match (path, gw) {
            (Path::DirectGrpc, _) => "direct gRPC round trip",
            (Path::Page, Gw::Standalone) => "page round trip, standalone",
            (Path::Page, Gw::Embedded) => "page round trip, embedded",
            (Path::Rosbridge, _) => continue,
        };
        print_row(name, rtt);
    }
    // The embedded gateway's share: its rows against the direct row of the same run.
    let (direct_p50, direct_p99) = p50_p99[0];
    for (i, (path, gw)) in PATHS.into_iter().enumerate() {
        if gw == Gw::Embedded {
            let (p50, p99) = p50_p99[i];
            println!(
                "{:<28} p50 {:+6.0} µs, p99 {:+6.0} µs over direct gRPC (p99 within 100 µs: {})",
                path_name(path, gw),
                p50 - direct_p50,
                p99 - direct_p99,
                if p99 - direct_p99 <= 100.0 { "yes" } else { "no" }
            );
        }
    }
    Ok(())
}

/// Runs `f` on a new thread with its own single-threaded runtime, like a separate process would have (the
/// standalone gateway binary runs on one thread too).
fn on_thread<T: Send + 'static>(
    name: &str,
    f: impl FnOnce() -> std::pin::Pin<Box<dyn std::future::Future<Output = T>>> + Send + 'static,
) -> std::thread::JoinHandle<T> {
    std::thread::Builder::new()
        .name(name.to_owned())
        .spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("runtime");
            rt.block_on(f())
        })
        .expect("thread")
}

/// Binds port-0 listeners, starts the gateway on the current runtime with `client`, reports its info and
/// runs it until `stop`.
async fn gateway_task(
    config: GatewayConfig,
    client: phone2act_sdk::Client,
    info_tx: std::sync::mpsc::Sender<phone2act_gateway::GatewayInfo>,
    stop: tokio::sync::oneshot::Receiver<()>,
) {
    let listeners = Listeners {
        rosbridge: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind")),
        https: Some(tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind")),
    };
    let gateway = Gateway::with_client(config, client, listeners).expect("gateway");
    info_tx.send(gateway.info().clone()).expect("main thread gone");
    let _ = gateway
        .run(async {
            let _ = stop.await;
        })
        .await;
}

/// One slice of `seconds`: the mock server, the gateway (standalone: on its own thread and runtime; embedded: on
/// the server's) and the phones each on their own thread and runtime. Returns the one-way latencies (phone send →
/// sample at the server) and, for the page, the round trips (phone send → feedback for that sample back at
/// the phone), both after a 1 s warm-up.
fn run(path: Path, gw: Gw, args: &Args, seconds: f64) -> Result<(Vec<i64>, Vec<i64>)> {
    let epoch = Instant::now();
    let arms: Vec<String> = (0..args.phones).map(|i| format!("arm{i}")).collect();
    let dir = std::env::temp_dir().join(format!("phone2act-gateway-bench-{}", std::process::id()));
    let mut config = GatewayConfig {
        cert_dir: Some(dir.clone()),
        print_qr: false,
        public_host: Some("127.0.0.1".into()),
        ..GatewayConfig::default()
    };
    config.topics.namespaces = arms.iter().map(|a| (a.clone(), a.clone())).collect();
    let (info_tx, info_rx) = std::sync::mpsc::channel();
    let (gw_stop_tx, gw_stop_rx) = tokio::sync::oneshot::channel::<()>();

    // "Server process" (with the gateway when it is embedded).
    let (mock_tx, mock_rx) = std::sync::mpsc::channel();
    let (server_stop_tx, server_stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server_arms = arms.clone();
    let embedded = (gw == Gw::Embedded).then(|| (config.clone(), info_tx.clone()));
    let (embedded_stop, standalone_stop) = match gw {
        Gw::Embedded => (Some(gw_stop_rx), None),
        Gw::Standalone => (None, Some(gw_stop_rx)),
    };
    let server = on_thread("server", move || {
        Box::pin(async move {
            let refs: Vec<&str> = server_arms.iter().map(String::as_str).collect();
            let mock = MockServer::start(&refs, epoch, true).await.expect("mock server");
            if let (Some((config, info_tx)), Some(stop)) = (embedded, embedded_stop) {
                let (client, incoming) = phone2act_sdk::Client::in_process(None).expect("client");
                mock.serve_in_process(incoming);
                tokio::spawn(gateway_task(config, client, info_tx, stop));
            }
            mock_tx.send(mock).expect("main thread gone");
            let _ = server_stop_rx.await;
        })
    });
    let mock = mock_rx.recv()?;

    // "Gateway process".
    let gateway = match standalone_stop {
        Some(stop) => {
            let url = mock.url();
            Some(on_thread("gateway", move || {
                Box::pin(async move {
                    // Inside the runtime: the lazy channel spawns its connection task there.
                    let options = phone2act_sdk::ConnectOptions::default();
                    let client = phone2act_sdk::Client::connect_lazy(&url, &options).expect("server URL");
                    gateway_task(config, client, info_tx, stop).await;
                })
            }))
        }
        None => None,
    };
    let info = info_rx.recv()?;

    // "Phones".
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let total = Duration::from_secs_f64(seconds + 1.0);
    let url = mock.url();
    let phone_arms = arms.clone();
    let phones = on_thread("phones", move || {
        Box::pin(async move {
            let mut phones = tokio::task::JoinSet::new();
            let mut round_trips = Vec::new();
            for (i, arm) in phone_arms.into_iter().enumerate() {
                let info = info.clone();
                let url = url.clone();
                phones.spawn(async move {
                    // Stagger phones so they do not always send in the same instant.
                    tokio::time::sleep(period.mul_f64(i as f64 / 2.0)).await;
                    match path {
                        Path::Rosbridge => rosbridge_phone(&info, &arm, epoch, period, total)
                            .await
                            .map(|()| Vec::new()),
                        Path::Page => page_phone(&info, &arm, epoch, period, total).await,
                        Path::DirectGrpc => grpc_phone(&url, &arm, epoch, period, total).await,
                    }
                });
            }
            while let Some(done) = phones.join_next().await {
                round_trips.extend(done??);
            }
            anyhow::Ok(round_trips)
        })
    });
    let round_trips = phones
        .join()
        .map_err(|_| anyhow::anyhow!("phones thread panicked"))??;
    std::thread::sleep(Duration::from_millis(100));
    let _ = gw_stop_tx.send(());
    if let Some(gateway) = gateway {
        let _ = gateway.join();
    }
    let warmup_ns = 1_000_000_000_i64;
    let latencies = mock
        .received()
        .iter()
        .filter(|r| r.sample.tracking_from_phone.is_some() && r.sample.capture_time_ns > warmup_ns)
        .map(|r| r.arrival_ns - r.sample.capture_time_ns)
        .collect();
    drop(mock);
    let _ = server_stop_tx.send(());
    let _ = server.join();
    let _ = std::fs::remove_dir_all(dir);
    Ok((latencies, round_trips))
}

/// A phone's frame clock: after a stall it carries on from now instead of bursting to catch up, as an XR
/// frame loop does.
fn phone_clock(period: Duration) -> tokio::time::Interval {
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tick
}

fn pose_json(topic: &str, stamp_ns: i64, x: f64) -> String {
    format!(
        r#"{{"op":"publish","topic":"{topic}","type":"geometry_msgs/PoseStamped","msg":{{"header":{{"stamp":{{"sec":{},"nanosec":{}}},"frame_id":"phone_ar_frame"}},"pose":{{"position":{{"x":{x},"y":1.2,"z":-0.3}},"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}}}}}}}}"#,
        stamp_ns / 1_000_000_000,
        stamp_ns % 1_000_000_000
    )
}

async fn rosbridge_phone(
    info: &phone2act_gateway::GatewayInfo,
    arm: &str,
    epoch: Instant,
    period: Duration,
    total: Duration,
) -> Result<()> {
    let addr = info.rosbridge_addr.context("no rosbridge listener")?;
    let tcp = TcpStream::connect(addr).await?;
    tcp.set_nodelay(true)?;
    let (mut ws, _) = tokio_tungstenite::client_async(format!("ws://{addr}/"), tcp).await?;
    let topic = format!("/{arm}/Phone2Act/ar_pose");
    ws.send(Message::Text(
        format!(r#"{{"op":"advertise","topic":"{topic}","type":"geometry_msgs/PoseStamped"}}"#).into(),
    ))
    .await?;
    let mut tick = phone_clock(period);
    let end = Instant::now() + total;
    let mut n = 0u64;
    while Instant::now() < end {
        tick.tick().await;
        n += 1;
        let x = (n as f64 * 0.01).sin() * 0.05;
        let text = pose_json(&topic, epoch.elapsed().as_nanos() as i64, x);
        ws.send(Message::Text(text.into())).await?;
    }
    Ok(())
}

async fn page_phone(
    info: &phone2act_gateway::GatewayInfo,
    arm: &str,
    epoch: Instant,
    period: Duration,
    total: Duration,
) -> Result<Vec<i64>> {
    use futures_util::StreamExt;
    use rustls::pki_types::pem::PemObject;
    let addr = info.https_addr.context("no https listener")?;
    let pem = std::fs::read(info.cert_path.as_ref().context("no cert")?)?;
    let mut roots = rustls::RootCertStore::empty();
    for cert in rustls::pki_types::CertificateDer::pem_slice_iter(&pem) {
        roots.add(cert?)?;
    }
    let config =
        rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots)
            .with_no_client_auth();
    let tcp = TcpStream::connect(addr).await?;
    tcp.set_nodelay(true)?;
    let tls = tokio_rustls::TlsConnector::from(Arc::new(config))
        .connect("localhost".try_into()?, tcp)
        .await?;
    let token = info.token.clone().unwrap_or_default();
    let (ws, _) =
        tokio_tungstenite::client_async(format!("wss://localhost:{}/ws?token={token}", addr.port()), tls)
            .await?;
    let (mut tx, mut rx) = ws.split();
    // Feedback flows back like on a phone: each one echoes the sample's t_ns, which gives the round trip the
    // page displays. Reading it also keeps the socket from backing up.
    let (rtt_tx, rtt_rx) = tokio::sync::oneshot::channel();
    let reader = tokio::spawn(async move {
        let mut round_trips = Vec::new();
        let deadline = tokio::time::Instant::now() + total + Duration::from_millis(200);
        while let Ok(Some(Ok(msg))) = tokio::time::timeout_at(deadline, rx.next()).await {
            let now_ns = epoch.elapsed().as_nanos() as i64;
            let Message::Text(text) = msg else { continue };
            let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) else {
                continue;
            };
            if let Some(t_ns) = v.get("t_ns").and_then(serde_json::Value::as_i64)
                && t_ns > 1_000_000_000
            {
                round_trips.push(now_ns - t_ns);
            }
        }
        let _ = rtt_tx.send(round_trips);
    });
    tx.send(Message::Text(
        format!(r#"{{"type":"hello","arm":"{arm}"}}"#).into(),
    ))
    .await?;
    let mut tick = phone_clock(period);
    let end = Instant::now() + total;
    let mut seq = 0u64;
    while Instant::now() < end {
        tick.tick().await;
        seq += 1;
        let x = (seq as f64 * 0.01).sin() * 0.05;
        let t_ns = epoch.elapsed().as_nanos() as i64;
        let text = format!(
            r#"{{"type":"sample","seq":{seq},"t_ns":{t_ns},"tracking":"tracking","pose":{{"p":[{x},1.2,-0.3],"q":[0,0,0,1]}}}}"#
        );
        tx.send(Message::Text(text.into())).await?;
    }
    let round_trips = rtt_rx.await.unwrap_or_default();
    reader.abort();
    Ok(round_trips)
}

async fn grpc_phone(
    url: &str,
    arm: &str,
    epoch: Instant,
    period: Duration,
    total: Duration,
) -> Result<Vec<i64>> {
    let channel = tonic::transport::Endpoint::from_shared(url.to_owned())?
        .tcp_nodelay(true)
        .connect()
        .await?;
    let mut client = phone2act_proto::v1::teleop_client::TeleopClient::new(channel);
    let (tx, rx) = tokio::sync::mpsc::channel::<PhoneSample>(4);
    let arm = arm.to_owned();
    tx.send(PhoneSample {
        arm: arm.clone(),
        ..PhoneSample::default()
    })
    .await?;
    let response = client
        .stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?;
    let mut inbound = response.into_inner();
    let reader = tokio::spawn(async move {
        let mut round_trips = Vec::new();
        while let Ok(Some(fb)) = inbound.message().await {
            if fb.echoed_capture_time_ns > 1_000_000_000 {
                round_trips.push(epoch.elapsed().as_nanos() as i64 - fb.echoed_capture_time_ns);
            }
        }
        round_trips
    });
    let mut tick = phone_clock(period);
    let end = Instant::now() + total;
    let mut seq = 0u64;
    while Instant::now() < end {
        tick.tick().await;
        seq += 1;
        let x = (seq as f64 * 0.01).sin() * 0.05;
        tx.send(PhoneSample {
            seq,
            arm: arm.clone(),
            capture_time_ns: epoch.elapsed().as_nanos() as i64,
            tracking_from_phone: Some(Pose::from_parts([x, 1.2, -0.3], [0.0, 0.0, 0.0, 1.0])),
            tracking: TrackingState::Tracking.into(),
            ..PhoneSample::default()
        })
        .await?;
    }
    drop(tx);
    // The stream ends once the server has answered the last sample.
    let round_trips = tokio::time::timeout(Duration::from_secs(2), reader)
        .await
        .map_or_else(|_| Vec::new(), Result::unwrap_or_default);
    Ok(round_trips)
}

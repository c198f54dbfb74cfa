//! Helpers for phone2act's end-to-end tests: start a real server in-process on an ephemeral port and
//! connect the real SDK to it; and the scripted operator ([`operator`]), a phone client that records
//! pick-and-place demonstrations.

pub mod bridge;
pub mod operator;
pub mod s3;

use phone2act_sdk::Client;
use phone2act_server::Config;
use std::net::SocketAddr;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// A policy session's hello as most tests open one: `arms`, 20 Hz observations without images, control
/// requested, named `name`, losing the arm after `silence_timeout_s` without a chunk (0: the server's default).
pub fn policy_hello(arms: &[&str], name: &str, silence_timeout_s: f64) -> phone2act_proto::v1::PolicyHello {
    phone2act_proto::v1::PolicyHello {
        arms: arms.iter().map(|&a| a.to_owned()).collect(),
        observation_rate_hz: 20.0,
        image_encoding: phone2act_proto::v1::ImageEncoding::None as i32,
        request_control: true,
        policy_name: name.to_owned(),
        silence_timeout_s,
        ..phone2act_proto::v1::PolicyHello::default()
    }
}

/// The embedded default configuration with its dataset under `dataset_root`, its camera shrunk to
/// 320x240 at 15 fps so that a dozen servers in unoptimised test builds fit on two cores.
pub fn default_config(dataset_root: &std::path::Path) -> Config {
    let mut config = embedded_default(dataset_root);
    for cam in &mut config.cameras {
        (cam.width, cam.height, cam.fps) = (320, 240, 15.0);
    }
    config
}

/// The embedded default configuration exactly as shipped, with its dataset under `dataset_root`.
pub fn embedded_default(dataset_root: &std::path::Path) -> Config {
    let mut config =
        Config::from_toml_str(phone2act_server::config::EMBEDDED_DEFAULT, "embedded", Vec::new())
            .expect("embedded default parses");
    dataset_root.clone_into(&mut config.recorder.root);
    config
}

/// The shipped bimanual configuration (two simulated arms `left` and `right`).
pub fn bimanual_config(dataset_root: &std::path::Path) -> Config {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../server/config/bimanual-sim.toml");
    let mut config = Config::from_toml_str(
        &std::fs::read_to_string(path).expect("bimanual config"),
        path,
        Vec::new(),
    )
    .expect("bimanual config parses");
    dataset_root.clone_into(&mut config.recorder.root);
    config
}

/// One remote-bridge arm `ext` (joints `a b c`) and one pushed 64x64 camera `pushed`, with its dataset under
/// `dataset_root`: what a client of `Bridge.Attach` and `Cameras.Push` talks to.
pub fn remote_config(dataset_root: &std::path::Path) -> Config {
    const REMOTE: &str = r#"
[[arms]]
name = "ext"
bridge = "remote"
[arms.remote]
joint_names = ["a", "b", "c"]

[[cameras]]
name = "pushed"
kind = "remote"
width = 64
height = 64
fps = 30
"#;
    let mut config =
        Config::from_toml_str(REMOTE, "remote_config", Vec::new()).expect("remote config parses");
    dataset_root.clone_into(&mut config.recorder.root);
    config
}

/// Position of a pose message as an array (metres).
pub fn pos(pose: &phone2act_proto::v1::Pose) -> [f64; 3] {
    let p = pose.position_m.as_ref().expect("pose has a position");
    [p.x, p.y, p.z]
}

/// The measured end-effector position of `arm`, through System.ListArms.
pub async fn sim_pose_of(client: &Client, arm: &str) -> [f64; 3] {
    let arms = client.system().list_arms().await.expect("ListArms");
    let state = arms.iter().find(|a| a.arm == arm).expect("arm listed");
    pos(state.robot_from_ee.as_ref().expect("arm has feedback"))
}

/// `arm`'s state, through System.ListArms.
pub async fn arm_state(client: &Client, arm: &str) -> phone2act_proto::v1::ArmState {
    client
        .system()
        .list_arms()
        .await
        .expect("ListArms")
        .into_iter()
        .find(|a| a.arm == arm)
        .expect("arm listed")
}

/// Polls `check` every 20 ms until it holds or `timeout` passes; true if it held. Tests wait for an outcome
/// rather than sleeping a guessed time, so a stalled 2-core machine only makes them slower.
pub async fn wait_until<F, Fut>(timeout: std::time::Duration, mut check: F) -> bool
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = tokio::time::Instant::now() + timeout;
    while tokio::time::Instant::now() < deadline {
        if check().await {
            return true;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    false
}

/// The parquet files under `dir`, recursively, sorted.
pub fn data_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            out.extend(data_files(&e.path()));
        } else if e.path().extension().is_some_and(|x| x == "parquet") {
            out.push(e.path());
        }
    }
    out.sort();
    out
}

/// Copies a dataset a test produced to `$PHONE2ACT_CONFORMANCE_DIR/<name>` so the conformance suite loads
/// it with the real lerobot library. Does nothing when the variable is unset.
pub fn keep_for_conformance(name: &str, dataset: &std::path::Path) {
    let Some(root) = std::env::var_os("PHONE2ACT_CONFORMANCE_DIR") else {
        return;
    };
    let dest = std::path::Path::new(&root).join(name);
    let _ = std::fs::remove_dir_all(&dest);
    copy_dir(dataset, &dest).expect("copy dataset for conformance");
}

/// [`keep_for_conformance`] with what the producing test expects the conformance check to find
/// (`phone2act_expect.json`, see tests/conformance/check.py).
pub fn keep_for_conformance_expecting(name: &str, dataset: &std::path::Path, expect: &serde_json::Value) {
    keep_for_conformance(name, dataset);
    if let Some(root) = std::env::var_os("PHONE2ACT_CONFORMANCE_DIR") {
        let path = std::path::Path::new(&root)
            .join(name)
            .join("phone2act_expect.json");
        std::fs::write(path, expect.to_string()).expect("write phone2act_expect.json");
    }
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            std::fs::copy(entry.path(), target)?;
        }
    }
    Ok(())
}

/// A server running in-process on 127.0.0.1 with an ephemeral port.
pub struct TestServer {
    pub addr: SocketAddr,
    /// An in-process connection to the server, as `phone2act serve` gives its embedded gateway.
    in_process: Client,
    stop: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), phone2act_server::ServerError>>>,
}

impl TestServer {
    /// Starts `config` (its listen address is ignored).
    pub async fn start(config: Config) -> anyhow::Result<Self> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let (stop, stopped) = oneshot::channel::<()>();
        // Start the app here, not inside the spawned server, so a bad config fails the test with its message.
        let app = std::sync::Arc::new(phone2act_server::app::App::start(config)?);
        let (in_process, local) = Client::in_process(None)?;
        let task = tokio::spawn(phone2act_server::serve_app_with_local(
            app,
            listener,
            Some(Box::new(move |routes, stopped| local.serve(routes, stopped))),
            async {
                let _ = stopped.await;
            },
        ));
        Ok(Self {
            addr,
            in_process,
            stop: Some(stop),
            task: Some(task),
        })
    }

    /// Starts the embedded default configuration with the dataset under `dataset_root`.
    pub async fn start_default(dataset_root: &std::path::Path) -> anyhow::Result<Self> {
        Self::start(embedded_default(dataset_root)).await
    }

    /// The gRPC URL.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// A connected SDK client.
    pub async fn client(&self) -> anyhow::Result<Client> {
        Ok(Client::connect(&self.url(), None).await?)
    }

    /// An in-process client (no socket) sending `token`: what the embedded gateway uses.
    pub fn in_process_client(&self, token: Option<&str>) -> Client {
        self.in_process
            .with_token(token)
            .expect("token is a valid header value")
    }

    /// Requests shutdown and waits for the server to return.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(task) = self.task.take() {
            task.await??;
        }
        Ok(())
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

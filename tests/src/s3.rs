//! A real S3 server on loopback for the storage tests: moto's `moto_server` (PyPI `moto[server]`), found
//! through `PHONE2ACT_MOTO_SERVER` (tests/scripts/s3-server.sh provides it). Authentication is enforced
//! (after the three unauthenticated IAM calls that create the station's user, key and policy), so wrong
//! credentials are refused as by AWS. Every request moto serves is one line of its log, which is how the
//! tests count PUTs. Also included by path from server/cli/tests, which may not depend on this crate.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// `moto_server`, or `None` (after saying so loudly: the test is skipped, not passed silently).
pub fn moto_server_path(test: &str) -> Option<PathBuf> {
    match std::env::var_os("PHONE2ACT_MOTO_SERVER").map(PathBuf::from) {
        Some(p) if p.exists() => Some(p),
        _ => {
            eprintln!(
                "SKIPPED {test}: no S3 server (set PHONE2ACT_MOTO_SERVER, e.g. \
                 PHONE2ACT_MOTO_SERVER=$(tests/scripts/s3-server.sh))"
            );
            None
        }
    }
}

/// A running moto server.
pub struct Moto {
    bin: PathBuf,
    child: Option<Child>,
    pub port: u16,
    log: PathBuf,
    /// The station's key pair (created in moto's IAM).
    pub key_id: String,
    pub secret: String,
    auth: bool,
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

impl Moto {
    /// Starts moto on a free port, logging into `dir`. With `auth`, requests must be signed with the
    /// station's key, created here in moto's IAM; without, any key is accepted (and a restarted server,
    /// which forgets its IAM users, still accepts the station).
    pub fn start(bin: &Path, dir: &Path, auth: bool) -> Moto {
        let mut m = Moto {
            bin: bin.to_owned(),
            child: None,
            port: free_port(),
            log: dir.join("moto.log"),
            key_id: "station-key".into(),
            secret: "station-secret".into(),
            auth,
        };
        m.spawn();
        if !auth {
            return m;
        }
        let out = m.python(
            r#"
import boto3, json, sys
kw = dict(endpoint_url=sys.argv[1], region_name="us-east-1", aws_access_key_id="x", aws_secret_access_key="y")
iam = boto3.client("iam", **kw)
iam.create_user(UserName="station")
k = iam.create_access_key(UserName="station")["AccessKey"]
iam.put_user_policy(UserName="station", PolicyName="s3", PolicyDocument=json.dumps(
    {"Version": "2012-10-17", "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}]}))
print(k["AccessKeyId"], k["SecretAccessKey"])
"#,
            &[],
        );
        let mut it = out.split_whitespace();
        it.next().expect("key id").clone_into(&mut m.key_id);
        it.next().expect("secret").clone_into(&mut m.secret);
        m
    }

    fn spawn(&mut self) {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .expect("moto log");
        let mut cmd = Command::new(&self.bin);
        if self.auth {
            cmd.env("INITIAL_NO_AUTH_ACTION_COUNT", "3");
        }
        let child = cmd
            .args(["-H", "127.0.0.1", "-p", &self.port.to_string()])
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .expect("moto_server starts");
        self.child = Some(child);
        // Up when it answers HTTP; moto starts in about a second, far longer on a loaded machine.
        let deadline = Instant::now() + Duration::from_mins(1);
        while Instant::now() < deadline {
            if let Ok(mut s) = TcpStream::connect(("127.0.0.1", self.port)) {
                let _ = write!(s, "GET /moto-api/ HTTP/1.0\r\n\r\n");
                let mut b = [0u8; 12];
                if s.read(&mut b).is_ok_and(|n| n > 0) {
                    return;
                }
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!("moto_server did not answer on port {} within 60 s", self.port);
    }

    /// `http://127.0.0.1:PORT`
    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// Runs a Python script with moto's interpreter (boto3 is there); argv[1] is the endpoint.
    pub fn python(&self, script: &str, args: &[&str]) -> String {
        let py = self.bin.with_file_name("python");
        let out = Command::new(py)
            .arg("-c")
            .arg(script)
            .arg(self.endpoint())
            .args(args)
            .env("AWS_ACCESS_KEY_ID", &self.key_id)
            .env("AWS_SECRET_ACCESS_KEY", &self.secret)
            .output()
            .expect("python runs");
        assert!(
            out.status.success(),
            "python failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    pub fn create_bucket(&self, bucket: &str) {
        self.python(
            r#"
import boto3, os, sys
boto3.client("s3", endpoint_url=sys.argv[1], region_name="us-east-1").create_bucket(Bucket=sys.argv[2])
"#,
            &[bucket],
        );
    }

    /// Object keys under `prefix` with their sizes.
    pub fn list(&self, bucket: &str, prefix: &str) -> Vec<(String, u64)> {
        let out = self.python(
            r#"
import boto3, sys
s3 = boto3.client("s3", endpoint_url=sys.argv[1], region_name="us-east-1")
for page in s3.get_paginator("list_objects_v2").paginate(Bucket=sys.argv[2], Prefix=sys.argv[3]):
    for o in page.get("Contents", []):
        print(o["Key"], o["Size"])
"#,
            &[bucket, prefix],
        );
        out.lines()
            .filter_map(|l| l.rsplit_once(' '))
            .map(|(k, s)| (k.to_owned(), s.parse().unwrap_or(0)))
            .collect()
    }

    /// Object PUTs moto has served (parts of multipart uploads included), from its request log.
    pub fn object_puts(&self) -> usize {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| l.split_once("\"PUT ").map(|(_, r)| r))
            .filter_map(|r| r.split_whitespace().next())
            .filter(|path| {
                let path = path.split('?').next().unwrap_or_default();
                path.trim_matches('/').contains('/')
            })
            .count()
    }

    /// A credentials file holding the station's key (or `secret` instead of the real one).
    pub fn credentials_file(&self, dir: &Path, secret: Option<&str>) -> PathBuf {
        let path = dir.join(format!("credentials-{}", secret.unwrap_or("ok")));
        std::fs::write(
            &path,
            format!(
                "[default]\naws_access_key_id = {}\naws_secret_access_key = {}\n",
                self.key_id,
                secret.unwrap_or(&self.secret)
            ),
        )
        .expect("credentials file");
        path
    }

    /// Kills the server (its in-memory state goes with it: moto keeps nothing).
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Starts it again on the same port, empty.
    pub fn restart(&mut self) {
        self.kill();
        self.spawn();
    }
}

impl Drop for Moto {
    fn drop(&mut self) {
        self.kill();
    }
}

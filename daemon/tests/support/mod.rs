//! Shared by the end-to-end tests: `relightd` as a child process on a configuration of the
//! test's own, killed when dropped.

use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub struct Daemon {
    pub child: Child,
    pub socket: PathBuf,
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Write `config` to `dir/relightd.toml`, start relightd on it with `RELIGHT_LOG = log` and
/// `env`, and wait until it serves its control socket at `socket` (the config's
/// `daemon.socket`).
pub fn start(dir: &Path, config: &str, socket: PathBuf, log: &str, env: &[(&str, &str)]) -> Daemon {
    let path = dir.join("relightd.toml");
    std::fs::write(&path, config).expect("config written");
    let child = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .arg("--config")
        .arg(&path)
        .env("RELIGHT_LOG", log)
        .envs(env.iter().copied())
        .stdout(Stdio::null())
        .spawn()
        .expect("relightd starts");
    let mut daemon = Daemon { child, socket };
    let deadline = Instant::now() + Duration::from_secs(30);
    while UnixStream::connect(&daemon.socket).is_err() {
        if let Some(status) = daemon.child.try_wait().unwrap() {
            panic!("relightd exited with {status} before serving its socket");
        }
        assert!(Instant::now() < deadline, "control socket never appeared");
        std::thread::sleep(Duration::from_millis(50));
    }
    daemon
}

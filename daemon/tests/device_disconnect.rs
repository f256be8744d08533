//! Pulled cables, end to end: `relightd` runs a hardware backend through that backend's own
//! replay or dummy path (a pseudo-terminal for the lamp, fakenect for the Kinect, a fake vendor
//! library for the uEye camera, OpenNI2's file driver), the device goes away mid-stream, and the
//! daemon must report it `lost` on the control socket, keep answering requests, and resume when
//! the device comes back.

#![cfg(any(
    feature = "lamp",
    feature = "freenect",
    feature = "ueye",
    feature = "openni2"
))]

mod support;

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use support::Daemon;

/// Start relightd on `sections` (device sections, `[rig]`, `[sync]`) with `env` set.
fn start(dir: &Path, sections: &str, env: &[(&str, &str)]) -> Daemon {
    let socket = dir.join("control.sock");
    let config = format!(
        "[daemon]\nsocket = \"{}\"\nwatchdog = false\n\n[engine]\nname = \"passthrough\"\n\n\
         [recorder]\ndir = \"{dir}/recordings\"\n\n[snapshot]\ndir = \"{dir}/snapshots\"\n\n{sections}",
        socket.display(),
        dir = dir.display(),
    );
    support::start(dir, &config, socket, "error", env)
}

fn status(socket: &Path) -> Value {
    let mut stream = UnixStream::connect(socket).expect("control socket answers");
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let request = json!({"jsonrpc": "2.0", "id": 1, "method": "status"});
    writeln!(stream, "{request}").unwrap();
    let mut line = String::new();
    BufReader::new(stream).read_line(&mut line).unwrap();
    let response: Value = serde_json::from_str(&line).unwrap();
    response["result"].clone()
}

/// The status of the device named `name`.
fn device(status: &Value, name: &str) -> Value {
    status["devices"]
        .as_array()
        .and_then(|devices| devices.iter().find(|d| d["name"] == name))
        .cloned()
        .unwrap_or_else(|| panic!("no device {name} in {status}"))
}

/// Poll the daemon's status until `ok` holds for device `name`; returns that device's status.
fn wait_for(daemon: &Daemon, name: &str, what: &str, ok: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let dev = device(&status(&daemon.socket), name);
        if ok(&dev) {
            return dev;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {name} to be {what}: {dev}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The pulled-cable cycle every backend must survive: running with frames → `lost` while the
/// control socket keeps answering → running again with more frames after `restore`.
fn unplug_and_replug(
    daemon: &Daemon,
    name: &str,
    unplug: impl FnOnce(),
    restore: impl FnOnce(),
) -> (u64, u64) {
    let before = wait_for(daemon, name, "running with frames", |d| {
        d["state"] == "running" && d["frames"].as_u64() > Some(3)
    });
    unplug();
    let lost = wait_for(daemon, name, "lost", |d| d["state"] == "lost");
    assert!(
        lost["last_error"].as_str().is_some_and(|e| !e.is_empty()),
        "{lost}"
    );
    // Still serving: several requests while the device is gone.
    for _ in 0..3 {
        assert_eq!(device(&status(&daemon.socket), name)["state"], "lost");
    }
    let frames_lost = lost["frames"].as_u64().unwrap();
    restore();
    let after = wait_for(daemon, name, "running again with new frames", |d| {
        d["state"] != "lost" && d["frames"].as_u64() > Some(frames_lost + 2)
    });
    (
        before["frames"].as_u64().unwrap(),
        after["frames"].as_u64().unwrap(),
    )
}

#[cfg(feature = "lamp")]
mod lamp {
    use super::*;
    use relight_backends::lamp_protocol::LampReport;
    use std::fs::File;
    use std::os::unix::ffi::OsStringExt;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    /// A pty pair whose master plays the lamp's firmware until dropped (the cable pulled).
    struct Lamp {
        stop: Arc<AtomicBool>,
        thread: Option<std::thread::JoinHandle<()>>,
        slave: PathBuf,
    }

    impl Lamp {
        fn plug(first_seq: u32) -> Self {
            use rustix::pty::{OpenptFlags, grantpt, openpt, ptsname, unlockpt};
            let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY | OpenptFlags::CLOEXEC)
                .expect("openpt");
            grantpt(&master).unwrap();
            unlockpt(&master).unwrap();
            let name = ptsname(&master, Vec::new()).unwrap();
            let mut termios = rustix::termios::tcgetattr(&master).unwrap();
            termios.make_raw();
            rustix::termios::tcsetattr(&master, rustix::termios::OptionalActions::Now, &termios)
                .unwrap();
            let mut master = File::from(master);
            let stop = Arc::new(AtomicBool::new(false));
            let thread = {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut seq = first_seq;
                    while !stop.load(Ordering::Acquire) {
                        let line = LampReport {
                            seq,
                            on: true,
                            level: 0.5,
                            cct_k: 3000,
                            orientation: None,
                        }
                        .to_line();
                        // A full pty buffer (nobody reading while the daemon reconnects) or a
                        // closed slave is not this firmware's problem.
                        let _ = master.write_all(line.as_bytes());
                        seq = seq.wrapping_add(1);
                        std::thread::sleep(Duration::from_millis(20));
                    }
                })
            };
            Self {
                stop,
                thread: Some(thread),
                slave: PathBuf::from(std::ffi::OsString::from_vec(name.into_bytes())),
            }
        }
    }

    impl Drop for Lamp {
        fn drop(&mut self) {
            self.stop.store(true, Ordering::Release);
            if let Some(thread) = self.thread.take() {
                thread.join().unwrap();
            }
        }
    }

    #[test]
    fn a_pulled_lamp_is_lost_and_a_replugged_one_resumes() {
        let dir = tempfile::tempdir().unwrap();
        let rig = relight_core::rig::RigCalibration::default();
        std::fs::write(dir.path().join("rig.toml"), rig.to_toml().unwrap()).unwrap();
        // The stable name udev gives a USB-serial adapter (/dev/serial/by-id/...), re-pointed
        // at each plug's new pty; removed on unplug as udev does.
        let link = dir.path().join("lamp-by-id");
        let lamp = Lamp::plug(0);
        std::os::unix::fs::symlink(&lamp.slave, &link).unwrap();
        let daemon = start(
            dir.path(),
            &format!(
                "[rig]\ncalibration = \"rig.toml\"\n\n[sync]\nstreams = [\"lamp\"]\nreference = \"lamp\"\n\n\
                 [lamp]\nbackend = \"lamp_serial\"\nport = \"{}\"\nmax_intensity_w_sr = 2.0\n\
                 marker_id = 7\nfallback_position = [0.0, 0.5, 0.0]\n",
                link.display()
            ),
            &[],
        );
        let lamp = std::cell::RefCell::new(Some(lamp));
        let (before, after) = unplug_and_replug(
            &daemon,
            "lamp",
            || {
                std::fs::remove_file(&link).unwrap();
                drop(lamp.borrow_mut().take());
            },
            || {
                let replugged = Lamp::plug(1000);
                std::os::unix::fs::symlink(&replugged.slave, &link).unwrap();
                *lamp.borrow_mut() = Some(replugged);
            },
        );
        assert!(after > before);
        let dev = device(&status(&daemon.socket), "lamp");
        assert_eq!(dev["backend"], "lamp");
        drop(daemon);
        drop(lamp);
    }
}

#[cfg(feature = "ueye")]
mod ueye {
    use super::*;

    #[test]
    fn an_unplugged_ueye_probe_is_lost_and_resumes_when_plugged_back() {
        let dir = tempfile::tempdir().unwrap();
        let library = dir.path().join("libueye_api.so");
        let source = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../backends/tests/fixtures/ueye/fake_ueye.c");
        let compiler = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        let built = Command::new(compiler)
            .args(["-shared", "-fPIC", "-O2", "-o"])
            .arg(&library)
            .arg(&source)
            .arg("-lpthread")
            .status()
            .expect("run the C compiler");
        assert!(built.success(), "compiling {}", source.display());
        let plug = dir.path().join("plugged");
        std::fs::write(&plug, "").unwrap();
        let daemon = start(
            dir.path(),
            &format!(
                "[sync]\nstreams = [\"probe\"]\nreference = \"probe\"\n\n\
                 [probe]\nbackend = \"ueye\"\nlibrary = \"{}\"\nbracket_us = [1000, 4000]\n",
                library.display()
            ),
            &[("FAKE_UEYE_PLUG_FILE", plug.to_str().unwrap())],
        );
        let (before, after) = unplug_and_replug(
            &daemon,
            "probe",
            || std::fs::remove_file(&plug).unwrap(),
            || std::fs::write(&plug, "").unwrap(),
        );
        assert!(after > before);
        assert_eq!(device(&status(&daemon.socket), "probe")["backend"], "ueye");
    }
}

#[cfg(feature = "freenect")]
mod freenect {
    use super::*;
    use relight_core::scene::Scene;
    use relight_sim::fakenect::write_fakenect_dump;
    use relight_sim::rig::{SimRig, SimSettings};

    /// fakenect ships a `libfreenect.so.0.5` in its own directory; on LD_LIBRARY_PATH it
    /// replaces the real library in the relightd child.
    fn fakenect_dir() -> Option<PathBuf> {
        [
            "/usr/lib/x86_64-linux-gnu/fakenect",
            "/usr/lib/aarch64-linux-gnu/fakenect",
        ]
        .into_iter()
        .map(PathBuf::from)
        .find(|dir| dir.join("libfreenect.so.0.5").exists())
    }

    #[test]
    fn a_kinect_whose_stream_breaks_is_lost_and_resumes_when_it_is_back() {
        let fakenect = fakenect_dir().expect("Debian's libfreenect0.5 ships fakenect");
        let dir = tempfile::tempdir().unwrap();
        let dump = dir.path().join("dump");
        let scene =
            Scene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box"))
                .unwrap();
        let rig = SimRig::new(
            &scene,
            SimSettings {
                width: 80,
                height: 60,
                frames: 90,
                color_spp: 1,
                truth_every: 0,
                ..SimSettings::default()
            },
        )
        .unwrap();
        let summary = write_fakenect_dump(&dump, &rig).unwrap();
        // The depth frame a third of the way in goes missing (a broken transfer stream) and
        // comes back later: fakenect cannot read on, so the device is lost until then.
        let missing = summary
            .entries
            .iter()
            .filter(|e| e.starts_with("d-"))
            .nth(30)
            .expect("a depth frame 30")
            .clone();
        let aside = dir.path().join("aside.pgm");
        let daemon = start(
            dir.path(),
            "[sync]\nstreams = [\"depth\", \"color\"]\n\n\
             [depth]\nbackend = \"freenect\"\n\n[color]\nbackend = \"freenect\"\n",
            &[
                ("LD_LIBRARY_PATH", fakenect.to_str().unwrap()),
                ("FAKENECT_PATH", dump.to_str().unwrap()),
            ],
        );
        let (before, after) = unplug_and_replug(
            &daemon,
            "depth+color",
            || std::fs::rename(dump.join(&missing), &aside).unwrap(),
            || std::fs::rename(&aside, dump.join(&missing)).unwrap(),
        );
        assert!(after > before);
        assert_eq!(
            device(&status(&daemon.socket), "depth+color")["backend"],
            "freenect"
        );
    }
}

#[cfg(feature = "openni2")]
mod openni2 {
    use super::*;
    use relight_backends::openni2::{OpenNi2Config, record_oni};
    use relight_core::StreamKind;

    /// OpenNI2's recorder makes a recording of its DummyDevice; relightd is told to play it
    /// before it exists (the sensor is not plugged in: `lost`, retried), then it appears (plays),
    /// then it ends (`stopped`) — and the control socket answers throughout.
    #[test]
    fn an_openni2_recording_that_appears_late_plays_and_its_end_stops_the_device() {
        let dir = tempfile::tempdir().unwrap();
        let made = dir.path().join("made.oni");
        let config = OpenNi2Config {
            uri: Some("Dummy".into()),
            ..OpenNi2Config::default()
        };
        let summary = record_oni(&config, &[StreamKind::Depth], &made, 45).unwrap();
        assert!(summary.frames(StreamKind::Depth).unwrap() >= 45);
        let oni = dir.path().join("session.oni");
        let daemon = start(
            dir.path(),
            &format!(
                "[sync]\nstreams = [\"depth\"]\n\n[depth]\nbackend = \"openni2\"\nuri = \"{}\"\n",
                oni.display()
            ),
            &[],
        );
        let lost = wait_for(&daemon, "depth", "lost (no recording yet)", |d| {
            d["state"] == "lost"
        });
        assert!(
            lost["last_error"]
                .as_str()
                .is_some_and(|e| e.contains("not found")),
            "{lost}"
        );
        std::fs::rename(&made, &oni).unwrap();
        wait_for(&daemon, "depth", "playing", |d| {
            d["state"] == "running" && d["frames"].as_u64() > Some(3)
        });
        let ended = wait_for(&daemon, "depth", "stopped at the end", |d| {
            d["state"] == "stopped"
        });
        assert!(ended["frames"].as_u64().unwrap() + ended["drops"].as_u64().unwrap() >= 45);
        assert_eq!(
            device(&status(&daemon.socket), "depth")["backend"],
            "openni2"
        );
    }
}

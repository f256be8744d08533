//! The hardware devices of a `[depth]` / `[color]` / `[probe]` / `[markers]` / `[lamp]`
//! configuration: each section's settings go to its backend's own typed config, and each device
//! runs under the failure contract of `relight_backends::device`.
//!
//! One physical sensor may supply two streams: `[depth]` and `[color]` naming the same
//! `openni2` or `freenect` backend open one device with both streams (their settings are merged
//! and must not contradict each other). Every other section is its own device.

use std::collections::BTreeMap;
use std::sync::Arc;

use anyhow::{Context, bail};
use relight_backends::device::Backoff;
use relight_backends::{Device, DeviceRunner};
use relight_core::StreamKind;
use relight_core::bus::Bus;
use relight_core::rig::RigCalibration;
use serde_json::{Map, Value};

use crate::config::{DeviceBackend, DeviceConfig};

/// One device to open: its backend, the streams it supplies and its merged settings.
#[derive(Debug, Clone, PartialEq)]
pub struct DevicePlan {
    pub backend: DeviceBackend,
    pub streams: Vec<StreamKind>,
    pub settings: Value,
}

impl DevicePlan {
    /// `depth+color` for a Kinect, else the stream's name: the runner's and the log's name.
    pub fn name(&self) -> String {
        self.streams
            .iter()
            .map(|s| s.name())
            .collect::<Vec<_>>()
            .join("+")
    }
}

/// Group the configured sections into devices.
pub fn plan(devices: &BTreeMap<StreamKind, DeviceConfig>) -> anyhow::Result<Vec<DevicePlan>> {
    let mut plans: Vec<DevicePlan> = Vec::new();
    for (&stream, device) in devices {
        let shares_sensor = matches!(
            device.backend,
            DeviceBackend::Openni2 | DeviceBackend::Freenect
        );
        let existing = plans
            .iter_mut()
            .find(|p| shares_sensor && p.backend == device.backend);
        match existing {
            Some(plan) => {
                merge_settings(&mut plan.settings, &device.settings).with_context(|| {
                    format!(
                        "[{}] and [{stream}] use one {} sensor",
                        plan.name(),
                        device.backend
                    )
                })?;
                plan.streams.push(stream);
            }
            None => plans.push(DevicePlan {
                backend: device.backend,
                streams: vec![stream],
                settings: device.settings.clone(),
            }),
        }
    }
    Ok(plans)
}

fn merge_settings(into: &mut Value, from: &Value) -> anyhow::Result<()> {
    let empty = Map::new();
    let from = from.as_object().unwrap_or(&empty);
    let Some(into) = into.as_object_mut() else {
        bail!("settings are not a table");
    };
    for (key, value) in from {
        match into.get(key) {
            Some(existing) if existing != value => {
                bail!("`{key}` differs ({existing} vs {value}); give it once")
            }
            _ => {
                into.insert(key.clone(), value.clone());
            }
        }
    }
    Ok(())
}

/// Keeps the USB hot-plug watcher (feature `hotplug`) running while the devices it wakes live.
/// Without it (or where libusb cannot watch) devices reconnect by polling with backoff.
#[derive(Debug, Default)]
pub struct Hotplug {
    #[cfg(feature = "hotplug")]
    _watcher: Option<relight_backends::hotplug::HotplugWatcher>,
}

/// Open every configured device on its own runner thread, publishing to `bus`. With the
/// `hotplug` feature, a rig USB device arriving (Kinect, PrimeSense, uEye, UVC camera, a lamp's
/// `usb_id`) cuts every lost device's reconnect backoff short.
pub fn spawn(
    devices: &BTreeMap<StreamKind, DeviceConfig>,
    rig: Option<&RigCalibration>,
    bus: &Arc<Bus>,
) -> anyhow::Result<(Vec<DeviceRunner>, Hotplug)> {
    let plans = plan(devices)?;
    #[cfg(feature = "hotplug")]
    let watcher = (!plans.is_empty()).then(|| start_hotplug(&plans)).flatten();
    let mut runners = Vec::new();
    for plan in plans {
        let name = plan.name();
        let device =
            build(&plan, rig, bus).with_context(|| format!("[{name}] {}", plan.backend))?;
        #[cfg(feature = "hotplug")]
        if let Some(watcher) = &watcher {
            let wake = watcher.wake_on(hotplug_filters(std::slice::from_ref(&plan)));
            runners.push(DeviceRunner::spawn_with_wake(
                name,
                device,
                bus.clone(),
                Backoff::default(),
                wake,
            )?);
            continue;
        }
        runners.push(DeviceRunner::spawn(
            name,
            device,
            bus.clone(),
            Backoff::default(),
        )?);
    }
    Ok((
        runners,
        Hotplug {
            #[cfg(feature = "hotplug")]
            _watcher: watcher,
        },
    ))
}

/// The rig's usual USB devices plus each lamp's adapter (`usb_id = "vvvv:pppp"`).
#[cfg(feature = "hotplug")]
fn hotplug_filters(plans: &[DevicePlan]) -> Vec<relight_backends::hotplug::UsbFilter> {
    use relight_backends::hotplug::UsbFilter;
    let mut filters = UsbFilter::rig_defaults();
    filters.extend(plans.iter().filter_map(|p| {
        p.settings
            .get("usb_id")?
            .as_str()?
            .parse::<UsbFilter>()
            .ok()
    }));
    filters
}

#[cfg(feature = "hotplug")]
fn start_hotplug(plans: &[DevicePlan]) -> Option<relight_backends::hotplug::HotplugWatcher> {
    relight_backends::hotplug::HotplugWatcher::start(hotplug_filters(plans))
        .inspect_err(|error| tracing::info!(%error, "no USB hot-plug"))
        .ok()
}

/// The backend's typed config from the section's settings; unknown keys and bad values are
/// errors that name the key.
#[allow(dead_code)]
fn settings<T: serde::de::DeserializeOwned>(settings: Value) -> anyhow::Result<T> {
    serde_json::from_value(settings).context("settings")
}

/// The settings with the sensor's per-stream switches (`depth = true`, `color = false`) set from
/// the sections present: a Kinect opened for depth alone does not stream colour.
#[allow(dead_code)]
fn with_stream_switches(
    plan: &DevicePlan,
    switches: &[(StreamKind, &str)],
) -> anyhow::Result<Value> {
    let mut settings = plan.settings.clone();
    let Some(table) = settings.as_object_mut() else {
        bail!("settings are not a table");
    };
    for &(stream, key) in switches {
        if table.contains_key(key) {
            bail!("`{key}` is set by which sections exist ([{stream}]); remove the key");
        }
        table.insert(key.to_owned(), Value::Bool(plan.streams.contains(&stream)));
    }
    Ok(settings)
}

/// Lamp reports consumers may hold at once (they are small; the recorder's queue is the bound).
#[cfg(feature = "lamp")]
const LAMP_POOL_FRAMES: usize = 64;

/// The colour camera a marker tracker sees through, from the rig's calibration.
#[allow(dead_code)]
fn colour_camera(
    rig: Option<&RigCalibration>,
) -> anyhow::Result<relight_core::camera::CameraModel> {
    rig.and_then(|r| r.color).context(
        "a marker tracker needs the colour camera's calibration: set [rig] calibration to a file with [color]",
    )
}

/// The one stream of a device that is not a shared sensor.
#[allow(dead_code)]
fn single_stream(plan: &DevicePlan) -> anyhow::Result<StreamKind> {
    match plan.streams.as_slice() {
        [stream] => Ok(*stream),
        streams => bail!("one device cannot supply {streams:?}"),
    }
}

/// A device's settings as its backend's typed config, with what it needs from the rig: every
/// check that does not touch the hardware, so `check-config` can run them.
enum Typed {
    #[cfg(feature = "openni2")]
    Openni2(relight_backends::openni2::OpenNi2Config),
    #[cfg(feature = "freenect")]
    Freenect(relight_backends::freenect::FreenectConfig),
    #[cfg(feature = "v4l2")]
    V4l2(relight_backends::v4l2::V4l2Config),
    #[cfg(feature = "ueye")]
    Ueye(relight_backends::ueye::UeyeConfig),
    #[cfg(feature = "apriltag")]
    Apriltag(
        relight_backends::markers::apriltag::AprilTagConfig,
        relight_core::camera::CameraModel,
    ),
    #[cfg(feature = "opencv")]
    Aruco(
        relight_backends::markers::aruco::ArucoConfig,
        relight_core::camera::CameraModel,
    ),
    #[cfg(feature = "lamp")]
    Lamp(
        relight_backends::lamp::LampConfig,
        String,
        Box<RigCalibration>,
    ),
}

fn typed(plan: &DevicePlan, rig: Option<&RigCalibration>) -> anyhow::Result<Typed> {
    let _ = rig;
    match plan.backend {
        #[cfg(feature = "openni2")]
        DeviceBackend::Openni2 => Ok(Typed::Openni2(settings(plan.settings.clone())?)),
        #[cfg(feature = "freenect")]
        DeviceBackend::Freenect => Ok(Typed::Freenect(settings(with_stream_switches(
            plan,
            &[(StreamKind::Depth, "depth"), (StreamKind::Color, "color")],
        )?)?)),
        #[cfg(feature = "v4l2")]
        DeviceBackend::V4l2 => Ok(Typed::V4l2(settings(plan.settings.clone())?)),
        #[cfg(feature = "ueye")]
        DeviceBackend::Ueye => Ok(Typed::Ueye(settings(plan.settings.clone())?)),
        #[cfg(feature = "apriltag")]
        DeviceBackend::Apriltag => Ok(Typed::Apriltag(
            settings(plan.settings.clone())?,
            colour_camera(rig)?,
        )),
        #[cfg(feature = "opencv")]
        DeviceBackend::Aruco => Ok(Typed::Aruco(
            settings(plan.settings.clone())?,
            colour_camera(rig)?,
        )),
        #[cfg(feature = "lamp")]
        DeviceBackend::LampSerial => {
            let mut config = plan.settings.clone();
            let board = match config.as_object_mut().and_then(|t| t.remove("board")) {
                None => "board".to_owned(),
                Some(Value::String(name)) => name,
                Some(other) => bail!("settings: `board` must be a string, got {other}"),
            };
            let Some(rig) = rig else {
                bail!("the lamp needs [rig] calibration (its marker's offset to the light)");
            };
            Ok(Typed::Lamp(settings(config)?, board, Box::new(rig.clone())))
        }
        #[allow(unreachable_patterns)]
        _ => bail!(
            "backend `{}` is not compiled into this build (cargo feature `{}` of relight-daemon)",
            plan.backend,
            plan.backend.feature()
        ),
    }
}

/// What `spawn` would refuse before opening anything: sections that contradict each other, and
/// settings their backend does not take. The error names the device (`depth+color`).
pub fn check(
    devices: &BTreeMap<StreamKind, DeviceConfig>,
    rig: Option<&RigCalibration>,
) -> Result<(), (StreamKind, String)> {
    let plans = plan(devices).map_err(|e| {
        let first = devices.keys().next().copied().unwrap_or(StreamKind::Depth);
        (first, format!("{e:#}"))
    })?;
    for plan in &plans {
        typed(plan, rig).map_err(|e| (plan.streams[0], format!("{}: {e:#}", plan.backend)))?;
    }
    Ok(())
}

/// Build one device of a backend compiled into this build.
fn build(
    plan: &DevicePlan,
    rig: Option<&RigCalibration>,
    bus: &Bus,
) -> anyhow::Result<Box<dyn Device>> {
    let _ = bus;
    match typed(plan, rig)? {
        #[cfg(feature = "openni2")]
        Typed::Openni2(config) => Ok(Box::new(relight_backends::openni2::OpenNi2Device::new(
            config,
            &plan.streams,
        )?)),
        #[cfg(feature = "freenect")]
        Typed::Freenect(config) => Ok(Box::new(relight_backends::freenect::FreenectDevice::new(
            config,
        )?)),
        #[cfg(feature = "v4l2")]
        Typed::V4l2(config) => {
            use relight_backends::v4l2::{V4l2Color, V4l2Probe};
            Ok(match single_stream(plan)? {
                StreamKind::Probe => Box::new(V4l2Probe::new(config)?.into_device()),
                _ => Box::new(V4l2Color::new(config)?.into_device()),
            })
        }
        #[cfg(feature = "ueye")]
        Typed::Ueye(config) => {
            use relight_backends::ueye::{UeyeColor, UeyeProbe};
            Ok(match single_stream(plan)? {
                StreamKind::Probe => Box::new(UeyeProbe::new(config)?.into_device()),
                _ => Box::new(UeyeColor::new(config)?.into_device()),
            })
        }
        #[cfg(feature = "apriltag")]
        Typed::Apriltag(config, camera) => Ok(Box::new(
            relight_backends::markers::apriltag::apriltag_device(&config, camera)?,
        )),
        #[cfg(feature = "opencv")]
        Typed::Aruco(config, camera) => Ok(Box::new(
            relight_backends::markers::aruco::aruco_device(&config, camera)?,
        )),
        #[cfg(feature = "lamp")]
        Typed::Lamp(config, board, rig) => {
            use relight_backends::lamp::{BoardPose, SerialLamp};
            use relight_backends::sources::SourceDevice;
            let lamp = SerialLamp::on_bus(config, bus, &rig, BoardPose::new(board))?;
            Ok(Box::new(SourceDevice::new(lamp, LAMP_POOL_FRAMES)))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn section(backend: DeviceBackend, settings: Value) -> DeviceConfig {
        DeviceConfig { backend, settings }
    }

    #[test]
    fn a_kinect_supplying_depth_and_colour_is_one_device() {
        let devices = BTreeMap::from([
            (
                StreamKind::Depth,
                section(DeviceBackend::Freenect, json!({"device_index": 1})),
            ),
            (
                StreamKind::Color,
                section(DeviceBackend::Freenect, json!({"device_index": 1})),
            ),
            (
                StreamKind::Probe,
                section(DeviceBackend::V4l2, json!({"device": "/dev/video2"})),
            ),
        ]);
        let plans = plan(&devices).unwrap();
        assert_eq!(plans.len(), 2);
        assert_eq!(plans[0].name(), "depth+color");
        assert_eq!(plans[0].settings, json!({"device_index": 1}));
        assert_eq!(plans[1].name(), "probe");
    }

    #[test]
    fn contradicting_kinect_sections_are_refused() {
        let devices = BTreeMap::from([
            (
                StreamKind::Depth,
                section(DeviceBackend::Openni2, json!({"uri": "a.oni"})),
            ),
            (
                StreamKind::Color,
                section(DeviceBackend::Openni2, json!({"uri": "b.oni"})),
            ),
        ]);
        let error = format!("{:#}", plan(&devices).unwrap_err());
        assert!(error.contains("`uri` differs"), "{error}");
    }

    #[test]
    fn colour_and_probe_cameras_on_one_backend_stay_apart() {
        let devices = BTreeMap::from([
            (StreamKind::Color, section(DeviceBackend::V4l2, json!({}))),
            (StreamKind::Probe, section(DeviceBackend::V4l2, json!({}))),
        ]);
        assert_eq!(plan(&devices).unwrap().len(), 2);
    }
}

//! The freenect backend's own checks that need no Kinect and no fakenect: open with no device,
//! its configuration, and the dump writer's refusals. Playback through fakenect, fed by the
//! simulator's dumps, is tested in `relight-sim` (`sim/tests/fakenect.rs`).

#![cfg(feature = "freenect")]

use relight_backends::freenect::disparity::RAW_INVALID;
use relight_backends::freenect::dump::{DumpError, DumpWriter};
use relight_backends::freenect::{DepthMode, FreenectConfig, FreenectDevice, library_is_fakenect};
use relight_backends::{Device, DeviceError};
use relight_core::{Image, PixelFormat, StreamKind, Timestamp};

/// With the real libfreenect and no Kinect at index 7, open is `NotFound` (retried).
#[test]
fn absent_kinect_is_not_found() {
    assert!(
        !library_is_fakenect(),
        "this test needs the real libfreenect (run without fakenect on LD_LIBRARY_PATH)"
    );
    let mut device = FreenectDevice::new(FreenectConfig {
        index: 7,
        ..FreenectConfig::default()
    })
    .unwrap();
    match device.open() {
        Err(DeviceError::NotFound { reason, .. }) => {
            assert!(
                reason.contains("Kinect") || reason.contains("libusb"),
                "{reason}"
            )
        }
        other => panic!("expected NotFound, got {other:?}"),
    }
    device.close();
}

#[test]
fn config_keys_have_defaults_and_mistakes_are_rejected() {
    let config: FreenectConfig = serde_json::from_str("{}").unwrap();
    assert_eq!(config, FreenectConfig::default());
    assert_eq!(
        (config.index, config.depth, config.color, config.depth_mode),
        (0, true, true, DepthMode::Auto)
    );
    let config: FreenectConfig = serde_json::from_str(
        r#"{"serial": "A00364A00000000A", "color": false, "depth_mode": "raw11"}"#,
    )
    .unwrap();
    let device = FreenectDevice::new(config).unwrap();
    assert_eq!(device.streams(), vec![StreamKind::Depth]);
    assert!(serde_json::from_str::<FreenectConfig>(r#"{"colour": true}"#).is_err());
    assert!(serde_json::from_str::<FreenectConfig>(r#"{"depth_mode": "disparity"}"#).is_err());
    for bad in [
        r#"{"depth": false, "color": false}"#,
        r#"{"stall_timeout_ms": 0}"#,
        r#"{"pool_frames": 0}"#,
        r#"{"serial": "A\u0000B"}"#,
    ] {
        let config: FreenectConfig = serde_json::from_str(bad).unwrap();
        assert!(
            matches!(FreenectDevice::new(config), Err(DeviceError::Config { .. })),
            "{bad}"
        );
    }
}

#[test]
fn dump_writer_refuses_what_fakenect_cannot_play() {
    let dir = tempfile::tempdir().unwrap();
    let mut writer = DumpWriter::create(dir.path()).unwrap();
    let stamp = Timestamp::new(0, 1_000_000_000);
    for (w, h) in [(100, 75), (320, 120), (1280, 960)] {
        let depth = Image::new(w, h, PixelFormat::DepthU16Mm);
        assert!(matches!(
            writer.write_depth(&depth, stamp),
            Err(DumpError::Size { .. })
        ));
    }
    let mono = Image::new(160, 120, PixelFormat::Mono8);
    assert!(matches!(
        writer.write_color(&mono, stamp),
        Err(DumpError::Format { .. })
    ));
    // A good frame, then its twin with the same stamp: the file exists, nothing is clobbered.
    let depth = Image::new(80, 60, PixelFormat::DepthU16Mm);
    let name = writer.write_depth(&depth, stamp).unwrap();
    assert!(matches!(
        writer.write_depth(&depth, stamp),
        Err(DumpError::Io { .. })
    ));
    let summary = writer.finish().unwrap();
    assert_eq!(summary.entries, vec![name]);
    let bytes = std::fs::read(dir.path().join(&summary.entries[0])).unwrap();
    let header = b"P5 640 480 65535\n";
    assert_eq!(&bytes[..header.len()], header);
    assert_eq!(bytes.len(), header.len() + 640 * 480 * 2);
    // Zero depth is "no measurement": the 11-bit invalid code.
    assert_eq!(
        u16::from_ne_bytes([bytes[header.len()], bytes[header.len() + 1]]),
        RAW_INVALID
    );
    assert!(matches!(
        DumpWriter::create(dir.path()),
        Err(DumpError::Exists { .. })
    ));
}

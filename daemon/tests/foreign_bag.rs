//! A bag another tool recorded replays: a RealSense-style ROS 2 MCAP bag, written by the
//! reference Python writer (`mcap-ros2-support`, `tests/helpers/realsense_bag.py`) from the
//! bundled recording's frames, with `bgr8` colour, `16UC1` or `32FC1` depth, `camera_info`
//! beside each image and no relight metadata. Read through a topic map, it must give back the
//! recording's frames exactly, its cameras from `camera_info`, and relightd must replay it
//! through the pipeline.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use relight_core::recording::{RecordingReader, TopicMap};
use relight_core::{Image, StreamKind, StreamMessage};

const COLOR_TOPIC: &str = "/camera/color/image_raw";
const DEPTH_TOPIC: &str = "/camera/depth/image_rect_raw";

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// The bag, or `None` where the Python interop checks are switched off.
fn realsense_bag(dir: &Path, depth_encoding: &str, frames: usize) -> Option<PathBuf> {
    realsense_bag_with(dir, depth_encoding, frames, "none")
}

/// [`realsense_bag`], with the colour also (`also`) or only (`only`) as PNG CompressedImage.
fn realsense_bag_with(
    dir: &Path,
    depth_encoding: &str,
    frames: usize,
    compressed_colour: &str,
) -> Option<PathBuf> {
    if std::env::var("RELIGHT_SKIP_PYTHON_INTEROP").is_ok_and(|v| v == "1") {
        eprintln!("RELIGHT_SKIP_PYTHON_INTEROP=1: skipping the bag written by the Python writer");
        return None;
    }
    let bag = dir.join(format!(
        "realsense-{depth_encoding}-{compressed_colour}.mcap"
    ));
    let out = Command::new("python3")
        .arg(repo("tests/helpers/realsense_bag.py"))
        .arg(repo("tests/fixtures/demo.mcap"))
        .arg(&bag)
        .args(["--depth", depth_encoding, "--frames", &frames.to_string()])
        .args(["--compressed-colour", compressed_colour])
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "realsense_bag.py: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Some(bag)
}

fn topics() -> TopicMap {
    TopicMap::new(BTreeMap::from([
        (StreamKind::Color, COLOR_TOPIC.to_owned()),
        (StreamKind::Depth, DEPTH_TOPIC.to_owned()),
    ]))
}

/// Colour and depth frames in order, with (seq, device ns, host ns) of each.
type Frames = Vec<(Image, (u64, u64, u64))>;

fn colour_and_depth(reader: &RecordingReader) -> (Frames, Frames) {
    let (mut colour, mut depth) = (Vec::new(), Vec::new());
    for message in reader.messages() {
        match message.expect("every message decodes") {
            StreamMessage::Color(f) => colour.push((
                f.payload.clone(),
                (f.seq, f.stamp.device_ns, f.stamp.host_ns),
            )),
            StreamMessage::Depth(f) => depth.push((
                f.payload.clone(),
                (f.seq, f.stamp.device_ns, f.stamp.host_ns),
            )),
            _ => {}
        }
    }
    (colour, depth)
}

#[test]
fn a_realsense_bag_reads_back_as_the_frames_it_was_written_from() {
    let dir = tempfile::tempdir().unwrap();
    let demo = RecordingReader::open(&repo("tests/fixtures/demo.mcap")).unwrap();
    let (demo_colour, demo_depth) = colour_and_depth(&demo);
    let demo_camera = demo.meta().calibration.as_ref().unwrap().color;
    for encoding in ["16UC1", "32FC1"] {
        let Some(path) = realsense_bag(dir.path(), encoding, 8) else {
            return;
        };
        let unmapped = RecordingReader::open(&path).unwrap();
        assert!(!unmapped.is_relight_recording());
        assert!(
            unmapped.messages().next().is_none(),
            "none of relight's topics"
        );
        assert!(unmapped.topics().iter().any(|t| t == "/camera/imu"));

        let bag = unmapped.with_topics(topics());
        let (colour, depth) = colour_and_depth(&bag);
        assert_eq!((colour.len(), depth.len()), (8, 8), "{encoding}");
        for (i, ((image, (seq, device_ns, host_ns)), (expected, _))) in
            colour.iter().zip(&demo_colour).enumerate()
        {
            assert_eq!(
                image, expected,
                "bgr8 colour frame {i} is the recording's rgb8"
            );
            // Numbered per stream in order (the bag's MCAP sequence is 0 throughout); the
            // device time is the driver's header.stamp, 2 ms before the host's log time.
            assert_eq!(*seq, i as u64);
            assert_eq!(host_ns - device_ns, 2_000_000);
        }
        for (i, ((image, _), (expected, _))) in depth.iter().zip(&demo_depth).enumerate() {
            let expected_mm = expected.as_u16().unwrap();
            match encoding {
                "16UC1" => assert_eq!(image, expected, "depth frame {i}"),
                _ => {
                    let metres = image.as_f32().expect("32FC1 reads as metres");
                    for (&m, &mm) in metres.iter().zip(expected_mm) {
                        if mm == 0 {
                            assert!(m.is_nan(), "invalid depth reads as NaN, got {m}");
                        } else {
                            assert_eq!((m * 1000.0).round() as u16, mm, "depth frame {i}");
                        }
                    }
                }
            }
        }
        let calibration = bag
            .calibration_from_camera_info()
            .unwrap()
            .expect("the bag has camera_info");
        assert_eq!(calibration.color, demo_camera);
        assert_eq!(calibration.depth, demo_camera, "depth registered to colour");
    }
}

/// image_transport's `…/compressed` sibling: read when it is the only colour topic (PNG, so
/// exactly), ignored when the raw topic is there too (no frame twice).
#[test]
fn compressed_colour_is_read_once_from_whichever_topic_holds_it() {
    let dir = tempfile::tempdir().unwrap();
    let demo = RecordingReader::open(&repo("tests/fixtures/demo.mcap")).unwrap();
    let (demo_colour, _) = colour_and_depth(&demo);
    for mode in ["also", "only"] {
        let Some(path) = realsense_bag_with(dir.path(), "16UC1", 4, mode) else {
            return;
        };
        let bag = RecordingReader::open(&path).unwrap().with_topics(topics());
        let (colour, depth) = colour_and_depth(&bag);
        assert_eq!((colour.len(), depth.len()), (4, 4), "{mode}");
        for (i, ((image, (seq, _, _)), (expected, _))) in
            colour.iter().zip(&demo_colour).enumerate()
        {
            assert_eq!(image, expected, "{mode}: colour frame {i}");
            assert_eq!(*seq, i as u64, "{mode}");
        }
    }
}

/// `relightd replay --topic …` plays the bag through tracking (the scene's pose: the bag has
/// no markers), reconstruction and `depth_preview`, which blends the depth over the colour
/// image: every frame set is rendered and written, and the depth shows in the composite.
#[test]
fn relightd_replays_a_realsense_bag_with_remapped_topics() {
    let dir = tempfile::tempdir().unwrap();
    let frames = 12;
    let Some(bag) = realsense_bag(dir.path(), "16UC1", frames) else {
        return;
    };
    let output = dir.path().join("out");
    let out = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .arg("replay")
        .arg(&bag)
        .args(["--mode", "fast", "--engine", "depth_preview", "--scene"])
        .arg(repo("tests/scenes/desk_box"))
        .arg("--topic")
        .arg(format!("color={COLOR_TOPIC}"))
        .arg("--topic")
        .arg(format!("depth={DEPTH_TOPIC}"))
        .arg("--output")
        .arg(&output)
        .arg("--socket")
        .arg(dir.path().join("control.sock"))
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains(&format!("rendered {frames} of {frames} frame sets"))
            && stdout.contains("engine depth_preview (0 not rendered)"),
        "{stdout}\n{stderr}"
    );
    let mut pngs: Vec<PathBuf> = std::fs::read_dir(&output)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    pngs.sort();
    assert_eq!(pngs.len(), frames, "{pngs:?}");

    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&pngs[0]).unwrap(),
    ));
    let mut png = decoder.read_info().unwrap();
    let mut composite = vec![0; png.output_buffer_size().unwrap()];
    let info = png.next_frame(&mut composite).unwrap();
    let demo = RecordingReader::open(&repo("tests/fixtures/demo.mcap")).unwrap();
    let (colour, _) = colour_and_depth(&demo);
    let camera = colour[0].0.as_u8().unwrap();
    assert_eq!(
        (info.width, info.height, info.color_type),
        (320, 240, png::ColorType::Rgb)
    );
    let mean_difference = composite
        .iter()
        .zip(camera)
        .map(|(&a, &b)| f64::from(a.abs_diff(b)))
        .sum::<f64>()
        / camera.len() as f64;
    assert!(
        mean_difference > 10.0,
        "the composite is the camera image: depth never reached the engine ({mean_difference:.1})"
    );
}

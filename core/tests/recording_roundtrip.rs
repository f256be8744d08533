//! A recording gives back exactly what was written: every stream, every pixel format, every
//! frame field, the calibration and the source.

mod recording_support;

use std::io::Cursor;
use std::sync::Arc;

use glam::{Vec2, Vec3};
use recording_support::{calibration, meta, record, small_chunks, traffic};
use relight_core::recording::{
    ColorEncoding, OutputMessage, RecordingCompression, RecordingError, RecordingMeta,
    RecordingOptions, RecordingReader, RecordingWriter,
};
use relight_core::{
    Frame, Image, LampState, MarkerDetection, MarkerSet, PixelFormat, Pose, StreamKind,
    StreamMessage, Timestamp,
};

fn read_all(reader: &RecordingReader) -> Vec<StreamMessage> {
    reader
        .messages()
        .collect::<Result<Vec<_>, _>>()
        .expect("every message reads back")
}

#[test]
fn every_stream_and_pixel_format_round_trips_frame_exact() {
    let messages = traffic(30, 40, 30, 7);
    let bytes = record(&messages, &small_chunks());
    let reader = RecordingReader::from_bytes(bytes).unwrap();
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    assert!(reader.has_summary());
    assert!(
        reader.chunks().len() >= 4,
        "small chunks make several chunks"
    );
    let back = read_all(&reader);
    assert_eq!(back.len(), messages.len());
    for (i, (written, read)) in messages.iter().zip(&back).enumerate() {
        assert_eq!(written, read, "message {i} ({})", written.kind());
    }

    let formats: std::collections::BTreeSet<_> = back
        .iter()
        .filter_map(|m| match m {
            StreamMessage::Depth(f) | StreamMessage::Color(f) => Some(f.payload.format()),
            StreamMessage::Probe(f) => Some(f.payload.image.format()),
            _ => None,
        })
        .map(|f| f.ros_encoding())
        .collect();
    assert_eq!(formats.len(), PixelFormat::ALL.len(), "{formats:?}");
}

#[test]
fn calibration_and_source_come_back() {
    let bytes = record(&traffic(1, 8, 8, 1), &RecordingOptions::default());
    let reader = RecordingReader::from_bytes(bytes).unwrap();
    assert_eq!(reader.meta(), &meta());
    assert_eq!(reader.meta().calibration, Some(calibration()));
}

#[test]
fn recording_without_calibration_has_none() {
    let meta = RecordingMeta {
        calibration: None,
        source: "bare".into(),
    };
    let writer = RecordingWriter::new(Cursor::new(Vec::new()), &meta).unwrap();
    let (summary, cursor) = writer.finish_into_inner().unwrap();
    assert_eq!(summary.total_messages(), 0);
    assert_eq!(summary.start_ns, None);
    let reader = RecordingReader::from_bytes(cursor.into_inner()).unwrap();
    assert_eq!(reader.meta(), &meta);
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    assert_eq!(reader.messages().count(), 0);
}

#[test]
fn file_round_trip_reports_counts_and_time_span() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("take.mcap");
    let messages = traffic(6, 16, 12, 3);
    let mut writer = RecordingWriter::create(&path, &meta()).unwrap();
    for msg in &messages {
        writer.write(msg).unwrap();
    }
    assert_eq!(writer.messages_written(), messages.len() as u64);
    let summary = writer.finish().unwrap();
    for kind in StreamKind::ALL {
        assert_eq!(summary.messages.get(&kind), Some(&6), "{kind}");
    }
    let host: Vec<u64> = messages.iter().map(|m| m.stamp().host_ns).collect();
    assert_eq!(summary.start_ns, host.iter().min().copied());
    assert_eq!(summary.end_ns, host.iter().max().copied());

    let reader = RecordingReader::open(&path).unwrap();
    assert_eq!(read_all(&reader), messages);
}

#[test]
fn messages_come_back_in_host_time_order() {
    // A lamp reading that arrives late (older host stamp than frames written before it) and
    // chunks small enough that the two end up in different chunks.
    let image = |seq: u64, host_ns: u64| {
        StreamMessage::Depth(Arc::new(Frame::new(
            seq,
            Timestamp::new(seq, host_ns),
            Image::new(64, 64, PixelFormat::DepthU16Mm),
        )))
    };
    let late_lamp = StreamMessage::Lamp(Arc::new(Frame::new(
        9,
        Timestamp::new(1, 1_500),
        LampState::default(),
    )));
    let written = vec![
        image(0, 1_000),
        image(1, 2_000),
        image(2, 3_000),
        late_lamp.clone(),
    ];
    let options = RecordingOptions {
        chunk_size_bytes: 1024,
        ..Default::default()
    };
    let reader = RecordingReader::from_bytes(record(&written, &options)).unwrap();
    let hosts: Vec<u64> = read_all(&reader)
        .iter()
        .map(|m| m.stamp().host_ns)
        .collect();
    assert_eq!(hosts, [1_000, 1_500, 2_000, 3_000]);
}

#[test]
fn every_compression_reads_back() {
    let messages = traffic(4, 16, 16, 11);
    for compression in [
        RecordingCompression::Zstd,
        RecordingCompression::Lz4,
        RecordingCompression::None,
    ] {
        let options = RecordingOptions {
            compression,
            ..small_chunks()
        };
        let reader = RecordingReader::from_bytes(record(&messages, &options)).unwrap();
        let expected = match compression {
            RecordingCompression::Zstd => "zstd",
            RecordingCompression::Lz4 => "lz4",
            RecordingCompression::None => "",
        };
        assert!(reader.chunks().iter().all(|c| c.compression == expected));
        assert_eq!(read_all(&reader), messages, "{compression:?}");
    }
}

#[test]
fn non_finite_marker_is_refused_and_writer_goes_on() {
    let mut writer = RecordingWriter::new(Cursor::new(Vec::new()), &meta()).unwrap();
    let bad = StreamMessage::Markers(Arc::new(Frame::new(
        4,
        Timestamp::new(1, 1),
        MarkerSet {
            detections: vec![MarkerDetection {
                family: "tag36h11".into(),
                marker_id: 3,
                corners_px: [Vec2::ZERO, Vec2::X, Vec2::ONE, Vec2::new(f32::NAN, 0.0)],
                camera_from_marker: Pose::IDENTITY,
                reprojection_rms_px: 0.1,
            }],
        },
    )));
    let err = writer.write(&bad).unwrap_err();
    assert!(
        matches!(&err, RecordingError::Encode { channel, seq: 4, .. } if channel == "/markers"),
        "{err}"
    );
    let good = StreamMessage::Lamp(Arc::new(Frame::new(
        5,
        Timestamp::new(2, 2),
        LampState {
            on: true,
            position_in_world: Vec3::ONE,
            intensity: Vec3::splat(0.5),
        },
    )));
    writer.write(&good).unwrap();
    assert_eq!(writer.messages_written(), 1);
    let (_, cursor) = writer.finish_into_inner().unwrap();
    let reader = RecordingReader::from_bytes(cursor.into_inner()).unwrap();
    assert_eq!(read_all(&reader), vec![good]);
}

#[test]
fn channels_use_documented_topics_and_schemas() {
    let bytes = record(&traffic(1, 4, 4, 5), &RecordingOptions::default());
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let mut channels: Vec<(String, String, String, String)> = summary
        .channels
        .values()
        .map(|c| {
            let schema = c.schema.as_ref().unwrap();
            (
                c.topic.clone(),
                c.message_encoding.clone(),
                schema.name.clone(),
                schema.encoding.clone(),
            )
        })
        .collect();
    channels.sort();
    let row = |t: &str, s: &str| (t.into(), "cdr".into(), s.into(), "ros2msg".into());
    // Every channel ROS 2 CDR (the `ros2` profile); camera_info only for the cameras the
    // calibration has (depth and probe here).
    assert_eq!(
        channels,
        vec![
            row("/color/frame_info", "relight_msgs/msg/FrameInfo"),
            row("/color/image_raw", "sensor_msgs/msg/Image"),
            row("/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
            row("/depth/frame_info", "relight_msgs/msg/FrameInfo"),
            row("/depth/image_raw", "sensor_msgs/msg/Image"),
            row("/lamp", "relight_msgs/msg/LampState"),
            row("/markers", "relight_msgs/msg/MarkerSet"),
            row("/probe/camera_info", "sensor_msgs/msg/CameraInfo"),
            row("/probe/frame_info", "relight_msgs/msg/FrameInfo"),
            row("/probe/image_raw", "sensor_msgs/msg/Image"),
            row("/tf", "tf2_msgs/msg/TFMessage"),
            row("/tf_static", "tf2_msgs/msg/TFMessage"),
        ]
    );
    let header = mcap::read::LinearReader::new(&bytes)
        .unwrap()
        .find_map(|r| match r.unwrap() {
            mcap::records::Record::Header(h) => Some(h),
            _ => None,
        })
        .unwrap();
    assert_eq!(header.profile, "ros2");
    // Depth and probe: frame_info, camera_info, image; colour: frame_info, image; markers
    // (none detected, so no /tf); lamp and its /tf; the /tf_static before the first message.
    let stats = summary.stats.unwrap();
    assert_eq!(stats.message_count, 3 + 2 + 3 + 1 + 2 + 1);
    assert!(!summary.chunk_indexes.is_empty());
    let names: Vec<&str> = summary
        .metadata_indexes
        .iter()
        .map(|m| m.name.as_str())
        .collect();
    assert_eq!(names, ["relight.recording", "relight.calibration"]);
}

#[test]
fn ground_truth_channels_round_trip_beside_the_streams() {
    use relight_core::light::Light;
    use relight_core::recording::truth::{MarkerTruth, TruthKind, TruthMessage, TruthState};

    let messages = traffic(4, 12, 10, 3);
    let mut rng = recording_support::Rng::new(11);
    let mut truth = Vec::new();
    for (i, msg) in messages
        .iter()
        .enumerate()
        .filter(|(_, m)| m.kind() == StreamKind::Depth)
    {
        let stamp = msg.stamp();
        for kind in [TruthKind::Depth, TruthKind::Normals, TruthKind::Albedo] {
            let format = kind.pixel_format().unwrap();
            let image = recording_support::noisy_image(&mut rng, 12, 10, format);
            truth.push(TruthMessage::Image(
                kind,
                Frame::new(i as u64, stamp, image),
            ));
        }
        let state = TruthState {
            world_from_camera: Pose::new(glam::Quat::from_rotation_y(i as f32), Vec3::X),
            world_from_probe: Some(Pose::IDENTITY),
            lights: vec![Light::Point {
                position_in_world: Vec3::splat(i as f32),
                intensity: Vec3::ONE,
            }],
            markers: vec![MarkerTruth {
                family: "tag36h11".into(),
                marker_id: 2,
                world_from_marker: Pose::IDENTITY,
                size_m: 0.1,
            }],
        };
        truth.push(TruthMessage::State(Frame::new(i as u64, stamp, state)));
    }

    let mut writer =
        RecordingWriter::with_options(Cursor::new(Vec::new()), &meta(), &small_chunks()).unwrap();
    let mut t = truth.iter();
    for msg in &messages {
        writer.write(msg).unwrap();
        if msg.kind() == StreamKind::Depth {
            for _ in 0..4 {
                writer.write_truth(t.next().unwrap()).unwrap();
            }
        }
    }
    // An image of the wrong format is refused and the writer goes on.
    let wrong = TruthMessage::Image(
        TruthKind::Depth,
        Frame::new(0, Timestamp::new(0, 0), Image::new(2, 2, PixelFormat::Rgb8)),
    );
    assert!(matches!(
        writer.write_truth(&wrong),
        Err(RecordingError::Encode { .. })
    ));
    let (_, cursor) = writer.finish_into_inner().unwrap();

    let reader = RecordingReader::from_bytes(cursor.into_inner()).unwrap();
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    assert_eq!(read_all(&reader), messages, "the streams are unchanged");
    let back: Vec<TruthMessage> = reader.truth().collect::<Result<_, _>>().unwrap();
    assert_eq!(back, truth);
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig { cases: 24, failure_persistence: None, ..Default::default() })]

    /// Write → read is exact for any traffic, image size, chunk size and compression.
    #[test]
    fn any_recording_reads_back_exactly(
        frames in 1usize..8,
        width in 1u32..24,
        height in 1u32..24,
        seed in proptest::prelude::any::<u64>(),
        chunk_size_bytes in 64u64..200_000,
        compression in 0usize..3,
    ) {
        let messages = traffic(frames, width, height, seed);
        let options = RecordingOptions {
            chunk_size_bytes,
            compression: [RecordingCompression::Zstd, RecordingCompression::Lz4, RecordingCompression::None][compression],
            ..Default::default()
        };
        let reader = RecordingReader::from_bytes(record(&messages, &options)).unwrap();
        proptest::prop_assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
        proptest::prop_assert_eq!(read_all(&reader), messages);
    }
}

/// PNG colour reads back exactly, JPEG within its loss; non-8-bit colour stays raw.
#[test]
fn compressed_colour_round_trips() {
    let messages = traffic(6, 40, 30, 12);
    for (encoding, exact) in [
        (ColorEncoding::Png, true),
        (ColorEncoding::Jpeg { quality: 90 }, false),
    ] {
        let options = RecordingOptions {
            color_encoding: encoding,
            ..small_chunks()
        };
        let reader = RecordingReader::from_bytes(record(&messages, &options)).unwrap();
        let back = read_all(&reader);
        assert_eq!(back.len(), messages.len());
        for (written, read) in messages.iter().zip(&back) {
            match (written, read) {
                (StreamMessage::Color(w), StreamMessage::Color(r)) => {
                    assert_eq!((w.seq, w.stamp), (r.seq, r.stamp));
                    let eight_bit =
                        matches!(w.payload.format(), PixelFormat::Rgb8 | PixelFormat::Mono8);
                    if exact || !eight_bit {
                        assert_eq!(w.payload, r.payload, "{encoding:?}");
                    } else {
                        assert_eq!(w.payload.format(), r.payload.format());
                        // Noise is JPEG's worst case; the mean error stays bounded.
                        let (a, b) = (w.payload.as_u8().unwrap(), r.payload.as_u8().unwrap());
                        let mean = a
                            .iter()
                            .zip(b)
                            .map(|(x, y)| f64::from(x.abs_diff(*y)))
                            .sum::<f64>()
                            / a.len() as f64;
                        assert!(mean < 40.0, "mean error {mean}");
                    }
                }
                _ => assert_eq!(written, read),
            }
        }
    }
}

#[test]
fn outputs_round_trip_beside_the_streams() {
    let messages = traffic(2, 8, 6, 3);
    let stamp = Timestamp::new(42, 1_700_000_000_000_000_000);
    let mut composite = Image::new(8, 6, PixelFormat::Rgb8);
    composite
        .as_u8_mut()
        .unwrap()
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = i as u8);
    let mut delta = Image::new(8, 6, PixelFormat::Rgba16F);
    delta
        .as_u16_mut()
        .unwrap()
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = half::f16::from_f32(i as f32 * -0.25).to_bits());
    let outputs = vec![
        OutputMessage::Composite(Frame::new(7, stamp, composite)),
        OutputMessage::Delta(Frame::new(7, stamp, delta)),
        OutputMessage::Lighting(Frame::new(7, stamp, r#"{"lights":[]}"#.to_owned())),
    ];
    for encoding in [ColorEncoding::Raw, ColorEncoding::Png] {
        let options = RecordingOptions {
            color_encoding: encoding,
            ..RecordingOptions::default()
        };
        let mut writer =
            RecordingWriter::with_options(Cursor::new(Vec::new()), &meta(), &options).unwrap();
        for msg in &messages {
            writer.write(msg).unwrap();
        }
        for output in &outputs {
            writer.write_output(output).unwrap();
        }
        let (_, cursor) = writer.finish_into_inner().unwrap();
        let reader = RecordingReader::from_bytes(cursor.into_inner()).unwrap();
        let back: Vec<OutputMessage> = reader.outputs().collect::<Result<_, _>>().unwrap();
        assert_eq!(back, outputs, "{encoding:?}");
        assert_eq!(read_all(&reader), messages, "the streams are untouched");
    }
    let mut writer = RecordingWriter::new(Cursor::new(Vec::new()), &meta()).unwrap();
    let long = OutputMessage::Lighting(Frame::new(1 << 40, stamp, "{}".into()));
    assert!(matches!(
        writer.write_output(&long),
        Err(RecordingError::Encode { .. })
    ));
}

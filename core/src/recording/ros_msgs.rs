//! The ROS 2 messages of a format-2 recording besides `sensor_msgs/msg/Image` and
//! `sensor_msgs/msg/CameraInfo`: relight's own `relight_msgs` (per-frame sensor facts, markers,
//! the lamp), `tf2_msgs/msg/TFMessage`, `sensor_msgs/msg/CompressedImage` and
//! `std_msgs/msg/String`, each as its schema text (the concatenated `.msg` form of ROS 2 bags,
//! which `mcap-ros2-support` and Foxglove parse) and a CDR codec.
//!
//! Poses are written in the ROS optical convention ([`crate::ros_frames`]) and read back into
//! relight's glTF convention, bit for bit. Every message's `header.stamp` is the host clock; the
//! sensor's own clock is the `device_stamp_ns` field.

use glam::{Vec2, Vec3};

use super::schema::{CdrReader, CdrWriter, header_definitions};
use crate::pose::Pose;
use crate::ros_frames;
use crate::stream::{LampState, MarkerDetection, MarkerSet};

/// Schema sections of the `geometry_msgs` the messages here use.
macro_rules! point_definition {
    () => {
        "\
================================================================================
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
"
    };
}

macro_rules! quaternion_definition {
    () => {
        "\
================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"
    };
}

pub const FRAME_INFO_SCHEMA_NAME: &str = "relight_msgs/msg/FrameInfo";
/// What a sensor said about one image that `sensor_msgs/Image` cannot hold; published beside
/// each image topic with the image's header (`/color/image_raw` → `/color/frame_info`).
/// `exposure_us` and `gain_db` are the probe's; 0 for cameras relight does not expose.
pub const FRAME_INFO_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
uint64 seq
uint64 device_stamp_ns
uint32 exposure_us
float32 gain_db
",
    header_definitions!()
);

pub const MARKER_SET_SCHEMA_NAME: &str = "relight_msgs/msg/MarkerSet";
/// The square markers detected in one image of `header.frame_id`; `camera_from_marker` in that
/// camera's optical frame (+z forward), the marker's frame +x right, +y up on the printed tag,
/// +z out of it; corners in pixels `[x0, y0, … x3, y3]`, counter-clockwise from the tag's
/// lower-left as seen in the image.
pub const MARKER_SET_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
uint64 seq
uint64 device_stamp_ns
relight_msgs/MarkerDetection[] detections
================================================================================
MSG: relight_msgs/MarkerDetection
string family
uint32 marker_id
float32[8] corners_px
geometry_msgs/Pose camera_from_marker
float32 reprojection_rms_px
================================================================================
MSG: geometry_msgs/Pose
Point position
Quaternion orientation
",
    point_definition!(),
    quaternion_definition!(),
    header_definitions!()
);

pub const LAMP_STATE_SCHEMA_NAME: &str = "relight_msgs/msg/LampState";
/// The tracked pocket lamp: `position` is the light's centre in `header.frame_id` (`world`, the
/// board's frame), metres; `intensity` linear RGB radiant intensity, W/sr.
pub const LAMP_STATE_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
uint64 seq
uint64 device_stamp_ns
bool on
geometry_msgs/Point position
float32[3] intensity
",
    point_definition!(),
    header_definitions!()
);

pub const TF_MESSAGE_SCHEMA_NAME: &str = "tf2_msgs/msg/TFMessage";
pub const TF_MESSAGE_SCHEMA: &str = concat!(
    "\
geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
Transform transform
================================================================================
MSG: geometry_msgs/Transform
Vector3 translation
Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
",
    quaternion_definition!(),
    header_definitions!()
);

pub const COMPRESSED_IMAGE_SCHEMA_NAME: &str = "sensor_msgs/msg/CompressedImage";
pub const COMPRESSED_IMAGE_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
string format
uint8[] data
",
    header_definitions!()
);

pub const STRING_SCHEMA_NAME: &str = "std_msgs/msg/String";
pub const STRING_SCHEMA: &str = "string data\n";

/// The `header` every message here starts with: host time and a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header<'a> {
    pub stamp_ns: u64,
    pub frame_id: &'a str,
}

/// A [`FRAME_INFO_SCHEMA`] message.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameInfo {
    pub seq: u64,
    pub device_stamp_ns: u64,
    pub exposure_us: u32,
    pub gain_db: f32,
}

pub fn encode_frame_info(
    out: &mut Vec<u8>,
    header: Header<'_>,
    info: &FrameInfo,
) -> Result<(), String> {
    out.clear();
    let mut cdr = CdrWriter::new(out);
    cdr.header(header.stamp_ns, header.frame_id)?;
    cdr.u64(info.seq);
    cdr.u64(info.device_stamp_ns);
    cdr.u32(info.exposure_us);
    cdr.f32(info.gain_db);
    Ok(())
}

pub fn decode_frame_info(data: &[u8]) -> Result<FrameInfo, String> {
    let mut cdr = CdrReader::new(data)?;
    cdr.header()?;
    Ok(FrameInfo {
        seq: cdr.u64()?,
        device_stamp_ns: cdr.u64()?,
        exposure_us: cdr.u32()?,
        gain_db: cdr.f32()?,
    })
}

fn write_point(cdr: &mut CdrWriter<'_>, p: Vec3) {
    for v in p.to_array() {
        cdr.f64(f64::from(v));
    }
}

fn read_point(cdr: &mut CdrReader<'_>) -> Result<Vec3, String> {
    Ok(Vec3::new(
        cdr.f64()? as f32,
        cdr.f64()? as f32,
        cdr.f64()? as f32,
    ))
}

/// `geometry_msgs/Pose` (or `Transform`: the same fields, point first).
fn write_pose(cdr: &mut CdrWriter<'_>, pose: Pose) {
    write_point(cdr, pose.translation);
    for v in pose.rotation.to_array() {
        cdr.f64(f64::from(v));
    }
}

fn read_pose(cdr: &mut CdrReader<'_>) -> Result<Pose, String> {
    let translation = read_point(cdr)?;
    let mut q = [0.0f32; 4];
    for v in &mut q {
        *v = cdr.f64()? as f32;
    }
    Ok(Pose {
        rotation: glam::Quat::from_array(q),
        translation,
    })
}

/// JSON had no NaN and neither does a recording: a non-finite value is refused, not written.
fn finite_detection(i: usize, d: &MarkerDetection) -> Result<(), String> {
    let finite = d.corners_px.iter().all(|c| c.is_finite())
        && d.camera_from_marker.rotation.is_finite()
        && d.camera_from_marker.translation.is_finite()
        && d.reprojection_rms_px.is_finite();
    if finite {
        Ok(())
    } else {
        Err(format!(
            "detection {i} (marker {}) holds a non-finite number",
            d.marker_id
        ))
    }
}

/// Encode a marker set seen by camera `header.frame_id`; poses go out in its optical frame.
pub fn encode_markers(
    out: &mut Vec<u8>,
    header: Header<'_>,
    seq: u64,
    device_stamp_ns: u64,
    markers: &MarkerSet,
) -> Result<(), String> {
    out.clear();
    for (i, d) in markers.detections.iter().enumerate() {
        finite_detection(i, d)?;
    }
    let mut cdr = CdrWriter::new(out);
    cdr.header(header.stamp_ns, header.frame_id)?;
    cdr.u64(seq);
    cdr.u64(device_stamp_ns);
    cdr.u32(u32::try_from(markers.detections.len()).map_err(|e| e.to_string())?);
    for d in &markers.detections {
        cdr.string(&d.family)?;
        cdr.u32(d.marker_id);
        for corner in d.corners_px {
            cdr.f32(corner.x);
            cdr.f32(corner.y);
        }
        write_pose(&mut cdr, ros_frames::optical_from(d.camera_from_marker));
        cdr.f32(d.reprojection_rms_px);
    }
    Ok(())
}

/// Decode a [`MARKER_SET_SCHEMA`] message: the set (poses back in the glTF camera frame), its
/// `seq` and device time.
pub fn decode_markers(data: &[u8]) -> Result<(MarkerSet, u64, u64), String> {
    let mut cdr = CdrReader::new(data)?;
    cdr.header()?;
    let seq = cdr.u64()?;
    let device_stamp_ns = cdr.u64()?;
    // A detection is at least a string length, an id, 8 corners, a pose and an RMS.
    let count = cdr.sequence_len(4 + 4 + 32 + 56 + 4)?;
    let mut detections = Vec::with_capacity(count);
    for _ in 0..count {
        let family = cdr.string("family")?.to_owned();
        let marker_id = cdr.u32()?;
        let mut corners_px = [Vec2::ZERO; 4];
        for corner in &mut corners_px {
            *corner = Vec2::new(cdr.f32()?, cdr.f32()?);
        }
        let camera_from_marker = ros_frames::gltf_from(read_pose(&mut cdr)?);
        let reprojection_rms_px = cdr.f32()?;
        detections.push(MarkerDetection {
            family,
            marker_id,
            corners_px,
            camera_from_marker,
            reprojection_rms_px,
        });
    }
    Ok((MarkerSet { detections }, seq, device_stamp_ns))
}

pub fn encode_lamp(
    out: &mut Vec<u8>,
    header: Header<'_>,
    seq: u64,
    device_stamp_ns: u64,
    lamp: &LampState,
) -> Result<(), String> {
    out.clear();
    if !(lamp.position_in_world.is_finite() && lamp.intensity.is_finite()) {
        return Err("lamp state holds a non-finite number".into());
    }
    let mut cdr = CdrWriter::new(out);
    cdr.header(header.stamp_ns, header.frame_id)?;
    cdr.u64(seq);
    cdr.u64(device_stamp_ns);
    cdr.bool(lamp.on);
    write_point(&mut cdr, lamp.position_in_world);
    for v in lamp.intensity.to_array() {
        cdr.f32(v);
    }
    Ok(())
}

/// Decode a [`LAMP_STATE_SCHEMA`] message: the state, its `seq` and device time.
pub fn decode_lamp(data: &[u8]) -> Result<(LampState, u64, u64), String> {
    let mut cdr = CdrReader::new(data)?;
    cdr.header()?;
    let seq = cdr.u64()?;
    let device_stamp_ns = cdr.u64()?;
    let on = cdr.bool()?;
    let position_in_world = read_point(&mut cdr)?;
    let intensity = Vec3::new(cdr.f32()?, cdr.f32()?, cdr.f32()?);
    Ok((
        LampState {
            on,
            position_in_world,
            intensity,
        },
        seq,
        device_stamp_ns,
    ))
}

/// One `geometry_msgs/TransformStamped`: `parent_from_child`, already in the frames' own
/// conventions (convert camera poses with [`crate::ros_frames`] first).
#[derive(Debug, Clone, PartialEq)]
pub struct Transform {
    pub parent: String,
    pub child: String,
    pub parent_from_child: Pose,
}

pub fn encode_tf(out: &mut Vec<u8>, stamp_ns: u64, transforms: &[Transform]) -> Result<(), String> {
    out.clear();
    if let Some(bad) = transforms.iter().find(|t| {
        !(t.parent_from_child.rotation.is_finite() && t.parent_from_child.translation.is_finite())
    }) {
        return Err(format!(
            "transform {} → {} holds a non-finite number",
            bad.parent, bad.child
        ));
    }
    let mut cdr = CdrWriter::new(out);
    cdr.u32(u32::try_from(transforms.len()).map_err(|e| e.to_string())?);
    for t in transforms {
        cdr.header(stamp_ns, &t.parent)?;
        cdr.string(&t.child)?;
        write_pose(&mut cdr, t.parent_from_child);
    }
    Ok(())
}

/// Decode a [`TF_MESSAGE_SCHEMA`] message.
pub fn decode_tf(data: &[u8]) -> Result<Vec<Transform>, String> {
    let mut cdr = CdrReader::new(data)?;
    // A transform is at least a stamp, two string lengths and a pose.
    let count = cdr.sequence_len(8 + 4 + 4 + 56)?;
    let mut transforms = Vec::with_capacity(count);
    for _ in 0..count {
        let (_, parent) = cdr.header()?;
        let parent = parent.to_owned();
        let child = cdr.string("child_frame_id")?.to_owned();
        let parent_from_child = read_pose(&mut cdr)?;
        transforms.push(Transform {
            parent,
            child,
            parent_from_child,
        });
    }
    Ok(transforms)
}

/// A decoded `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressedImage<'a> {
    pub stamp_ns: u64,
    pub frame_id: &'a str,
    pub format: &'a str,
    pub data: &'a [u8],
}

pub fn encode_compressed_image(
    out: &mut Vec<u8>,
    header: Header<'_>,
    format: &str,
    data: &[u8],
) -> Result<(), String> {
    out.clear();
    out.reserve(data.len() + 64);
    let mut cdr = CdrWriter::new(out);
    cdr.header(header.stamp_ns, header.frame_id)?;
    cdr.string(format)?;
    cdr.bytes(data)
}

pub fn decode_compressed_image(data: &[u8]) -> Result<CompressedImage<'_>, String> {
    let mut cdr = CdrReader::new(data)?;
    let (stamp_ns, frame_id) = cdr.header()?;
    let format = cdr.string("format")?;
    let data = cdr.bytes()?;
    Ok(CompressedImage {
        stamp_ns,
        frame_id,
        format,
        data,
    })
}

pub fn encode_string(out: &mut Vec<u8>, text: &str) -> Result<(), String> {
    out.clear();
    CdrWriter::new(out).string(text)
}

pub fn decode_string(data: &[u8]) -> Result<&str, String> {
    CdrReader::new(data)?.string("data")
}

#[cfg(test)]
mod tests {
    use glam::Quat;

    use super::*;

    fn detection() -> MarkerDetection {
        MarkerDetection {
            family: "tag36h11".into(),
            marker_id: 7,
            corners_px: [
                Vec2::new(1.0, 2.0),
                Vec2::new(3.5, 2.0),
                Vec2::new(3.5, 4.25),
                Vec2::new(1.0, 4.0),
            ],
            camera_from_marker: Pose {
                rotation: Quat::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 1.1),
                translation: Vec3::new(0.1, -0.2, -1.86),
            },
            reprojection_rms_px: 0.31,
        }
    }

    #[test]
    fn markers_go_out_optical_and_come_back_exactly() {
        let markers = MarkerSet {
            detections: vec![detection(), detection()],
        };
        let mut out = Vec::new();
        let header = Header {
            stamp_ns: 5,
            frame_id: "color",
        };
        encode_markers(&mut out, header, u64::MAX, 9, &markers).unwrap();
        let (back, seq, device) = decode_markers(&out).unwrap();
        assert_eq!((back, seq, device), (markers, u64::MAX, 9));
        // The marker 1.86 m in front of the camera has optical z = +1.86 on the wire.
        let z_at = out.len() - 4 - 4 * 8 - 8;
        let z = f64::from_le_bytes(out[z_at..z_at + 8].try_into().unwrap());
        assert!((z - 1.86).abs() < 1e-6, "{z}");
        for len in 0..out.len() {
            assert!(decode_markers(&out[..len]).is_err(), "prefix of {len}");
        }
    }

    #[test]
    fn a_lying_sequence_length_is_an_error_not_an_allocation() {
        let mut out = Vec::new();
        let mut cdr = CdrWriter::new(&mut out);
        cdr.header(0, "color").unwrap();
        cdr.u64(0);
        cdr.u64(0);
        cdr.u32(u32::MAX);
        assert!(decode_markers(&out).unwrap_err().contains("does not fit"));
    }

    #[test]
    fn lamp_frame_info_tf_and_strings_round_trip() {
        let lamp = LampState {
            on: true,
            position_in_world: Vec3::new(0.3, 0.9, -0.1),
            intensity: Vec3::new(2.0, 1.5, 1.0),
        };
        let header = Header {
            stamp_ns: 1,
            frame_id: "world",
        };
        let mut out = Vec::new();
        encode_lamp(&mut out, header, 3, 4, &lamp).unwrap();
        assert_eq!(decode_lamp(&out).unwrap(), (lamp, 3, 4));
        let bad = LampState {
            on: true,
            position_in_world: Vec3::NAN,
            ..lamp
        };
        assert!(encode_lamp(&mut out, header, 0, 0, &bad).is_err());

        let info = FrameInfo {
            seq: 1 << 40,
            device_stamp_ns: 77,
            exposure_us: 250,
            gain_db: 0.1 + f32::EPSILON,
        };
        encode_frame_info(&mut out, header, &info).unwrap();
        assert_eq!(decode_frame_info(&out).unwrap(), info);

        let transforms = vec![Transform {
            parent: "color".into(),
            child: "marker_7".into(),
            parent_from_child: detection().camera_from_marker,
        }];
        encode_tf(&mut out, 8, &transforms).unwrap();
        assert_eq!(decode_tf(&out).unwrap(), transforms);

        encode_string(&mut out, "{\"a\":1}").unwrap();
        assert_eq!(decode_string(&out).unwrap(), "{\"a\":1}");

        encode_compressed_image(&mut out, header, "jpeg", &[1, 2, 3]).unwrap();
        let image = decode_compressed_image(&out).unwrap();
        assert_eq!((image.format, image.data), ("jpeg", &[1u8, 2, 3][..]));
    }
}

//! ROS 2 `sensor_msgs/msg/CameraInfo`: a camera's intrinsics as ROS drivers publish them beside
//! each image topic (`/camera/color/image_raw` → `/camera/color/camera_info`), read into a
//! [`CameraModel`] so that a bag from another rig replays without a relight calibration.
//!
//! ROS's `plumb_bob` (and `rational_polynomial` with its extra terms zero) is the
//! Brown–Conrady model of [`Pinhole`], `d = [k1, k2, p1, p2, k3]`; `equidistant` is the
//! Kannala–Brandt model, `d = [k1, k2, k3, k4]`. `k` is the row-major intrinsic matrix of the
//! unrectified image, in pixels, in the optical convention (+z forward, +y down) that relight's
//! camera models share.

use super::schema::{CdrReader, CdrWriter, header_definitions};
use crate::camera::{CameraModel, KannalaBrandt, Pinhole};

/// ROS 2 type name of the camera-info schema.
pub const CAMERA_INFO_SCHEMA_NAME: &str = "sensor_msgs/msg/CameraInfo";
/// `sensor_msgs/msg/CameraInfo` with its dependencies, in the concatenated form of ROS 2 bags.
pub const CAMERA_INFO_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
",
    header_definitions!(),
    "\
================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
"
);

/// The topic a ROS driver publishes an image topic's camera info on: the image topic's last
/// name replaced by `camera_info`.
pub fn camera_info_topic(image_topic: &str) -> String {
    match image_topic.rsplit_once('/') {
        Some((namespace, _)) => format!("{namespace}/camera_info"),
        None => "camera_info".to_owned(),
    }
}

/// Decode a CDR `sensor_msgs/msg/CameraInfo` into the camera model it describes.
pub fn decode_camera_info(data: &[u8]) -> Result<CameraModel, String> {
    let mut cdr = CdrReader::new(data)?;
    cdr.header()?;
    let height = cdr.u32()?;
    let width = cdr.u32()?;
    let model = cdr.string("distortion_model")?.to_owned();
    let count = cdr.u32()? as usize;
    if count > 64 {
        return Err(format!("{count} distortion coefficients"));
    }
    let d = (0..count)
        .map(|_| cdr.f64())
        .collect::<Result<Vec<f64>, String>>()?;
    let mut k = [0.0; 9];
    for value in &mut k {
        *value = cdr.f64()?;
    }
    let coefficient = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let (fx, fy, cx, cy) = (k[0], k[4], k[2], k[5]);
    if k[1] != 0.0 {
        return Err(format!("intrinsic matrix has skew {}", k[1]));
    }
    let camera = match model.as_str() {
        "plumb_bob" | "rational_polynomial" | "" => {
            if let Some(extra) = d.iter().skip(5).find(|&&c| c != 0.0) {
                return Err(format!(
                    "`{model}` coefficient {extra} beyond k3 is not modelled (Brown–Conrady k1, k2, p1, p2, k3)"
                ));
            }
            CameraModel::Pinhole(Pinhole {
                width,
                height,
                fx,
                fy,
                cx,
                cy,
                k1: coefficient(0),
                k2: coefficient(1),
                p1: coefficient(2),
                p2: coefficient(3),
                k3: coefficient(4),
            })
        }
        "equidistant" => CameraModel::KannalaBrandt(KannalaBrandt {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            k1: coefficient(0),
            k2: coefficient(1),
            k3: coefficient(2),
            k4: coefficient(3),
        }),
        other => return Err(format!("distortion model `{other}` is not supported")),
    };
    camera.validate().map_err(|e| e.to_string())?;
    Ok(camera)
}

/// Encode `camera` as a CDR `sensor_msgs/msg/CameraInfo` into `out` (cleared first): no
/// rectification (`r` identity, `p` = `[k | 0]`), no binning, the full image as region.
pub fn encode_camera_info(
    out: &mut Vec<u8>,
    stamp_ns: u64,
    frame_id: &str,
    camera: &CameraModel,
) -> Result<(), String> {
    out.clear();
    let (model, width, height, [fx, fy, cx, cy], d): (_, _, _, _, Vec<f64>) = match camera {
        CameraModel::Pinhole(c) => (
            "plumb_bob",
            c.width,
            c.height,
            [c.fx, c.fy, c.cx, c.cy],
            vec![c.k1, c.k2, c.p1, c.p2, c.k3],
        ),
        CameraModel::KannalaBrandt(c) => (
            "equidistant",
            c.width,
            c.height,
            [c.fx, c.fy, c.cx, c.cy],
            vec![c.k1, c.k2, c.k3, c.k4],
        ),
    };
    let mut cdr = CdrWriter::new(out);
    cdr.header(stamp_ns, frame_id)?;
    cdr.u32(height);
    cdr.u32(width);
    cdr.string(model)?;
    cdr.u32(d.len() as u32);
    for value in d {
        cdr.f64(value);
    }
    let k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0];
    let r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    let p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0];
    for value in k.into_iter().chain(r).chain(p) {
        cdr.f64(value);
    }
    cdr.u32(0);
    cdr.u32(0);
    for value in [0, 0, height, width] {
        cdr.u32(value);
    }
    cdr.u8(0);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 640,
            height: 480,
            fx: 615.5,
            fy: 614.25,
            cx: 321.75,
            cy: 238.5,
            k1: 0.125,
            k2: -0.25,
            p1: 0.001,
            p2: -0.002,
            k3: 0.0625,
        })
    }

    #[test]
    fn camera_info_round_trips_both_models() {
        let fisheye = CameraModel::KannalaBrandt(KannalaBrandt {
            width: 1280,
            height: 1024,
            fx: 330.0,
            fy: 331.0,
            cx: 640.5,
            cy: 511.5,
            k1: 0.01,
            k2: -0.002,
            k3: 0.0003,
            k4: -0.00004,
        });
        let mut bytes = Vec::new();
        for camera in [pinhole(), fisheye] {
            encode_camera_info(&mut bytes, 1_700_000_000_123_456_789, "color", &camera).unwrap();
            assert_eq!(decode_camera_info(&bytes).unwrap(), camera);
        }
    }

    /// The layout ROS 2 writes, checked byte by byte at the alignment that trips hand-written
    /// CDR: the `d` sequence's doubles start 8-aligned after its u32 length.
    #[test]
    fn camera_info_layout_is_ros_cdr() {
        let mut bytes = Vec::new();
        encode_camera_info(&mut bytes, 0, "ab", &pinhole()).unwrap();
        // Body offsets: sec 0, nanosec 4 | frame_id length 8, "ab\0" 12, pad 1 | height 16,
        // width 20 | model length 24, "plumb_bob\0" 28, pad 2 | d length 40, pad 4 | d 48.
        let body = &bytes[4..];
        assert_eq!(&body[24..28], &10u32.to_le_bytes());
        assert_eq!(&body[28..37], b"plumb_bob");
        assert_eq!(&body[40..44], &5u32.to_le_bytes());
        assert_eq!(&body[48..56], &0.125f64.to_le_bytes());
        // 5 d + 9 k + 9 r + 12 p doubles, binning 2 × u32, roi 4 × u32 + bool.
        assert_eq!(body.len(), 48 + 35 * 8 + 8 + 16 + 1);
    }

    #[test]
    fn camera_info_refuses_what_it_cannot_model() {
        let mut bytes = Vec::new();
        encode_camera_info(&mut bytes, 0, "c", &pinhole()).unwrap();
        let model_at = 4 + 28;
        let mut unknown = bytes.clone();
        unknown[model_at..model_at + 9].copy_from_slice(b"plumb_rob");
        assert!(
            decode_camera_info(&unknown)
                .unwrap_err()
                .contains("plumb_rob")
        );
        assert!(decode_camera_info(&bytes[..60]).is_err());
        assert_eq!(
            camera_info_topic("/camera/color/image_raw"),
            "/camera/color/camera_info"
        );
    }
}

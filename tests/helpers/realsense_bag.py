#!/usr/bin/env python3
"""Write a RealSense-style ROS 2 bag from a relight recording, with the reference PyPI writer.

Usage: python3 tests/helpers/realsense_bag.py IN.mcap OUT.mcap [--depth 16UC1|32FC1] [--frames N]
                                             [--compressed-colour none|also|only]

The bag looks as `ros2 bag record` of the `realsense2_camera` driver leaves it, not as relight
writes: `mcap-ros2-support`'s writer, MCAP sequence 0 on every message, host log times in 2023,
`header.stamp` the driver's clock, no relight metadata. Its topics:
  /camera/color/image_raw        sensor_msgs/msg/Image, bgr8
  /camera/depth/image_rect_raw   sensor_msgs/msg/Image, 16UC1 millimetres or 32FC1 metres (NaN
                                 where invalid)
  /camera/color/camera_info      sensor_msgs/msg/CameraInfo, plumb_bob, from the recording's
  /camera/depth/camera_info      relight.calibration (the depth is registered to colour)
  /camera/imu                    a topic relight does not read (std_msgs/msg/String here)
  /camera/color/image_raw/compressed
                                 sensor_msgs/msg/CompressedImage, PNG, with --compressed-colour
                                 also (beside the raw topic, as image_transport records both)
                                 or only (instead of it)

Prints one JSON object: {"color": N, "depth": N} messages written.
Exit status 3 (and a message naming the pip command) when a package is missing.
"""

import argparse
import json
import math
import struct
import sys
import tomllib
import zlib

PIP_COMMAND = "python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'"

try:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from mcap_ros2.writer import Writer
except ImportError as error:
    print(
        f"realsense_bag.py: missing Python package ({error}); install with: {PIP_COMMAND}",
        file=sys.stderr,
    )
    sys.exit(3)

TIME_DEFS = """
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""

IMAGE = """std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data""" + TIME_DEFS

CAMERA_INFO = """std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi""" + TIME_DEFS + """================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
"""

COMPRESSED_IMAGE = """std_msgs/Header header
string format
uint8[] data""" + TIME_DEFS

# Where a 2023 host clock would put the recording's first message.
HOST_EPOCH_NS = 1_690_000_000_000_000_000


def header(stamp_ns: int, frame_id: str) -> dict:
    return {
        "stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
        "frame_id": frame_id,
    }


def camera_info(camera: dict, stamp_ns: int, frame_id: str) -> dict:
    fx, fy, cx, cy = camera["fx"], camera["fy"], camera["cx"], camera["cy"]
    return {
        "header": header(stamp_ns, frame_id),
        "height": camera["height"],
        "width": camera["width"],
        "distortion_model": "plumb_bob",
        "d": [camera.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")],
        "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def bgr8(message) -> bytes:
    rgb = bytes(message.data)
    out = bytearray(len(rgb))
    out[0::3], out[1::3], out[2::3] = rgb[2::3], rgb[1::3], rgb[0::3]
    return bytes(out)


def png_rgb8(width: int, height: int, rgb: bytes) -> bytes:
    """A PNG of 8-bit RGB pixels (no filter), as cv::imencode would make for image_transport."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))
    stride = width * 3
    raw = b"".join(b"\x00" + rgb[y * stride:(y + 1) * stride] for y in range(height))
    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


def depth_32fc1(message) -> bytes:
    millimetres = struct.unpack(f"<{len(message.data) // 2}H", bytes(message.data))
    metres = [mm / 1000.0 if mm else math.nan for mm in millimetres]
    return struct.pack(f"<{len(metres)}f", *metres)


def main() -> dict:
    parser = argparse.ArgumentParser()
    parser.add_argument("input")
    parser.add_argument("output")
    parser.add_argument("--depth", choices=["16UC1", "32FC1"], default="16UC1")
    parser.add_argument("--frames", type=int, default=1 << 30)
    parser.add_argument("--compressed-colour", choices=["none", "also", "only"], default="none")
    args = parser.parse_args()

    written = {"color": 0, "depth": 0}
    with open(args.input, "rb") as source, open(args.output, "wb") as sink:
        reader = make_reader(source, decoder_factories=[DecoderFactory()])
        calibration = next(
            tomllib.loads(record.metadata["toml"])
            for record in reader.iter_metadata()
            if record.name == "relight.calibration"
        )
        writer = Writer(sink)
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        string_schema = writer.register_msgdef("std_msgs/msg/String", "string data\n")
        compressed_schema = writer.register_msgdef(
            "sensor_msgs/msg/CompressedImage", COMPRESSED_IMAGE)
        origin = None
        infos_written = False
        for _schema, channel, message, decoded in reader.iter_decoded_messages(
            topics=["/color", "/depth"]
        ):
            if origin is None:
                origin = message.log_time
            log_time = HOST_EPOCH_NS + message.log_time - origin
            stamp = log_time - 2_000_000
            if not infos_written:
                for name, frame in (("color", "camera_color_optical_frame"),
                                    ("depth", "camera_depth_optical_frame")):
                    camera = calibration.get(name) or calibration["color"]
                    writer.write_message(
                        f"/camera/{name}/camera_info", info_schema,
                        camera_info(camera, stamp, frame), log_time, log_time)
                writer.write_message("/camera/imu", string_schema, {"data": "imu"},
                                     log_time, log_time)
                infos_written = True
            kind = channel.topic.lstrip("/")
            if written[kind] >= args.frames:
                continue
            if kind == "color" and args.compressed_colour != "none":
                writer.write_message("/camera/color/image_raw/compressed", compressed_schema, {
                    "header": header(stamp, "camera_color_optical_frame"),
                    "format": "rgb8; png compressed rgb8",
                    "data": png_rgb8(decoded.width, decoded.height, bytes(decoded.data)),
                }, log_time, log_time)
                if args.compressed_colour == "only":
                    written[kind] += 1
                    continue
            if kind == "color":
                topic, frame, encoding = ("/camera/color/image_raw",
                                          "camera_color_optical_frame", "bgr8")
                data = bgr8(decoded)
            elif args.depth == "16UC1":
                topic, frame, encoding = ("/camera/depth/image_rect_raw",
                                          "camera_depth_optical_frame", "16UC1")
                data = bytes(decoded.data)
            else:
                topic, frame, encoding = ("/camera/depth/image_rect_raw",
                                          "camera_depth_optical_frame", "32FC1")
                data = depth_32fc1(decoded)
            bytes_per_pixel = len(data) // (decoded.width * decoded.height)
            writer.write_message(topic, image_schema, {
                "header": header(stamp, frame),
                "height": decoded.height,
                "width": decoded.width,
                "encoding": encoding,
                "is_bigendian": 0,
                "step": decoded.width * bytes_per_pixel,
                "data": data,
            }, log_time, log_time)
            written[kind] += 1
        writer.finish()
    return written


if __name__ == "__main__":
    print(json.dumps(main()))

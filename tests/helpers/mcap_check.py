#!/usr/bin/env python3
"""Open a relight recording with the reference PyPI tooling and print what it sees as JSON.

Usage: python3 tests/helpers/mcap_check.py FILE.mcap

Proves that a recording is readable without relight: the `mcap` package parses the file
(validating chunk CRCs) and `mcap-ros2-support` decodes every CDR channel (images, camera info,
relight_msgs, TF) from the schema text stored in the file. JSON channels (format 1) are parsed
with the standard library.

Prints one JSON object:
  library, profile                  from the header record
  channels: [{topic, message_encoding, schema_name, schema_encoding, message_count}]
  message_count                     total over all channels (from iterating, not statistics)
  statistics_message_count          from the summary section (null if there is none)
  metadata: {name: {key: value}}
  attachments: [{name, media_type, size}]
  images: {topic: {width, height, encoding, step, is_bigendian, frame_id, stamp_ns, data_len}}
          (the first message of each sensor_msgs/msg/Image channel)
  messages: {topic: the first message of each CDR channel as a JSON object, byte arrays
             given as their length, times (sec, nanosec) as integer nanoseconds}
  json: {topic: first message of each JSON channel, parsed}

Exit status 3 (and a message naming the pip command) when a package is missing.
"""

import json
import sys

PIP_COMMAND = "python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'"

try:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
except ImportError as error:
    print(
        f"mcap_check.py: missing Python package ({error}); install with: {PIP_COMMAND}",
        file=sys.stderr,
    )
    sys.exit(3)


def plain(value):
    """A decoded ROS message as JSON-able values."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return {"bytes": len(value)}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    slots = getattr(type(value), "__slots__", None)
    if slots is not None:
        out = {name: plain(getattr(value, name)) for name in slots}
        if set(out) == {"sec", "nanosec"}:
            return out["sec"] * 1_000_000_000 + out["nanosec"]
        return out
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def main(path: str) -> dict:
    factory = DecoderFactory()
    decoders = {}
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
        counts = {}
        channels = {}
        images = {}
        decoded_messages = {}
        json_messages = {}
        for schema, channel, message in reader.iter_messages():
            channels[channel.id] = (schema, channel)
            counts[channel.id] = counts.get(channel.id, 0) + 1
            topic = channel.topic
            if channel.message_encoding == "cdr" and topic not in decoded_messages:
                if channel.id not in decoders:
                    decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
                decoded = decoders[channel.id](message.data)
                decoded_messages[topic] = plain(decoded)
                if schema.name != "sensor_msgs/msg/Image":
                    continue
                image = decoded
                stamp = image.header.stamp
                images[topic] = {
                    "width": image.width,
                    "height": image.height,
                    "encoding": image.encoding,
                    "step": image.step,
                    "is_bigendian": image.is_bigendian,
                    "frame_id": image.header.frame_id,
                    "stamp_ns": stamp.sec * 1_000_000_000 + stamp.nanosec,
                    "data_len": len(image.data),
                }
            elif channel.message_encoding == "json" and topic not in json_messages:
                json_messages[topic] = json.loads(message.data)

        # Channels without messages are listed from the summary when there is one.
        if summary is not None:
            for channel_id, channel in summary.channels.items():
                if channel_id not in channels:
                    channels[channel_id] = (summary.schemas.get(channel.schema_id), channel)

        stream.seek(0)
        reader = make_reader(stream)
        metadata = {record.name: dict(record.metadata) for record in reader.iter_metadata()}
        stream.seek(0)
        reader = make_reader(stream)
        attachments = [
            {"name": a.name, "media_type": a.media_type, "size": len(a.data)}
            for a in reader.iter_attachments()
        ]

    channel_rows = []
    for channel_id, (schema, channel) in sorted(channels.items()):
        channel_rows.append(
            {
                "topic": channel.topic,
                "message_encoding": channel.message_encoding,
                "schema_name": schema.name if schema is not None else None,
                "schema_encoding": schema.encoding if schema is not None else None,
                "message_count": counts.get(channel_id, 0),
            }
        )
    stats = summary.statistics if summary is not None else None
    return {
        "library": header.library,
        "profile": header.profile,
        "channels": channel_rows,
        "message_count": sum(counts.values()),
        "statistics_message_count": stats.message_count if stats is not None else None,
        "metadata": metadata,
        "attachments": attachments,
        "images": images,
        "messages": decoded_messages,
        "json": json_messages,
    }


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    print(json.dumps(main(sys.argv[1]), indent=2, sort_keys=True))

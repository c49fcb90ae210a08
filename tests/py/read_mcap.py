"""Independent reader for the round-trip tests: the official Python `mcap`
library with its ROS 1 / ROS 2 decoders. Reads every record, checks chunk and
data CRCs, decodes every ROS message, and prints counts as JSON."""
import json
import sys

from mcap.reader import make_reader
from mcap.records import Attachment, Chunk, Metadata
from mcap.stream_reader import StreamReader
from mcap_ros1.decoder import DecoderFactory as Ros1Decoders
from mcap_ros2.decoder import DecoderFactory as Ros2Decoders

path = sys.argv[1]
report = {"topics": {}, "decoded": 0, "attachments": 0, "metadata": {}, "chunks": 0, "images": {}}

# Record level, CRCs validated.
with open(path, "rb") as f:
    for record in StreamReader(f, skip_magic=False, emit_chunks=True, validate_crcs=True).records:
        if isinstance(record, Chunk):
            report["chunks"] += 1
with open(path, "rb") as f:
    for record in StreamReader(f, validate_crcs=True).records:
        if isinstance(record, Attachment):
            report["attachments"] += 1
        elif isinstance(record, Metadata):
            report["metadata"][record.name] = record.metadata

# Message level: every ROS message must decode. Decoders are chosen per channel, not per
# topic: one topic may be carried by channels of several encodings (ROS 2 and Foxglove).
factories = [Ros1Decoders(), Ros2Decoders()]
decoders = {}
with open(path, "rb") as f:
    reader = make_reader(f)
    for schema, channel, message in reader.iter_messages():
        topic = report["topics"].setdefault(channel.topic, {"messages": 0, "encoding": channel.message_encoding,
                                                            "schema": schema.name if schema else ""})
        topic["messages"] += 1
        if channel.message_encoding not in ("cdr", "ros1"):
            continue
        if channel.id not in decoders:
            found = [d for d in (fac.decoder_for(channel.message_encoding, schema) for fac in factories) if d]
            if not found:
                raise SystemExit(f"no decoder for {channel.topic} ({channel.message_encoding})")
            decoders[channel.id] = found[0]
        decoded = decoders[channel.id](message.data)
        report["decoded"] += 1
        if hasattr(decoded, "encoding") and hasattr(decoded, "step"):
            report["images"].setdefault(channel.topic, [decoded.height, decoded.width, decoded.encoding, decoded.step,
                                                        len(decoded.data)])
print(json.dumps(report))

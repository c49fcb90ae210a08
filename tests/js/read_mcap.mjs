// Independent reader for the round-trip tests, built from Foxglove's own
// libraries: @mcap/core reads the records (CRCs checked), the ROS 1 / ROS 2
// deserializers and protobufjs decode every message. Prints counts as JSON;
// exits non-zero if any message fails to decode.
import { readFileSync } from "node:fs";
import { McapStreamReader } from "@mcap/core";
import { parse as parseMsgDef } from "@foxglove/rosmsg";
import { MessageReader as Ros1Reader } from "@foxglove/rosmsg-serialization";
import { MessageReader as Ros2Reader } from "@foxglove/rosmsg2-serialization";
import { decompress as zstdDecompress } from "fzstd";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";

const path = process.argv[2];
const reader = new McapStreamReader({
  validateCrcs: true,
  decompressHandlers: { zstd: (data, size) => zstdDecompress(data, new Uint8Array(Number(size))) },
});
reader.append(readFileSync(path));

const schemas = new Map();
const channels = new Map();
const decoders = new Map();
const report = { topics: {}, decoded: 0, failures: [], images: {}, clouds: {}, values: {} };

// Range of pixel values per image topic ([min, max] of 32FC1 floats, sorted distinct bytes
// of mono8), so tests can check units (e.g. a probability stays in 0..1).
function trackValues(topic, msg) {
  const bytes = msg.data instanceof Uint8Array ? msg.data : new Uint8Array(msg.data);
  if (msg.encoding === "32FC1") {
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    let [lo, hi] = report.values[topic] ?? [Infinity, -Infinity];
    for (let i = 0; i + 4 <= bytes.length; i += 4) {
      const v = view.getFloat32(i, true);
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    report.values[topic] = [lo, hi];
  } else if (msg.encoding === "mono8") {
    const seen = new Set(report.values[topic] ?? []);
    for (const b of bytes) seen.add(b);
    report.values[topic] = [...seen].sort((a, b) => a - b);
  }
}

function decoderFor(channel) {
  if (decoders.has(channel.id)) return decoders.get(channel.id);
  const schema = schemas.get(channel.schemaId);
  let decode;
  if (channel.messageEncoding === "cdr" || channel.messageEncoding === "ros1") {
    const text = new TextDecoder().decode(schema.data);
    const defs = parseMsgDef(text, { ros2: channel.messageEncoding === "cdr" });
    const r = channel.messageEncoding === "cdr" ? new Ros2Reader(defs) : new Ros1Reader(defs);
    decode = (data) => r.readMessage(data);
  } else if (channel.messageEncoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(schema.data);
    const type = protobuf.Root.fromDescriptor(set).lookupType(schema.name);
    decode = (data) => type.toObject(type.decode(data), { longs: Number });
  } else if (channel.messageEncoding === "json") {
    decode = (data) => JSON.parse(new TextDecoder().decode(data));
  } else {
    decode = null;
  }
  decoders.set(channel.id, decode);
  return decode;
}

for (let record; (record = reader.nextRecord()); ) {
  if (record.type === "Schema") schemas.set(record.id, record);
  else if (record.type === "Channel") channels.set(record.id, record);
  else if (record.type === "Message") {
    const channel = channels.get(record.channelId);
    const t = (report.topics[channel.topic] ??= { messages: 0, encoding: channel.messageEncoding });
    t.messages += 1;
    const decode = decoderFor(channel);
    if (!decode) continue;
    try {
      const msg = decode(record.data);
      report.decoded += 1;
      if (msg.encoding !== undefined && msg.step !== undefined) {
        report.images[channel.topic] ??= [msg.height, msg.width, msg.encoding, msg.step, msg.data.length];
        trackValues(channel.topic, msg);
      }
      if (msg.fields !== undefined && msg.data !== undefined) {
        report.clouds[channel.topic] ??= msg.fields.map((f) => f.name);
        const stride = msg.point_step ?? msg.point_stride ?? msg.pointStride;
        if (!stride || msg.data.length % stride !== 0) {
          report.failures.push(`${channel.topic} @ ${record.logTime}: ${msg.data.length} bytes of points with stride ${stride}`);
        }
      }
    } catch (e) {
      report.failures.push(`${channel.topic} @ ${record.logTime}: ${e.message}`);
    }
  }
}
if (!reader.done()) report.failures.push("file did not end cleanly");
console.log(JSON.stringify(report));
process.exit(report.failures.length === 0 ? 0 : 1);

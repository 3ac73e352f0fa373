// Decode every message of an MCAP file with the standard Node reader and decoders only:
// @mcap/core (the reader), @mcap/support (decompression, protobuf schemas from a
// FileDescriptorSet) and protobufjs; JSON messages with JSON.parse, checked for the fields
// their embedded JSON Schema requires. No sinewatch code. Prints, as JSON, per channel its
// encodings and each decoded message, so a test can compare them with what was sent.
//
// Usage: node decode_mcap.mjs FILE.mcap
import { readFile } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { loadDecompressHandlers, protobufFromBinaryDescriptor } from "@mcap/support";

const bytes = new Uint8Array(await readFile(process.argv[2]));
const readable = {
  size: async () => BigInt(bytes.byteLength),
  read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)),
};
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: await loadDecompressHandlers() });

const decoders = new Map(); // channel id -> (data) => object
function decoderFor(channel) {
  const schema = reader.schemasById.get(channel.schemaId);
  if (channel.messageEncoding === "protobuf" && schema.encoding === "protobuf") {
    const type = protobufFromBinaryDescriptor(schema.data).lookupType(schema.name);
    // longs and bytes as strings: exact in JSON (a JavaScript number is not, past 2^53)
    return (data) => {
      const msg = type.toObject(type.decode(data), { longs: String, bytes: String, defaults: true });
      if (msg.raw !== undefined) msg.raw = Buffer.from(msg.raw, "base64").toString("hex");
      return msg;
    };
  }
  if (channel.messageEncoding === "json" && schema.encoding === "jsonschema") {
    const required = JSON.parse(new TextDecoder().decode(schema.data)).required ?? [];
    return (data) => {
      const msg = JSON.parse(new TextDecoder().decode(data));
      const missing = required.filter((k) => !(k in msg));
      if (missing.length > 0) throw new Error(`${channel.topic}: missing ${missing} required by ${schema.name}`);
      return msg;
    };
  }
  throw new Error(`${channel.topic}: no standard decoder for ${channel.messageEncoding} / ${schema.encoding}`);
}

const channels = {};
for await (const message of reader.readMessages()) {
  const channel = reader.channelsById.get(message.channelId);
  if (!decoders.has(channel.id)) decoders.set(channel.id, decoderFor(channel));
  const schema = reader.schemasById.get(channel.schemaId);
  const out = (channels[channel.id] ??= {
    topic: channel.topic,
    message_encoding: channel.messageEncoding,
    schema_name: schema.name,
    schema_encoding: schema.encoding,
    metadata: Object.fromEntries(channel.metadata),
    messages: [],
    log_times: [],
  });
  out.messages.push(decoders.get(channel.id)(message.data));
  out.log_times.push(Number(message.logTime));
}
const counts = {};
for (const [id, n] of reader.statistics.channelMessageCounts) counts[id] = Number(n);
process.stdout.write(JSON.stringify({ channels, counts }));

// Reads a ROS 1 MCAP as Foxglove and Lichtblick do, with their npm libraries (@mcap/core's indexed
// reader, @mcap/support's decompression, @foxglove/rosmsg's parser of the stored definition and
// @foxglove/rosmsg-serialization's ROS 1 reader), and decodes every message of every channel with
// its channel's stored schema. A message decodes when the reader reads it without error and its
// definition accounts for every byte (LazyMessageReader.size equals the stored length).
//
//   node mcap_read.js FILE.mcap      -> one JSON line: profile, statistics, per topic counts, errors
"use strict";

const fs = require("fs/promises");
const { McapIndexedReader } = require("@mcap/core");
const { FileHandleReadable } = require("@mcap/nodejs");
const { loadDecompressHandlers } = require("@mcap/support");
const { parse } = require("@foxglove/rosmsg");
const { LazyMessageReader, MessageReader } = require("@foxglove/rosmsg-serialization");

const MAX_ERRORS_LISTED = 20;

function firstOf(type, msg) {
  // What a reader of the first message sees: its header, and for a cloud whether its data adds up.
  const out = {};
  if (msg && msg.header) {
    out.frame_id = msg.header.frame_id;
    out.stamp = msg.header.stamp.sec + msg.header.stamp.nsec / 1e9;
  }
  if (type === "sensor_msgs/PointCloud2") {
    out.points = msg.width * msg.height;
    out.data_adds_up = msg.data.byteLength === msg.row_step * msg.height;
  }
  if (type === "tf2_msgs/TFMessage") out.transforms = msg.transforms.length;
  return out;
}

async function main() {
  const path = process.argv[2];
  const handle = await fs.open(path, "r");
  const reader = await McapIndexedReader.Initialize({
    readable: new FileHandleReadable(handle),
    decompressHandlers: await loadDecompressHandlers(),
  });
  const topics = {};
  const errors = [];
  const decoders = new Map(); // channel id -> { full, lazy, type }
  const note = (text) => {
    if (errors.length < MAX_ERRORS_LISTED) errors.push(text);
  };
  for (const [id, channel] of reader.channelsById) {
    const schema = reader.schemasById.get(channel.schemaId);
    topics[channel.topic] = topics[channel.topic] || {
      type: schema ? schema.name : "",
      messages: 0,
      decoded: 0,
      errors: 0,
      first: null,
    };
    if (channel.messageEncoding !== "ros1" || !schema || schema.encoding !== "ros1msg") {
      note(`${channel.topic}: encoding ${channel.messageEncoding}, schema ${schema ? schema.encoding : "none"}`);
      continue;
    }
    try {
      const definitions = parse(new TextDecoder().decode(schema.data), { ros2: false });
      decoders.set(id, {
        full: new MessageReader(definitions),
        lazy: new LazyMessageReader(definitions),
        type: schema.name,
      });
    } catch (error) {
      note(`${channel.topic}: its stored definition does not parse: ${error.message}`);
    }
  }
  let errorCount = 0;
  for await (const message of reader.readMessages()) {
    const channel = reader.channelsById.get(message.channelId);
    const row = topics[channel.topic];
    row.messages += 1;
    const decoder = decoders.get(message.channelId);
    if (!decoder) {
      row.errors += 1;
      errorCount += 1;
      continue;
    }
    try {
      const msg = decoder.full.readMessage(message.data);
      const size = decoder.lazy.size(message.data);
      if (size !== message.data.byteLength) {
        throw new Error(`the definition reads ${size} of its ${message.data.byteLength} bytes`);
      }
      row.decoded += 1;
      if (row.first === null) row.first = firstOf(decoder.type, msg);
    } catch (error) {
      row.errors += 1;
      errorCount += 1;
      note(`${channel.topic}: ${error.message}`);
    }
  }
  await handle.close();
  const stats = reader.statistics;
  const report = {
    profile: reader.header.profile,
    library: reader.header.library,
    message_count: stats ? Number(stats.messageCount) : null,
    topics,
    decode_errors: errorCount,
    errors,
  };
  process.stdout.write(JSON.stringify(report) + "\n");
}

main().catch((error) => {
  process.stderr.write(`${error.stack || error}\n`);
  process.exit(1);
});

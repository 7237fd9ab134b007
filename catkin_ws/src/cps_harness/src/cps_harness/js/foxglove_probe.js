// A Foxglove viewer's view of a WebSocket endpoint, through the npm @foxglove/ws-protocol client
// (test support: cps_harness.foxglove_probe runs it with node). Lists the advertised channels,
// subscribes those asked for, decodes every message with the schema its channel advertised
// (protobuf: the FileDescriptorSet the channel carries, via protobufjs; json: JSON.parse) and prints
// one JSON report on stdout. With --stall it subscribes, then never reads the socket again.
//
// usage: node foxglove_probe.js URL SECONDS TOPICS_JSON [--stall] [--call SERVICE REQUEST_JSON]...
//   TOPICS_JSON: a JSON list of topics to subscribe ([] : every advertised channel)
//   --call: call the advertised SERVICE with REQUEST_JSON (json encoding); its response or failure
//   is in the report's `calls`, in the order given
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");
const protobuf = require("protobufjs");
const descriptor = require("protobufjs/ext/descriptor");

const [url, secondsText, topicsJson, ...flags] = process.argv.slice(2);
const wanted = JSON.parse(topicsJson || "[]");
const stall = flags.includes("--stall");
const calls = [];
flags.forEach((flag, i) => { if (flag === "--call") calls.push({ service: flags[i + 1], request: flags[i + 2] }); });
// The foxglove-sdk server speaks the ws-protocol spec under the subprotocol foxglove.sdk.v1; the
// client takes whatever subprotocol its WebSocket negotiated (ws-protocol PR 916).
const ws = new WebSocket(url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const report = { url, server: null, channels: [], services: [], calls: [], messages: {}, decode_errors: {}, samples: {}, errors: [] };
const decoders = new Map(); // subscription id -> {topic, decode}

function decoderOf(channel) {
  if (channel.encoding === "protobuf" && channel.schemaEncoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(Buffer.from(channel.schema, "base64"));
    const type = protobuf.Root.fromDescriptor(set).lookupType(channel.schemaName);
    // defaults: proto3 leaves a field at its default off the wire, and toObject leaves it out too
    // (the map's first message, published before any cloud, has no points: `data` was undefined)
    return (bytes) => type.toObject(type.decode(bytes), { longs: Number, bytes: Buffer, defaults: true });
  }
  if (channel.encoding === "json") {
    return (bytes) => JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(bytes));
  }
  throw new Error(`no decoder for encoding ${channel.encoding} / schema ${channel.schemaEncoding}`);
}

// What a decoded message says, in a few numbers a test can check.
function summary(schemaName, m) {
  switch (schemaName) {
    case "foxglove.PointCloud":
      return { frame_id: m.frame_id, points: m.point_stride ? m.data.length / m.point_stride : 0,
               whole: m.point_stride > 0 && m.data.length % m.point_stride === 0, fields: (m.fields || []).map((f) => f.name) };
    case "foxglove.CompressedImage":
      return { format: m.format, bytes: m.data.length, jpeg_soi: m.data.length > 1 && m.data[0] === 0xff && m.data[1] === 0xd8 };
    case "foxglove.PoseInFrame":
      return { frame_id: m.frame_id, x: (m.pose && m.pose.position && m.pose.position.x) || 0 };
    case "foxglove.SceneUpdate":
      return { entities: (m.entities || []).map((e) => e.id), cubes: (m.entities || []).reduce((n, e) => n + (e.cubes || []).length, 0) };
    case "foxglove.FrameTransforms":
      return { transforms: (m.transforms || []).map((t) => `${t.parent_frame_id}->${t.child_frame_id}`) };
    default:
      return { keys: Object.keys(m) };
  }
}

client.on("serverInfo", (info) => { report.server = { name: info.name, capabilities: info.capabilities }; });
client.on("error", (err) => report.errors.push(String(err)));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    report.channels.push({ topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName, schemaEncoding: ch.schemaEncoding });
    if (wanted.length && !wanted.includes(ch.topic)) continue;
    let decode;
    try {
      decode = decoderOf(ch);
    } catch (err) {
      report.decode_errors[ch.topic] = [String(err)];
      continue;
    }
    decoders.set(client.subscribe(ch.id), { topic: ch.topic, schemaName: ch.schemaName, decode });
  }
  if (stall && decoders.size) {
    setTimeout(() => {
      if (ws._socket) ws._socket.pause();
      process.stderr.write("paused\n"); // the caller waits for this line, not for a time
    }, 200);
  }
});
client.on("advertiseServices", (services) => {
  const encoder = new TextEncoder();
  for (const service of services) report.services.push(service.name);
  calls.forEach((call, callId) => {
    const service = services.find((s) => s.name === call.service);
    if (!service) return;
    report.calls[callId] = { service: call.service, request: call.request, response: null, failure: null };
    client.sendServiceCallRequest({ serviceId: service.id, callId, encoding: "json", data: encoder.encode(call.request) });
  });
});
client.on("serviceCallResponse", ({ callId, data }) => {
  report.calls[callId].response = JSON.parse(new TextDecoder().decode(data));
});
client.on("serviceCallFailure", ({ callId, message }) => {
  report.calls[callId].failure = message;
});
client.on("message", ({ subscriptionId, data }) => {
  const d = decoders.get(subscriptionId);
  if (!d) return;
  report.messages[d.topic] = (report.messages[d.topic] || 0) + 1;
  try {
    const m = d.decode(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    report.samples[d.topic] = summary(d.schemaName, m);
  } catch (err) {
    (report.decode_errors[d.topic] = report.decode_errors[d.topic] || []).push(String(err));
  }
});
ws.on("error", (err) => report.errors.push(`websocket: ${err.message}`));
setTimeout(() => {
  process.stdout.write(JSON.stringify(report) + "\n");
  process.exit(0);
}, Number(secondsText) * 1000);

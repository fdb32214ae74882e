// Connect to a Foxglove WebSocket server with the official client, subscribe to the given topics and print the
// first message of each, decoded with the schema the server advertised (protobuf FileDescriptorSet or JSON).
// foxglove-sdk servers speak the protocol under the subprotocol "foxglove.sdk.v1" (the Foxglove app offers it);
// this client offers it next to the original "foxglove.websocket.v1".
// Usage: node check.mjs ws://127.0.0.1:8765 /scan /map /tf   (exit 1 when a topic sends nothing within 60 s)
import wsProtocol from "@foxglove/ws-protocol";
import protobufjs from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
const [url, ...topics] = process.argv.slice(2);
const wanted = new Set(topics);
const decoders = new Map(); // subscription id -> {topic, schemaName, encoding, decode}
const done = new Map();

function decoderFor(channel) {
  if (channel.encoding === "protobuf") {
    const fds = descriptor.FileDescriptorSet.decode(Buffer.from(channel.schema, "base64"));
    const type = protobufjs.Root.fromDescriptor(fds).lookupType(channel.schemaName);
    return (bytes) => type.toObject(type.decode(bytes), { longs: Number, bytes: Array, defaults: true });
  }
  if (channel.encoding === "json") {
    return (bytes) => JSON.parse(new TextDecoder().decode(bytes));
  }
  throw new Error(`${channel.topic}: unsupported encoding ${channel.encoding}`);
}

const client = new FoxgloveClient({ ws: new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"]) });
const timer = setTimeout(() => {
  const missing = [...wanted].filter((t) => !done.has(t));
  console.error(`no message within 60 s on: ${missing.join(", ")}`);
  process.exit(1);
}, 60000);

client.on("error", (err) => {
  console.error(`client error: ${err}`);
  process.exit(1);
});
client.on("advertise", (channels) => {
  for (const channel of channels) {
    if (!wanted.has(channel.topic) || [...decoders.values()].some((d) => d.topic === channel.topic)) continue;
    const decode = decoderFor(channel);
    const id = client.subscribe(channel.id);
    decoders.set(id, { topic: channel.topic, schemaName: channel.schemaName, encoding: channel.encoding, decode });
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const d = decoders.get(subscriptionId);
  if (!d || done.has(d.topic)) return;
  const message = d.decode(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
  done.set(d.topic, true);
  // long arrays (ranges, grid cells) are printed as their length and first values
  const brief = (key, value) =>
    Array.isArray(value) && value.length > 8 ? { length: value.length, head: value.slice(0, 8) } : value;
  const line = JSON.stringify({ topic: d.topic, schemaName: d.schemaName, encoding: d.encoding, message }, brief);
  process.stdout.write(line + "\n");
  if (done.size === wanted.size) {
    clearTimeout(timer);
    client.close();
    process.stdout.write("", () => process.exit(0));
  }
});

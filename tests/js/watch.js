// A Foxglove viewer written against @foxglove/ws-protocol's own FoxgloveClient: connect with the
// subprotocol given, subscribe to every channel advertised, collect what arrives.
// Usage: node watch.js ws://127.0.0.1:PORT SUBPROTOCOL SECONDS  ->  JSON on stdout:
// {serverInfo, channels: [{id, topic, encoding, schemaName}], messages: {topic: [base64, ...]}}
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, subprotocol, seconds] = process.argv.slice(2);
const client = new FoxgloveClient({ ws: new WebSocket(url, [subprotocol]) });
const out = { serverInfo: null, channels: [], messages: {} };
const topicOf = new Map();

client.on("serverInfo", (info) => { out.serverInfo = info; });
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels.push({ id: ch.id, topic: ch.topic, encoding: ch.encoding,
                        schemaName: ch.schemaName });
    topicOf.set(client.subscribe(ch.id), ch.topic);
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const topic = topicOf.get(subscriptionId);
  (out.messages[topic] ??= []).push(Buffer.from(data.buffer, data.byteOffset,
                                                data.byteLength).toString("base64"));
});
client.on("error", (err) => { console.error(String(err)); process.exit(2); });
client.on("close", (ev) => { if (!out.serverInfo) { console.error("closed", ev.code); process.exit(3); } });
setTimeout(() => { console.log(JSON.stringify(out)); client.close(); process.exit(0); },
           Number(seconds) * 1000);

// A Foxglove WebSocket client built on the official client library (@foxglove/ws-protocol,
// FoxgloveClient). It offers the subprotocols viewers offer: "foxglove.sdk.v1" (the only one
// foxglove-sdk's server accepts; the same protocol under a new name) and the library's own
// "foxglove.websocket.v1" (older servers). It subscribes to every channel the server advertises
// (0.2 s after the advertisements pause) and prints, one JSON object per line,
//   {"serverInfo": {...}}                      the server's info message
//   {"advertise": [channel, ...]}              each advertise message (topic, encoding, schema...)
//   {"message": {"topic", "logTime", "data"}}  the first message of each channel (data in base64)
// A subscription the server refuses ("Unknown channel ID") is sent again.
// It connects again every 0.3 s until the server listens; it exits 0 once every topic named in
// --topics (comma-separated; default: every advertised channel) has delivered a message, 1 after
// --timeout seconds with what is missing on stderr.
//
//   node client.mjs ws://127.0.0.1:8765 [--topics /tf,/scene] [--timeout 30]
import wsProtocol from "@foxglove/ws-protocol"; // the CommonJS build (the ESM one has extensionless imports)
const { FoxgloveClient } = wsProtocol;
import WebSocket from "ws";

const args = process.argv.slice(2);
const url = args[0];
const option = (name, fallback) => {
  const i = args.indexOf(name);
  return i >= 0 ? args[i + 1] : fallback;
};
const wanted = option("--topics", "").split(",").filter((t) => t);
const timeoutS = Number(option("--timeout", "30"));
if (!url || !url.startsWith("ws")) {
  console.error("usage: node client.mjs ws://HOST:PORT [--topics T1,T2] [--timeout S]");
  process.exit(2);
}

const print = (object) => process.stdout.write(JSON.stringify(object) + "\n");
const channels = new Map(); // subscription id -> channel
const advertised = new Set();
const received = new Set();
let client;

function done() {
  const topics = wanted.length ? wanted : [...advertised];
  return topics.length > 0 && topics.every((t) => received.has(t));
}

const timer = setTimeout(() => {
  const topics = wanted.length ? wanted : [...advertised];
  console.error(`timeout: no message yet on ${topics.filter((t) => !received.has(t)).join(", ") || "(no channel advertised)"}`);
  process.exit(1);
}, timeoutS * 1000);

// Until the server listens (it may start after this client), connection errors mean: try again.
function connect() {
  let opened = false;
  client = new FoxgloveClient({ ws: new WebSocket(url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
  client.on("open", () => {
    opened = true;
  });
  client.on("error", (error) => {
    if (opened) {
      console.error(`error: ${error?.message ?? error}`);
      process.exit(1);
    }
  });
  client.on("close", (event) => {
    if (!opened) {
      setTimeout(connect, 300);
      return;
    }
    console.error(`closed by the server (code ${event?.code}) before every topic arrived`);
    process.exit(1);
  });
  client.on("serverInfo", (info) => print({ serverInfo: info }));
  // Subscribe once the advertisements have paused for 0.2 s, as a viewer subscribes when a panel
  // asks: foxglove-sdk's server (0.30.3) can lose a subscription that arrives while the channel
  // it has just advertised is being registered ("attempted to subscribe to unknown channel").
  let pending = [];
  let settle;
  client.on("advertise", (newChannels) => {
    print({ advertise: newChannels });
    for (const channel of newChannels) {
      advertised.add(channel.topic);
      pending.push(channel);
    }
    clearTimeout(settle);
    settle = setTimeout(() => {
      for (const channel of pending) {
        channels.set(client.subscribe(channel.id), channel);
      }
      pending = [];
    }, 200);
  });
  // Should it still refuse one (a status "Unknown channel ID: N"), subscribe to that channel again.
  client.on("status", ({ message }) => {
    const refused = /^Unknown channel ID: (\d+)/.exec(message ?? "");
    if (!refused) {
      return;
    }
    for (const [subscriptionId, channel] of channels) {
      if (channel.id === Number(refused[1])) {
        channels.delete(subscriptionId);
        setTimeout(() => channels.set(client.subscribe(channel.id), channel), 50);
      }
    }
  });
  client.on("message", ({ subscriptionId, timestamp, data }) => {
    const channel = channels.get(subscriptionId);
    if (!channel || received.has(channel.topic)) {
      return;
    }
    received.add(channel.topic);
    const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
    print({ message: { topic: channel.topic, logTime: timestamp.toString(), data: bytes.toString("base64") } });
    if (done()) {
      clearTimeout(timer);
      process.stdout.write("", () => process.exit(0));
    }
  });
}

connect();

// Drive the real @foxglove/ws-protocol client from a test: commands in as JSON lines on stdin,
// everything the server says out as JSON lines on stdout (binary payloads in base64).
//
//   node client.js ws://127.0.0.1:8765 [subprotocol]
"use strict";

const readline = require("node:readline");
const WebSocket = require("ws");
const { FoxgloveClient } = require("@foxglove/ws-protocol");

const [url, subprotocol = FoxgloveClient.SUPPORTED_SUBPROTOCOL] = process.argv.slice(2);
const ws = new WebSocket(url, [subprotocol]);
const client = new FoxgloveClient({ ws });
const channels = new Map(); // topic -> channel
const services = new Map(); // name -> service

function emit(event, fields) {
  process.stdout.write(JSON.stringify({ event, ...fields }) + "\n");
}

function base64(view) {
  return Buffer.from(view.buffer, view.byteOffset, view.byteLength).toString("base64");
}

client.on("open", () => emit("open", { protocol: ws.protocol }));
client.on("error", (error) => emit("error", { message: String(error && error.message ? error.message : error) }));
client.on("close", (event) => emit("close", { code: event.code }));
client.on("serverInfo", (info) => emit("serverInfo", { info }));
client.on("status", (status) => emit("status", { status }));
client.on("advertise", (added) => {
  for (const channel of added) channels.set(channel.topic, channel);
  emit("advertise", { channels: added });
});
client.on("unadvertise", (ids) => {
  for (const [topic, channel] of channels) if (ids.includes(channel.id)) channels.delete(topic);
  emit("unadvertise", { channelIds: ids });
});
client.on("advertiseServices", (added) => {
  for (const service of added) services.set(service.name, service);
  emit("advertiseServices", { services: added });
});
client.on("unadvertiseServices", (ids) => emit("unadvertiseServices", { serviceIds: ids }));
client.on("message", ({ subscriptionId, timestamp, data }) =>
  emit("message", { subscriptionId, timestamp: String(timestamp), data: base64(data) }),
);
client.on("serviceCallResponse", ({ serviceId, callId, encoding, data }) =>
  emit("serviceCallResponse", { serviceId, callId, encoding, data: base64(data) }),
);
client.on("serviceCallFailure", (failure) => emit("serviceCallFailure", { failure }));
client.on("parameterValues", ({ parameters, id }) => emit("parameterValues", { parameters, id }));
client.on("time", ({ timestamp }) => emit("time", { timestamp: String(timestamp) }));

const commands = {
  subscribe({ topic }) {
    const channel = channels.get(topic);
    if (!channel) return emit("refused", { message: `no channel for ${topic}` });
    emit("subscribed", { topic, channelId: channel.id, subscriptionId: client.subscribe(channel.id) });
  },
  unsubscribe({ subscriptionId }) {
    client.unsubscribe(subscriptionId);
  },
  advertise({ topic, encoding, schemaName }) {
    emit("advertised", { topic, channelId: client.advertise({ topic, encoding, schemaName }) });
  },
  unadvertise({ channelId }) {
    client.unadvertise(channelId);
  },
  publish({ channelId, data }) {
    client.sendMessage(channelId, new Uint8Array(Buffer.from(data, "base64")));
  },
  call({ service, callId, encoding, data }) {
    const known = services.get(service);
    if (!known) return emit("refused", { message: `no service ${service}` });
    client.sendServiceCallRequest({
      serviceId: known.id,
      callId,
      encoding,
      data: new DataView(new Uint8Array(Buffer.from(data, "base64")).buffer),
    });
  },
  getParameters({ names, id }) {
    client.getParameters(names, id);
  },
  setParameters({ parameters, id }) {
    client.setParameters(parameters, id);
  },
  subscribeParameterUpdates({ names }) {
    client.subscribeParameterUpdates(names);
  },
  unsubscribeParameterUpdates({ names }) {
    client.unsubscribeParameterUpdates(names);
  },
  raw({ text, binary }) {
    ws.send(text !== undefined ? text : Buffer.from(binary, "base64"));
  },
  close() {
    client.close();
  },
};

readline.createInterface({ input: process.stdin }).on("line", (line) => {
  const command = JSON.parse(line);
  commands[command.cmd](command);
});
process.stdin.on("end", () => {
  client.close();
  setTimeout(() => process.exit(0), 100);
});

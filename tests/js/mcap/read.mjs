// Read an MCAP file as Foxglove does: @mcap/core's indexed reader, zstd chunks through
// @foxglove/wasm-zstd. Prints one JSON line: header, channels with their schemas, and message counts.
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import zstd from "@foxglove/wasm-zstd";

const [path] = process.argv.slice(2);
await zstd.isLoaded;
const file = await open(path, "r");
const { size } = await file.stat();
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buffer = new Uint8Array(Number(length));
    await file.read(buffer, 0, Number(length), Number(offset));
    return buffer;
  },
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: { zstd: (data, decompressedSize) => zstd.decompress(data, Number(decompressedSize)) },
});
const counts = {};
let first = null;
for await (const message of reader.readMessages()) {
  const topic = reader.channelsById.get(message.channelId).topic;
  counts[topic] = (counts[topic] ?? 0) + 1;
  first ??= { topic, bytes: Buffer.from(message.data).toString("base64") };
}
const channels = [...reader.channelsById.values()].map((channel) => {
  const schema = reader.schemasById.get(channel.schemaId);
  return {
    topic: channel.topic,
    messageEncoding: channel.messageEncoding,
    schema: schema && { name: schema.name, encoding: schema.encoding, data: Buffer.from(schema.data).toString() },
  };
});
console.log(
  JSON.stringify({
    profile: reader.header.profile,
    library: reader.header.library,
    channels,
    counts,
    statistics: reader.statistics && { messageCount: Number(reader.statistics.messageCount) },
    first,
  }),
);
await file.close();

// Independent check of a followbus recording: read it with the official @mcap/core stream reader
// (CRCs validated, chunks decompressed by @mcap/support), and validate every message of every
// foxglove.* channel against the JSON schema shipped in @foxglove/schemas (ajv). Prints a JSON
// summary on stdout; exit status 1 on any problem.
//
// usage: node check_mcap.mjs FILE.mcap
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";
import { isDeepStrictEqual } from "node:util";

// The packages are CommonJS: require() them rather than rely on ESM interop of named exports.
const require = createRequire(import.meta.url);
const foxglove = require("@foxglove/schemas/jsonschema");
const { McapStreamReader } = require("@mcap/core");
const { loadDecompressHandlers } = require("@mcap/support");
const Ajv = require("ajv");

const file = process.argv[2];
const reader = new McapStreamReader({ decompressHandlers: await loadDecompressHandlers(), validateCrcs: true });
reader.append(new Uint8Array(readFileSync(file)));

const ajv = new Ajv({ allErrors: true });
const official = {
  "foxglove.CompressedImage": foxglove.CompressedImage,
  "foxglove.ImageAnnotations": foxglove.ImageAnnotations,
};
const validators = Object.fromEntries(Object.entries(official).map(([name, s]) => [name, ajv.compile(s)]));

const schemas = new Map();
const channels = new Map();
const summary = { file, complete: false, channels: {}, errors: [] };
const fail = (msg) => {
  if (summary.errors.length < 50) summary.errors.push(msg);
};
const utf8 = new TextDecoder("utf-8", { fatal: true });

for (let record; (record = reader.nextRecord()); ) {
  if (record.type === "Schema") {
    schemas.set(record.id, record);
  } else if (record.type === "Channel") {
    channels.set(record.id, record);
    const schema = schemas.get(record.schemaId);
    const name = schema ? schema.name : "";
    summary.channels[record.topic] ??= { schema: name, encoding: record.messageEncoding, count: 0 };
    if (!name.startsWith("foxglove.")) continue;
    if (!(name in official)) fail(`${record.topic}: unknown Foxglove schema ${name}`);
    if (schema.encoding !== "jsonschema") fail(`${record.topic}: schema encoding ${schema.encoding}, not jsonschema`);
    if (record.messageEncoding !== "json") fail(`${record.topic}: message encoding ${record.messageEncoding}`);
    if (name in official && !isDeepStrictEqual(JSON.parse(utf8.decode(schema.data)), official[name])) {
      fail(`${record.topic}: the schema stored for ${name} differs from @foxglove/schemas`);
    }
  } else if (record.type === "Message") {
    const channel = channels.get(record.channelId);
    if (!channel) {
      fail(`message on unknown channel ${record.channelId}`);
      continue;
    }
    const entry = summary.channels[channel.topic];
    entry.count += 1;
    if (record.logTime === 0n) fail(`${channel.topic}: log_time 0`);
    const validate = validators[entry.schema];
    if (!validate) continue;
    let msg;
    try {
      msg = JSON.parse(utf8.decode(record.data));
    } catch (err) {
      fail(`${channel.topic}: not JSON (${err.message})`);
      continue;
    }
    if (!validate(msg)) {
      fail(`${channel.topic} @${record.logTime}: ${ajv.errorsText(validate.errors)}`);
      continue;
    }
    const stamp = msg.timestamp ?? msg.points?.[0]?.timestamp ?? msg.texts?.[0]?.timestamp;
    if (stamp && BigInt(stamp.sec) * 1000000000n + BigInt(stamp.nsec) !== record.logTime) {
      fail(`${channel.topic}: timestamp ${stamp.sec}.${stamp.nsec} is not the log time ${record.logTime}`);
    }
    if (entry.schema === "foxglove.CompressedImage") {
      const bytes = Buffer.from(msg.data, "base64");
      const jpeg = bytes.length > 4 && bytes[0] === 0xff && bytes[1] === 0xd8 && bytes.at(-2) === 0xff && bytes.at(-1) === 0xd9;
      if (msg.format !== "jpeg" || !jpeg) fail(`${channel.topic}: format ${msg.format}, data is not a JPEG image`);
      entry.jpeg_bytes = (entry.jpeg_bytes ?? 0) + bytes.length;
    } else {
      entry.boxes = (entry.boxes ?? 0) + msg.points.length;
    }
  } else if (record.type === "Footer") {
    summary.complete = true;
  }
}
if (!reader.done()) fail("trailing bytes after the footer, or a truncated file");
if (!summary.complete) fail("no footer: the file was not finalised");
console.log(JSON.stringify(summary));
process.exit(summary.errors.length ? 1 : 0);

// node read_ktx2.mjs FILE.ktx2 -> ktx-parse's view of the container as JSON (header, levels, DFD, key/values).
import { readFile } from "node:fs/promises";
import { read } from "ktx-parse";

const c = read(new Uint8Array(await readFile(process.argv[2])));
const kv = {};
for (const [k, v] of Object.entries(c.keyValue)) kv[k] = typeof v === "string" ? v : Array.from(v);
process.stdout.write(JSON.stringify({
  vkFormat: c.vkFormat, typeSize: c.typeSize, pixelWidth: c.pixelWidth, pixelHeight: c.pixelHeight,
  pixelDepth: c.pixelDepth, layerCount: c.layerCount, faceCount: c.faceCount, levelCount: c.levels.length,
  supercompressionScheme: c.supercompressionScheme,
  levels: c.levels.map((l) => ({ bytes: l.levelData.byteLength, uncompressed: l.uncompressedByteLength })),
  dfd: c.dataFormatDescriptor.map((d) => ({ colorModel: d.colorModel, colorPrimaries: d.colorPrimaries,
    transferFunction: d.transferFunction, bytesPlane: d.bytesPlane, samples: d.samples })),
  keyValue: kv,
}));

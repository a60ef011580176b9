// node validate_gltf.mjs FILE.gltf -> the Khronos glTF-Validator's report as JSON on stdout.
// External resources (images) are read from the file's directory, as a loader would.
import { readFile } from "node:fs/promises";
import { dirname, join } from "node:path";
import validator from "gltf-validator";

const path = process.argv[2];
const data = new Uint8Array(await readFile(path));
const report = await validator.validateBytes(data, {
  uri: path,
  externalResourceFunction: (uri) => readFile(join(dirname(path), decodeURIComponent(uri.split("?")[0]))).then((b) => new Uint8Array(b)),
});
process.stdout.write(JSON.stringify(report));

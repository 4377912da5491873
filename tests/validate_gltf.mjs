// Validate one glTF 2.0 / GLB file with the Khronos glTF-Validator (npm "gltf-validator" installed in
// frontend/node_modules) and print the full report as JSON on stdout.
// Usage: node tests/validate_gltf.mjs <file.glb|file.gltf>
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const require = createRequire(path.join(here, "..", "frontend", "package.json"));
const validator = require("gltf-validator");

const file = process.argv[2];
if (!file) {
  console.error("usage: node validate_gltf.mjs <file>");
  process.exit(2);
}
const bytes = new Uint8Array(await readFile(file));
const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 1000,
  writeTimestamp: false,
  // Our files must be self-contained: any external resource is an error.
  externalResourceFunction: (uri) => Promise.reject(new Error(`external resource not allowed: ${uri}`)),
});
process.stdout.write(JSON.stringify(report));

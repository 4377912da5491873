// Validate many glTF/GLB files in one node process (start-up once) and print {path: summary} as JSON.
// Usage: node tests/validate_gltf_many.mjs <file> [<file> ...]
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const require = createRequire(path.join(here, "..", "frontend", "package.json"));
const validator = require("gltf-validator");

const out = {};
for (const file of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(file)), {
    uri: path.basename(file),
    maxIssues: 100,
    writeTimestamp: false,
    externalResourceFunction: (uri) => Promise.reject(new Error(`external resource not allowed: ${uri}`)),
  });
  out[file] = { numErrors: report.issues.numErrors, numWarnings: report.issues.numWarnings,
    messages: report.issues.messages.filter((m) => m.severity <= 1).slice(0, 10) };
}
process.stdout.write(JSON.stringify(out));

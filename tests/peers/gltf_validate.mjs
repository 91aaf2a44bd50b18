// The Khronos glTF validator (npm `gltf-validator`, the reference implementation of the glTF 2.0
// specification's rules) run on one file: an outside judge of `lungdyn export gltf`.
//
//   node tests/peers/gltf_validate.mjs NODE_MODULES FILE.glb
//
// Prints the validator's whole report as JSON on stdout (issues.numErrors, numWarnings, numInfos,
// numHints, and every message with its code, severity and JSON pointer). Exits 0 when it ran; the
// caller judges the report. Exits 2 when it could not run (bad arguments, unreadable file).
import { createRequire } from "node:module";
import { readFile } from "node:fs/promises";
import path from "node:path";

const [modules, file] = process.argv.slice(2);
if (!modules || !file) {
  console.error("usage: node gltf_validate.mjs NODE_MODULES FILE.glb");
  process.exit(2);
}
const require = createRequire(path.join(path.resolve(modules), "lungdyn-peer.js"));
const validator = require("gltf-validator");
let bytes;
try {
  bytes = new Uint8Array(await readFile(file));
} catch (e) {
  console.error(`cannot read ${file}: ${e.message}`);
  process.exit(2);
}
const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 0, // all of them
  // A .glb holds its buffers: nothing outside it may be asked for.
  externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
});
console.log(JSON.stringify(report));

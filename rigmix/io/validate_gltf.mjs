// Run the Khronos glTF-Validator on one file and print its JSON report on stdout.
// Usage: node validate_gltf.mjs <file.glb|file.gltf> <node_modules folder>
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";

const [file, modules] = process.argv.slice(2);
const require = createRequire(path.join(path.resolve(modules), "_rigmix_.js"));
const validator = require("gltf-validator");
const bytes = new Uint8Array(await readFile(file));
const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 1000,
  externalResourceFunction: async (uri) =>
    new Uint8Array(await readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)))),
});
process.stdout.write(JSON.stringify(report));

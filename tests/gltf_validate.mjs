// Validate glTF/GLB files with the Khronos glTF validator (npm package gltf-validator, validateBytes).
//
//   node tests/gltf_validate.mjs [--prefix DIR] file.glb [more.glb ...]
//
// The package is looked up in DIR/node_modules (DIR from --prefix, else $GLTF_VALIDATOR_PREFIX, else
// ~/.cache/hackneck/gltf-validator, where tests/test_gltf.py installs it); install it there, outside the
// repository, with
//   npm install --no-save --prefix DIR gltf-validator
// Prints one JSON line per file: {"file", "validator", "errors", "warnings", "infos", "hints", "messages"}
// (messages: the errors and warnings, code + pointer + message). Exit status 0 when no file has errors,
// 1 when one has, 2 on bad usage or a missing package.
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";
import os from "node:os";
import path from "node:path";

const args = process.argv.slice(2);
let prefix = process.env.GLTF_VALIDATOR_PREFIX || path.join(os.homedir(), ".cache", "hackneck", "gltf-validator");
const files = [];
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--prefix") prefix = args[++i];
  else files.push(args[i]);
}
if (files.length === 0 || !prefix) {
  console.error("usage: node tests/gltf_validate.mjs [--prefix DIR] file.glb [...]");
  process.exit(2);
}
let validator;
try {
  validator = createRequire(path.join(path.resolve(prefix), "node_modules", "noop.js"))("gltf-validator");
} catch (e) {
  console.error(`gltf-validator not found under ${prefix}/node_modules: npm install --no-save --prefix ${prefix} gltf-validator`);
  process.exit(2);
}

let failed = false;
for (const file of files) {
  let report;
  try {
    report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
      uri: path.basename(file),
      maxIssues: 0, // all issues
    });
  } catch (e) {
    console.error(`${file}: cannot validate (${e})`);
    process.exit(2);
  }
  const issues = report.issues;
  const messages = issues.messages
    .filter((m) => m.severity <= 1)
    .slice(0, 20)
    .map((m) => ({ code: m.code, severity: m.severity, pointer: m.pointer, message: m.message }));
  console.log(JSON.stringify({
    file,
    validator: report.validatorVersion,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    hints: issues.numHints,
    messages,
  }));
  if (issues.numErrors > 0) failed = true;
}
process.exit(failed ? 1 : 0);

// The Khronos glTF validator (npm gltf-validator, installed by scripts/setup in
// daemon/assets/viewer) on each file given: one JSON line per file with the counts of errors,
// warnings, infos and hints, and the errors' and warnings' messages.
// usage: node tests/tools/gltf_validate.mjs FILE.glb|FILE.gltf ...
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";

const require = createRequire(new URL("../../daemon/assets/viewer/package.json", import.meta.url));
const validator = require("gltf-validator");

for (const file of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
    uri: file,
    maxIssues: 0,
    // choreod's files are self-contained: any external reference is a fault.
    externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
  });
  const issues = report.issues;
  console.log(JSON.stringify({
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    hints: issues.numHints,
    messages: issues.messages.filter((m) => m.severity <= 1),
    info: report.info,
  }));
}

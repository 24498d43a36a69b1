// The Khronos glTF validator (npm's gltf-validator) on one file: prints its report as JSON.
// Copied next to the node_modules it needs by tools/interop_test.py:  node validate.mjs FILE.glb
import fs from "fs";
import validator from "gltf-validator";

const bytes = new Uint8Array(fs.readFileSync(process.argv[2]));
const report = await validator.validateBytes(bytes, { maxIssues: 100 });
console.log(JSON.stringify({ validatorVersion: report.validatorVersion, issues: report.issues, info: report.info }));

// Validates one glTF or GLB file with the Khronos glTF validator; prints its JSON report to stdout.
// Usage: node validate_gltf.mjs FILE
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";

export async function validateGltf(file) {
  const bytes = new Uint8Array(await readFile(file));
  const dir = path.dirname(file);
  return validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 0,
    externalResourceFunction: (uri) =>
      readFile(path.resolve(dir, decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
  });
}

if (import.meta.url === `file://${process.argv[1]}`) {
  if (process.argv.length !== 3) {
    console.error("usage: node validate_gltf.mjs FILE");
    process.exit(2);
  }
  try {
    console.log(JSON.stringify(await validateGltf(process.argv[2]), null, 1));
  } catch (e) {
    console.error(`${process.argv[2]}: ${e}`);
    process.exit(2);
  }
}

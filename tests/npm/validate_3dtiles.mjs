// Validates a 3D Tiles 1.1 tileset directory; prints a JSON report to stdout:
// {numErrors, numWarnings, numInfos, issues: [{severity, path, message}], tiles, contents}.
// Checks: tileset.json against tileset.schema.json (the 3D Tiles 1.1 specification's required
// properties and value ranges of what bbcity writes; CesiumGS's 3d-tiles-validator is not on npm),
// parsed by loaders.gl's Tiles3DLoader; every tile's geometric error no larger than its
// parent's; every content URI inside DIR and present, each GLB content through the Khronos
// glTF validator (its errors and warnings counted here) and parsed by Tiles3DLoader.
// Usage: node validate_3dtiles.mjs DIR
import { readFile } from "node:fs/promises";
import path from "node:path";
import { fileURLToPath } from "node:url";
import Ajv2020 from "ajv/dist/2020.js";
import { parse } from "@loaders.gl/core";
import { Tiles3DLoader } from "@loaders.gl/3d-tiles";
import { validateGltf } from "./validate_gltf.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const issues = [];
const issue = (severity, where, message) => issues.push({ severity, path: where, message });

async function schemaValidator() {
  const ajv = new Ajv2020({ strict: false, allErrors: true, validateFormats: false });
  return ajv.compile(JSON.parse(await readFile(path.join(here, "tileset.schema.json"), "utf8")));
}

async function walk(tile, where, parentError, root, counts) {
  counts.tiles += 1;
  if (tile.geometricError > parentError) {
    issue("WARNING", where, `geometricError ${tile.geometricError} is larger than its parent's ${parentError}`);
  }
  const contents = [tile.content, ...(tile.contents || [])].filter(Boolean);
  for (const [k, c] of contents.entries()) {
    const at = `${where}/content${contents.length > 1 ? `s/${k}` : ""}`;
    const file = path.resolve(root, decodeURIComponent(c.uri));
    if (!file.startsWith(root + path.sep)) {
      issue("ERROR", at, `uri ${c.uri} leads outside the tileset`);
      continue;
    }
    let bytes;
    try {
      bytes = await readFile(file);
    } catch (e) {
      issue("ERROR", at, `uri ${c.uri}: ${e.message}`);
      continue;
    }
    counts.contents += 1;
    if (bytes.subarray(0, 4).toString("latin1") !== "glTF") {
      issue("ERROR", at, `uri ${c.uri} is not a GLB`);
      continue;
    }
    const report = await validateGltf(file);
    for (const m of report.issues.messages) {
      const severity = ["ERROR", "WARNING", "INFO", "INFO"][m.severity];
      issue(severity, `${at} ${c.uri}${m.pointer || ""}`, `${m.code}: ${m.message}`);
    }
    try {
      await parse(bytes, Tiles3DLoader, { "3d-tiles": { loadGLTF: false } });
    } catch (e) {
      issue("ERROR", at, `Tiles3DLoader cannot parse ${c.uri}: ${e.message}`);
    }
  }
  for (const [k, child] of (tile.children || []).entries()) {
    await walk(child, `${where}/children/${k}`, tile.geometricError, root, counts);
  }
}

async function main(dir) {
  const root = path.resolve(dir);
  const file = path.join(root, "tileset.json");
  const text = await readFile(file, "utf8");
  const doc = JSON.parse(text);
  const validate = await schemaValidator();
  if (!validate(doc)) {
    for (const e of validate.errors) issue("ERROR", `tileset.json${e.instancePath}`, `schema: ${e.message}`);
  }
  if (doc.asset?.version !== "1.1") issue("ERROR", "tileset.json/asset/version", `is ${doc.asset?.version}, expected 1.1`);
  try {
    const parsed = await parse(new TextEncoder().encode(text), Tiles3DLoader, { "3d-tiles": { isTileset: true } },
      { url: file });
    if (!parsed.root) issue("ERROR", "tileset.json", "Tiles3DLoader found no root tile");
  } catch (e) {
    issue("ERROR", "tileset.json", `Tiles3DLoader cannot parse it: ${e.message}`);
  }
  const counts = { tiles: 0, contents: 0 };
  if (doc.root) {
    if (doc.root.geometricError > doc.geometricError) {
      issue("WARNING", "tileset.json/root", "the root's geometricError is larger than the tileset's");
    }
    await walk(doc.root, "tileset.json/root", doc.geometricError, root, counts);
  }
  const count = (s) => issues.filter((i) => i.severity === s).length;
  return { numErrors: count("ERROR"), numWarnings: count("WARNING"), numInfos: count("INFO"), issues, ...counts };
}

if (process.argv.length !== 3) {
  console.error("usage: node validate_3dtiles.mjs DIR");
  process.exit(2);
}
try {
  console.log(JSON.stringify(await main(process.argv[2]), null, 1));
} catch (e) {
  console.error(`${process.argv[2]}: ${e}`);
  process.exit(2);
}

// Bundle src/ with three.js into one minified script for the Python package (scripts/build-web runs this).
// The first line of the output records the SHA-256 of the sources and the lock file it was built from;
// tests/test_viewer.py checks it against the tree, so a source change without a rebuild fails the tests.
import { build } from "esbuild";
import { createHash } from "node:crypto";
import { readFileSync, readdirSync, writeFileSync } from "node:fs";

// The bundle's path: the package's by default, or the first argument (scripts/build-web --check builds elsewhere).
const OUT = process.argv[2] ?? "../occflownet/viewer/assets/occflownet-web.js";
const inputs = ["package.json", "package-lock.json", "build.mjs",
  ...readdirSync("src").filter((f) => f.endsWith(".js")).sort().map((f) => `src/${f}`)];
const hash = createHash("sha256");
for (const f of inputs) hash.update(f + "\0" + readFileSync(f, "utf8").replace(/\r\n/g, "\n") + "\0");
const three = JSON.parse(readFileSync("node_modules/three/package.json", "utf8")).version;
const result = await build({
  entryPoints: ["src/index.js"], bundle: true, minify: true, format: "iife", target: "es2020",
  legalComments: "eof", write: false,
});
const banner = `/* occflownet-web sources-sha256=${hash.digest("hex")} three=${three} (MIT, three.js authors) */\n`;
writeFileSync(OUT, banner + result.outputFiles[0].text);
console.log(`wrote ${OUT}: ${(banner.length + result.outputFiles[0].text.length) / 1024 | 0} KiB (three ${three})`);

// A glTF file shown in a real browser: Google's <model-viewer> (npm `@google/model-viewer`, three.js
// inside) in Chromium driven by playwright-core, the page served from 127.0.0.1 by this script.
// The camera looks at the model's front (+Z, glTF's "front of the asset"), level.
//
//   node tests/peers/gltf_view.mjs NODE_MODULES CHROMIUM FILE.glb OUT_PREFIX TIME_S...
//
// For each TIME_S: the animation (the file's first) paused at that time, one 800x600 screenshot,
// OUT_PREFIX_<i>.png. Prints JSON on stdout: {loaded, error, duration_s, animations, shots: [...],
// console: [...]}. Exits 0 when the page ran (the caller judges the pictures), 2 otherwise.
import { createRequire } from "node:module";
import { readFile } from "node:fs/promises";
import http from "node:http";
import path from "node:path";

const [modules, chromiumPath, file, prefix, ...times] = process.argv.slice(2);
if (!modules || !chromiumPath || !file || !prefix || times.length === 0) {
  console.error("usage: node gltf_view.mjs NODE_MODULES CHROMIUM FILE.glb OUT_PREFIX TIME_S...");
  process.exit(2);
}
const require = createRequire(path.join(path.resolve(modules), "lungdyn-peer.js"));
const { chromium } = require("playwright-core");
const viewerJs = await readFile(
  path.join(modules, "@google/model-viewer/dist/model-viewer.min.js"),
);
const glb = await readFile(file);
const page = `<!doctype html>
<html><head><meta charset="utf-8"><title>lungdyn breath</title>
<script type="module" src="/model-viewer.min.js"></script>
<style>html,body{margin:0;background:#ffffff} model-viewer{width:800px;height:600px;
background-color:#ffffff;--poster-color:#ffffff}</style></head>
<body><model-viewer id="mv" src="/breath.glb" camera-orbit="0deg 90deg auto"
 interaction-prompt="none" shadow-intensity="0" environment-image="neutral"></model-viewer>
<script>
const mv = document.getElementById("mv");
mv.addEventListener("load", () => { window.lungdynLoaded = true; });
mv.addEventListener("error", (e) => { window.lungdynError = JSON.stringify(e.detail || e.type); });
</script></body></html>`;
const server = http.createServer((req, res) => {
  // (Chromium also asks for /favicon.ico: a 404, said on the page's console.)
  const body = { "/": page, "/model-viewer.min.js": viewerJs, "/breath.glb": glb }[req.url];
  const type = {
    "/": "text/html",
    "/model-viewer.min.js": "text/javascript",
    "/breath.glb": "model/gltf-binary",
  }[req.url];
  if (body === undefined) {
    res.writeHead(404);
    res.end();
    return;
  }
  res.writeHead(200, { "content-type": type });
  res.end(body);
});
await new Promise((ok) => server.listen(0, "127.0.0.1", ok));
const url = `http://127.0.0.1:${server.address().port}/`;
const out = { loaded: false, error: null, duration_s: null, animations: [], shots: [], console: [] };
const browser = await chromium.launch({
  executablePath: chromiumPath,
  // No GPU: WebGL on SwiftShader, Chromium's CPU rasteriser.
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
});
try {
  const tab = await browser.newPage({ viewport: { width: 800, height: 600 } });
  tab.on("console", (m) => out.console.push(`${m.type()}: ${m.text()}`));
  tab.on("pageerror", (e) => out.console.push(`pageerror: ${e.message}`));
  await tab.goto(url);
  await tab.waitForFunction(() => window.lungdynLoaded || window.lungdynError, null, {
    timeout: 90000,
  });
  out.error = await tab.evaluate(() => window.lungdynError || null);
  out.loaded = await tab.evaluate(() => !!window.lungdynLoaded);
  if (out.loaded) {
    out.animations = await tab.evaluate(() => document.getElementById("mv").availableAnimations);
    out.duration_s = await tab.evaluate(async () => {
      const mv = document.getElementById("mv");
      mv.animationName = mv.availableAnimations[0];
      mv.play();
      await mv.updateComplete;
      await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
      mv.pause();
      return mv.duration;
    });
    for (const [i, t] of times.entries()) {
      await tab.evaluate(async (t) => {
        const mv = document.getElementById("mv");
        mv.animationName = mv.availableAnimations[0];
        mv.pause();
        mv.currentTime = Number(t);
        await mv.updateComplete;
        // Two frames: the new pose rendered and composited.
        await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
      }, t);
      await tab.waitForTimeout(500);
      const shot = `${prefix}_${i}.png`;
      await tab.screenshot({ path: shot });
      out.shots.push({ time_s: Number(t), file: shot });
    }
  }
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify(out));

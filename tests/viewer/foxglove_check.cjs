// Opens annotated logs in the Foxglove Studio 1.48 web app (npm @foxglove/studio-base's
// prebuilt bundle) in headless Chromium and prints, per log, one JSON line: the topics the
// app lists and the text of its Problems tab, with a screenshot of each tab. Usage:
//   node foxglove_check.cjs MODULES_DIR CHROMIUM OUT_DIR [--layout LAYOUT.json AT[,AT...]] LOG.mcap...
// With --layout, each log opens in that Foxglove layout instead of the default one, and is
// seeked to each fraction AT (0..1) of the log's time span in turn: a screenshot there
// ("layout" for the first, "layout.AT" for the others), the panels' text and where the
// panels' canvases are.
// MODULES_DIR holds node_modules with playwright-core, react 17, react-dom 17 and studio-base.
"use strict";
const fs = require("fs");
const http = require("http");
const path = require("path");

const [modules, chromium, outDir, ...rest] = process.argv.slice(2);
const layoutFile = rest[0] === "--layout" ? rest[1] : undefined;
const layoutAts = layoutFile ? rest[2].split(",").map(Number) : [];
const logs = layoutFile ? rest.slice(3) : rest;
// The layout, stored as Foxglove's layout storage holds it, and selected in the user profile.
const LAYOUT_ID = "doseqslam";
const storedLayout = layoutFile && { id: LAYOUT_ID, name: "doseqslam", permission: "CREATOR_WRITE",
  baseline: { data: JSON.parse(fs.readFileSync(layoutFile, "utf8")), savedAt: undefined },
  working: undefined, syncInfo: undefined };
const nm = path.join(modules, "node_modules");
const { chromium: launcher } = require(path.join(nm, "playwright-core"));
const assets = path.join(nm, "@foxglove", "studio-base", "assets");

const PAGE = `<!doctype html><html><head><meta charset="utf-8"></head><body>
<div id="root" style="height:100vh"></div>
<script src="/react.js"></script><script src="/react-dom.js"></script>
<script>self.react = self.React; self["react-dom"] = self.ReactDOM;</script>
<script src="/assets/index.js"></script><script src="/boot.js"></script></body></html>`;

// The studio-web entry point, reduced: in-memory settings and layouts, remote files only.
const BOOT = `(async () => {
  const values = {};
  const settings = { get: (k) => values[k], set: async (k, v) => { values[k] = v; },
    addChangeListener() {}, removeChangeListener() {} };
  const layouts = new Map(self.storedLayout ? [[self.storedLayout.id, self.storedLayout]] : []);
  const storage = { list: async () => [...layouts.values()], get: async (ns, id) => layouts.get(id),
    put: async (ns, l) => (layouts.set(l.id, l), l), delete: async (ns, id) => { layouts.delete(id); },
    importLayouts: async () => {} };
  await self.waitForFonts();
  await self.initI18n();
  ReactDOM.render(React.createElement(self.App, { deepLinks: [location.href],
    dataSources: [new self.RemoteDataSourceFactory()], appConfiguration: settings,
    layoutStorage: storage, extensionLoaders: [], enableGlobalCss: true }),
    document.getElementById("root"));
})();`;

const FILES = {
  "/": [PAGE, "text/html"],
  "/boot.js": [BOOT, "text/javascript"],
};

function send(res, req, file, type) {
  const size = fs.statSync(file).size;
  const range = /bytes=(\d+)-(\d*)/.exec(req.headers.range ?? "");
  const start = range ? Number(range[1]) : 0;
  const end = range && range[2] ? Number(range[2]) : size - 1;
  res.writeHead(range ? 206 : 200, { "content-type": type, "accept-ranges": "bytes",
    "content-length": end - start + 1, "access-control-allow-origin": "*",
    ...(range ? { "content-range": `bytes ${start}-${end}/${size}` } : {}) });
  fs.createReadStream(file, { start, end }).pipe(res);
}

function serve(req, res) {
  const url = new URL(req.url, "http://localhost").pathname;
  if (FILES[url]) {
    res.writeHead(200, { "content-type": FILES[url][1] });
    return res.end(FILES[url][0]);
  }
  const umd = { "/react.js": "react/umd/react.production.min.js",
    "/react-dom.js": "react-dom/umd/react-dom.production.min.js" }[url];
  if (umd) return send(res, req, path.join(nm, umd), "text/javascript");
  if (url.startsWith("/data/")) return send(res, req, logs[Number(url.split("/")[2])], "application/octet-stream");
  const file = path.join(assets, path.normalize(url.replace(/^\/assets\//, "")));
  if (url.startsWith("/assets/") && fs.existsSync(file)) {
    const type = file.endsWith(".js") ? "text/javascript" : file.endsWith(".wasm") ? "application/wasm" : "application/octet-stream";
    return send(res, req, file, type);
  }
  res.writeHead(404).end();
}

async function main() {
  const server = http.createServer(serve).listen(0, "127.0.0.1");
  await new Promise((ok) => server.once("listening", ok));
  const origin = `http://127.0.0.1:${server.address().port}`;
  const browser = await launcher.launch({ executablePath: chromium, headless: true,
    args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
      "--disable-background-networking", "--disable-component-update", "--disable-sync"] });
  try {
    for (const [i, log] of logs.entries()) {
      const page = await browser.newPage({ viewport: { width: 1600, height: 1000 } });
      if (storedLayout) {
        await page.addInitScript(([layout]) => {
          self.storedLayout = layout;
          localStorage.setItem("studio.profile-data", JSON.stringify({ currentLayoutId: layout.id }));
        }, [storedLayout]);
      }
      const errors = [];
      page.on("pageerror", (e) => errors.push(String(e)));
      const url = `${origin}/?ds=remote-file&ds.url=${encodeURIComponent(`${origin}/data/${i}/${path.basename(log)}`)}`;
      await page.goto(url);
      // Loaded once the sidebar shows the log's duration (it shows "—" before).
      await page.waitForFunction(() => /DURATION\n\d/.test(document.body.innerText), null,
        { timeout: 120000 });
      await page.waitForTimeout(2000); // let the panels draw
      const shot = (what) => path.join(outDir, `${path.basename(log)}.${what}.png`);
      await page.screenshot({ path: shot("topics") });
      const text = () => page.evaluate(() => document.body.innerText);
      const topics = (await text()).split("\n").filter((line) => line.startsWith("/"));
      await page.getByRole("tab", { name: /Problems/ }).click();
      await page.waitForTimeout(500);
      await page.screenshot({ path: shot("problems") });
      const problems = (await text()).split("\n");
      // The scrubber is the bar just above the playback buttons, across the window.
      const buttons = await page.getByTitle("Seek backward").boundingBox();
      if (storedLayout) {
        const seeks = [];
        for (const [k, at] of layoutAts.entries()) {
          await page.mouse.click(page.viewportSize().width * at, buttons.y - 24);
          await page.waitForTimeout(4000);
          const screenshot = shot(k === 0 ? "layout" : `layout.${at}`);
          await page.screenshot({ path: screenshot });
          const message = (await text()).split("\n"); // the panels' text after the seek
          const canvases = await page.evaluate(() => [...document.querySelectorAll("canvas")]
            .map((c) => c.getBoundingClientRect()).filter((r) => r.width > 0 && r.height > 0)
            .map((r) => ({ x: r.x, y: r.y, width: r.width, height: r.height })));
          seeks.push({ at, screenshot, message, canvases });
        }
        const { message } = seeks[0];
        console.log(JSON.stringify({ log, topics, problems, message, seeks, errors }));
        await page.close();
        continue;
      }
      // Our loop closure decoded: the Raw Messages panel of the default layout, at 90 % of the log.
      await page.getByPlaceholder("/some/topic.msgs[0].field").fill("/doseqslam/loop_closures");
      await page.mouse.click(page.viewportSize().width * 0.9, buttons.y - 24);
      await page.waitForTimeout(2000);
      await page.screenshot({ path: shot("message") });
      const message = (await text()).split("\n");
      console.log(JSON.stringify({ log, topics, problems, message, errors }));
      await page.close();
    }
  } finally {
    await browser.close();
    server.close();
  }
}

main().catch((e) => { console.error(e); process.exit(1); });

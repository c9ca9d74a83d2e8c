// The bundle's entry: `window.OccFlowNet` for scripts, and what runs by itself on load:
// - a viewer file (occflownet view) carries its data in <script type="application/json" id="occ-data">;
// - the server page (GET /ui) has <main id="occ-page">.
import { decodeBytes, surface, topDown } from "./grid.js";
import { cameraOf, startPage } from "./page.js";
import { injectStyles } from "./styles.js";
import { Viewer } from "./viewer.js";

async function startViewerFile(node) {
  const data = JSON.parse(node.textContent);
  const box = document.getElementById("occ-view");
  try {
    window.occViewer = await Viewer.create(box, data);
  } catch (e) {
    box.textContent = `cannot show this grid: ${e}`;
    box.dataset.error = String(e);
    throw e;
  }
}

function start() {
  injectStyles();
  const data = document.getElementById("occ-data");
  if (data) startViewerFile(data);
  if (document.getElementById("occ-page")) startPage();
}

window.OccFlowNet = { Viewer, decodeBytes, surface, topDown, cameraOf };
if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
else start();

// The viewer's and the page's styles, injected once as a <style> element (the bundle is the only asset).
export const CSS = `
.occ-viewer { display: flex; gap: 10px; height: 72vh; min-height: 420px; font: 13px/1.35 system-ui, sans-serif; }
.occ-main { position: relative; flex: 1; min-width: 0; border: 1px solid #d6d9de; }
.occ-canvas { position: absolute; inset: 0; }
.occ-canvas canvas { display: block; }
.occ-pane-labels { position: absolute; top: 6px; left: 0; right: 0; display: flex; pointer-events: none; }
.occ-pane-labels span { text-align: center; font-weight: 600; color: #333; }
.occ-side { width: 300px; overflow-y: auto; }
.occ-controls { display: flex; flex-wrap: wrap; gap: 6px 14px; margin-bottom: 6px; }
.occ-legend-row { display: flex; align-items: center; gap: 4px; }
.occ-legend-row > span:first-child { flex: 1; display: flex; align-items: center; gap: 4px; }
.occ-legend-head { font-weight: 600; border-bottom: 1px solid #ddd; }
.occ-count { width: 80px; text-align: right; font-variant-numeric: tabular-nums; color: #444; overflow: hidden; }
.occ-swatch { display: inline-block; width: 14px; height: 14px; border: 1px solid #0003; }
.occ-stats, .occ-hint { margin-top: 6px; color: #555; }
.occ-thumbs { display: grid; grid-template-columns: repeat(3, minmax(0, 220px)); gap: 6px; margin-top: 8px; }
.occ-thumbs figure { margin: 0; cursor: crosshair; }
.occ-thumbs img { width: 100%; display: block; border: 1px solid #ccc; }
.occ-thumbs figcaption { font: 11px system-ui, sans-serif; color: #444; }
.occ-page [hidden] { display: none !important; }
body.occ-body { margin: 12px 16px; font: 14px/1.4 system-ui, sans-serif; color: #222; background: #fff; }
.occ-page h1 { font-size: 20px; margin: 0 0 4px; }
.occ-form { display: grid; grid-template-columns: max-content 1fr; gap: 6px 12px; align-items: center; margin: 10px 0; }
.occ-drop { border: 2px dashed #bbb; padding: 8px; border-radius: 6px; }
.occ-drop.over { border-color: #36c; background: #eef3ff; }
.occ-assign { border-collapse: collapse; margin: 6px 0; }
.occ-assign td { padding: 1px 10px 1px 0; }
.occ-assign .missing { color: #b00; }
.occ-error { color: #fff; background: #b3261e; padding: 8px 10px; border-radius: 4px; margin: 8px 0; white-space: pre-wrap; }
.occ-note { color: #555; }
.occ-result { display: flex; gap: 12px; align-items: flex-start; margin-top: 10px; }
.occ-result .occ-topdown { flex: none; text-align: center; }
.occ-result .occ-3d { flex: 1; min-width: 0; }
.occ-latency { font-variant-numeric: tabular-nums; margin: 6px 0; }
`;

export function injectStyles() {
  if (document.getElementById("occ-styles")) return;
  const s = document.createElement("style");
  s.id = "occ-styles";
  s.textContent = CSS;
  document.head.append(s);
}

"use strict";
// The map every station's page draws with (served at /map.js): a local flat projection around
// the first point shown, map tiles under it (OpenStreetMap's by default, from GET /api/map) or,
// where tiles cannot be loaded, a metric grid, and the layers the page gives: fences, homes,
// plans with numbered waypoints, tracks and vehicles, with a legend of what is drawn and a
// scale bar. Pan by dragging, zoom with the wheel; a click that did not drag goes to onClick.
//
// What is drawn is also written on the canvas's data attributes (data-tiles, data-grid,
// data-fence, data-home, data-waypoints, data-vehicles), for tests and for curious users.

const EARTH_R = 6371008.8;
const tileLon = (x, z) => x / 2 ** z * 360 - 180;
const tileLat = (y, z) => 180 / Math.PI * Math.atan(Math.sinh(Math.PI - 2 * Math.PI * y / 2 ** z));
const lonTile = (lon, z) => Math.floor((lon + 180) / 360 * 2 ** z);
const latTile = (lat, z) => {
  const r = Math.max(-85, Math.min(85, lat)) * Math.PI / 180;
  return Math.floor((1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2 * 2 ** z);
};
const mapEsc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));

class StationMap {
  // opts: legend and status (elements),
  // onClick(lat, lon), underlay(map) and overlay(map) (the page's own drawing, under the layers
  // and over them), format(metres) and unitMetres() (the page's length unit).
  constructor(canvas, opts = {}) {
    this.cv = canvas;
    this.ctx = canvas.getContext("2d");
    this.opts = opts;
    // scale: pixels per metre; auto: fitted by the page, not moved by the user.
    this.view = { lat0: 0, lon0: 0, cx: 0, cy: 0, scale: 1, set: false, auto: false };
    this.layers = { fences: [], homes: [], routes: [], tracks: [], vehicles: [] };
    this.tiles = null;
    this.tilesShown = true;
    this.tileImgs = new Map();
    this.drag = null;
    fetch("/api/map").then((r) => r.json()).then((c) => { this.tiles = c.tiles; this.draw(); })
      .catch(() => { this.tiles = null; this.draw(); });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = canvas.getBoundingClientRect(), mx = e.clientX - r.left, my = e.clientY - r.top;
      const [la, lo] = this.fromPx(mx, my);
      this.view.scale = Math.max(1e-4, Math.min(500, this.view.scale * (e.deltaY < 0 ? 1.25 : 0.8)));
      this.view.auto = false;
      const [x, y] = this.toXY(la, lo);
      this.view.cx = x - (mx - canvas.width / 2) / this.view.scale;
      this.view.cy = y + (my - canvas.height / 2) / this.view.scale;
      this.draw();
    }, { passive: false });
    canvas.addEventListener("pointerdown", (e) => {
      this.drag = { x: e.clientX, y: e.clientY, cx: this.view.cx, cy: this.view.cy, moved: false };
    });
    addEventListener("pointermove", (e) => {
      const d = this.drag;
      if (!d) return;
      const dx = e.clientX - d.x, dy = e.clientY - d.y;
      if (Math.abs(dx) + Math.abs(dy) > 3) { d.moved = true; this.view.auto = false; }
      this.view.cx = d.cx - dx / this.view.scale; this.view.cy = d.cy + dy / this.view.scale;
      this.draw();
    });
    addEventListener("pointerup", (e) => {
      const d = this.drag;
      this.drag = null;
      if (d && !d.moved && e.target === canvas && opts.onClick) {
        const r = canvas.getBoundingClientRect();
        const [la, lo] = this.fromPx(e.clientX - r.left, e.clientY - r.top);
        opts.onClick(la, lo);
      }
    });
    addEventListener("resize", () => this.draw());
  }

  toXY(lat, lon) {
    const v = this.view;
    return [(lon - v.lon0) * Math.PI / 180 * EARTH_R * Math.cos(v.lat0 * Math.PI / 180), (lat - v.lat0) * Math.PI / 180 * EARTH_R];
  }
  toLatLon(x, y) {
    const v = this.view;
    return [v.lat0 + y / EARTH_R * 180 / Math.PI, v.lon0 + x / (EARTH_R * Math.cos(v.lat0 * Math.PI / 180)) * 180 / Math.PI];
  }
  toPx(lat, lon) {
    const [x, y] = this.toXY(lat, lon), v = this.view;
    return [this.cv.width / 2 + (x - v.cx) * v.scale, this.cv.height / 2 - (y - v.cy) * v.scale];
  }
  fromPx(px, py) {
    const v = this.view;
    return this.toLatLon(v.cx + (px - this.cv.width / 2) / v.scale, v.cy - (py - this.cv.height / 2) / v.scale);
  }

  // Fits the view to `pts` ([lat, lon] each); `auto`: the page's choice, which it may redo.
  fit(pts, auto = false) {
    pts = pts.filter((p) => isFinite(p[0]) && isFinite(p[1]));
    if (!pts.length) return;
    const v = this.view;
    if (!v.set) { v.lat0 = pts[0][0]; v.lon0 = pts[0][1]; }
    const xy = pts.map((p) => this.toXY(p[0], p[1]));
    const xs = xy.map((p) => p[0]), ys = xy.map((p) => p[1]);
    const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    this.resize();
    v.cx = (x0 + x1) / 2; v.cy = (y0 + y1) / 2;
    v.scale = Math.min(5000, 0.85 * Math.min(this.cv.width / Math.max(x1 - x0, 5), this.cv.height / Math.max(y1 - y0, 5)));
    v.set = true; v.auto = auto;
    this.draw();
  }
  // Centres on one point, keeping the zoom.
  centre(lat, lon) {
    if (!this.view.set) { this.fit([[lat, lon]], true); return; }
    const [x, y] = this.toXY(lat, lon);
    this.view.cx = x; this.view.cy = y;
    this.draw();
  }

  setLayers(layers) { this.layers = Object.assign({ fences: [], homes: [], routes: [], tracks: [], vehicles: [] }, layers); this.draw(); }
  showTiles(on) { this.tilesShown = on; this.draw(); }

  resize() {
    const w = this.cv.clientWidth, h = this.cv.clientHeight;
    if (this.cv.width !== w || this.cv.height !== h) { this.cv.width = w; this.cv.height = h; }
  }

  metres(m) {
    const f = this.opts.format;
    return f ? f(m) : m >= 1000 ? (m / 1000).toFixed(m % 1000 ? 1 : 0) + " km" : Math.round(m) + " m";
  }
  // A round length near `m` metres in the page's unit (1, 2 or 5 times a power of ten).
  niceLen(m) {
    const u = this.opts.unitMetres ? this.opts.unitMetres() : 1;
    const x = m / u, p = Math.pow(10, Math.floor(Math.log10(x))), n = x / p >= 5 ? 5 : x / p >= 2 ? 2 : 1;
    return n * p * u;
  }

  drawGrid() {
    const ctx = this.ctx, v = this.view, step = this.niceLen(90 / v.scale);
    const [west, north] = [v.cx - this.cv.width / 2 / v.scale, v.cy + this.cv.height / 2 / v.scale];
    const [east, south] = [v.cx + this.cv.width / 2 / v.scale, v.cy - this.cv.height / 2 / v.scale];
    ctx.strokeStyle = "#1f3328"; ctx.lineWidth = 1; ctx.beginPath();
    for (let x = Math.ceil(west / step) * step; x <= east; x += step) {
      const px = this.cv.width / 2 + (x - v.cx) * v.scale; ctx.moveTo(px, 0); ctx.lineTo(px, this.cv.height);
    }
    for (let y = Math.ceil(south / step) * step; y <= north; y += step) {
      const py = this.cv.height / 2 - (y - v.cy) * v.scale; ctx.moveTo(0, py); ctx.lineTo(this.cv.width, py);
    }
    ctx.stroke();
    this.cv.dataset.grid = this.metres(step);
    return step;
  }

  // Tiles in view; returns [drawn, failed, wanted].
  drawTiles() {
    const t = this.tiles, v = this.view;
    this.cv.dataset.tiles = "";
    if (!t || !this.tilesShown) return [0, 0, 0];
    // The zoom whose 256-px tiles show about as many metres per pixel as the map does.
    const z = Math.max(t.minzoom, Math.min(t.maxzoom,
      Math.round(Math.log2(156543.034 * Math.cos(v.lat0 * Math.PI / 180) * v.scale))));
    const [n, w] = this.fromPx(0, 0), [s, e] = this.fromPx(this.cv.width, this.cv.height), last = 2 ** z - 1;
    const x0 = Math.max(0, lonTile(w, z)), x1 = Math.min(last, lonTile(e, z));
    const y0 = Math.max(0, latTile(n, z)), y1 = Math.min(last, latTile(s, z));
    if ((x1 - x0 + 1) * (y1 - y0 + 1) > 300) return [0, 0, 0];
    if (this.tileImgs.size > 600) this.tileImgs.clear();
    let drawn = 0, failed = 0, wanted = 0;
    for (let x = x0; x <= x1; x++) for (let y = y0; y <= y1; y++) {
      const key = `${z}/${x}/${y}`;
      let im = this.tileImgs.get(key);
      if (!im) {
        im = new Image();
        im.onload = () => this.draw();
        im.onerror = () => { im.failed = true; this.draw(); };
        im.src = t.url.replace("{z}", z).replace("{x}", x).replace("{y}", y);
        this.tileImgs.set(key, im);
      }
      wanted++;
      if (im.failed) { failed++; continue; }
      if (!im.complete || !im.naturalWidth) continue;
      const [px0, py0] = this.toPx(tileLat(y, z), tileLon(x, z)), [px1, py1] = this.toPx(tileLat(y + 1, z), tileLon(x + 1, z));
      this.ctx.drawImage(im, px0, py0, px1 - px0, py1 - py0); drawn++;
    }
    this.cv.dataset.tiles = drawn ? `z${z}:${drawn}` : "";
    return [drawn, failed, wanted];
  }

  drawFence(f) {
    const ctx = this.ctx, parts = [];
    ctx.save();
    ctx.strokeStyle = f.colour || "#f5a623"; ctx.lineWidth = 2; ctx.setLineDash([8, 5]);
    if (f.max_distance_m && f.home) {
      const [hx, hy] = this.toPx(f.home[0], f.home[1]);
      ctx.beginPath(); ctx.arc(hx, hy, f.max_distance_m * this.view.scale, 0, 2 * Math.PI); ctx.stroke();
      parts.push("circle");
    }
    if (f.polygon && f.polygon.length >= 3) {
      ctx.beginPath();
      f.polygon.forEach((p, i) => { const [x, y] = this.toPx(p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
      ctx.closePath(); ctx.stroke();
      parts.push("polygon");
    }
    ctx.restore();
    return parts;
  }

  drawHome(h) {
    const ctx = this.ctx, [x, y] = this.toPx(h.lat, h.lon);
    ctx.fillStyle = "#ffd23f"; ctx.strokeStyle = "#000"; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.arc(x, y, 9, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    ctx.fillStyle = "#000"; ctx.font = "bold 11px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
    ctx.fillText("H", x, y + 0.5);
    if (h.label) { ctx.fillStyle = "#ffd23f"; ctx.textAlign = "left"; ctx.fillText(h.label, x + 12, y); }
    ctx.textAlign = "start"; ctx.textBaseline = "alphabetic";
  }

  // A plan: its legs (the current one highlighted, waiting parts dashed), a dot at every
  // waypoint and its number in flying order where there is room; returns the numbers drawn.
  drawRoute(r) {
    const ctx = this.ctx, pts = r.points || [];
    const px = pts.map((w) => this.toPx(w.lat, w.lon));
    ctx.lineWidth = 1.5;
    for (let i = 1; i < pts.length; i++) {
      const w = pts[i];
      ctx.strokeStyle = w.leg === r.current ? "#7f7" : w.waits ? "#a88" : (r.colour || "#58a");
      ctx.setLineDash(w.waits ? [4, 4] : []);
      ctx.beginPath(); ctx.moveTo(px[i - 1][0], px[i - 1][1]); ctx.lineTo(px[i][0], px[i][1]); ctx.stroke();
    }
    ctx.setLineDash([]);
    // A number goes where no earlier one is within LABEL_GAP px: a loop flown again keeps the
    // numbers of its first pass, a dense scan shows every few.
    const LABEL_GAP = 22, taken = new Map();
    const cell = (x, y) => `${Math.floor(x / LABEL_GAP)},${Math.floor(y / LABEL_GAP)}`;
    const crowded = (x, y) => {
      for (let dx = -1; dx <= 1; dx++) for (let dy = -1; dy <= 1; dy++) {
        for (const [lx, ly] of taken.get(cell(x + dx * LABEL_GAP, y + dy * LABEL_GAP)) || []) {
          if (Math.hypot(x - lx, y - ly) < LABEL_GAP) return true;
        }
      }
      return false;
    };
    let numbered = 0;
    ctx.font = "11px system-ui, sans-serif"; ctx.textBaseline = "middle";
    pts.forEach((w, i) => {
      const [x, y] = px[i];
      ctx.fillStyle = w.leg === r.current ? "#7f7" : "#9cf";
      ctx.beginPath(); ctx.arc(x, y, 2.5, 0, 2 * Math.PI); ctx.fill();
      if (x < -50 || y < -50 || x > this.cv.width + 50 || y > this.cv.height + 50 || crowded(x, y)) return;
      const text = String(i + 1);
      ctx.fillStyle = "rgba(0,0,0,.6)"; ctx.fillRect(x + 4, y - 7, ctx.measureText(text).width + 4, 14);
      ctx.fillStyle = "#fff"; ctx.fillText(text, x + 6, y);
      const k = cell(x, y);
      if (!taken.has(k)) taken.set(k, []);
      taken.get(k).push([x, y]);
      numbered++;
    });
    ctx.textBaseline = "alphabetic";
    return numbered;
  }

  drawTrack(t) {
    const ctx = this.ctx, pts = t.points || [];
    if (pts.length < 2) return;
    ctx.strokeStyle = t.colour || "#fc6"; ctx.lineWidth = 1; ctx.setLineDash([2, 3]); ctx.beginPath();
    pts.forEach((p, i) => { const [x, y] = this.toPx(p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.stroke(); ctx.setLineDash([]);
  }

  drawVehicle(v) {
    const ctx = this.ctx, [x, y] = this.toPx(v.lat, v.lon), s = v.selected ? 1.3 : 1;
    ctx.save(); ctx.translate(x, y); ctx.rotate((v.heading || 0) * Math.PI / 180);
    ctx.fillStyle = v.stale ? "#777" : (v.colour || "#f44"); ctx.strokeStyle = "#000"; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(0, -11 * s); ctx.lineTo(7 * s, 8 * s); ctx.lineTo(0, 4 * s); ctx.lineTo(-7 * s, 8 * s); ctx.closePath();
    ctx.fill(); ctx.stroke(); ctx.restore();
    if (v.label) {
      ctx.font = (v.selected ? "bold " : "") + "12px system-ui, sans-serif";
      ctx.fillStyle = v.stale ? "#999" : "#fff"; ctx.fillText(v.label, x + 12, y - 8);
    }
  }

  draw() {
    this.resize();
    const ctx = this.ctx, cv = this.cv, L = this.layers, v = this.view;
    ctx.fillStyle = "#0b1410"; ctx.fillRect(0, 0, cv.width, cv.height);
    // Nothing placed yet: the area the tiles cover, when they say.
    if (!v.set && this.tiles && this.tiles.bounds) {
      const [tw, ts, te, tn] = this.tiles.bounds;
      this.fit([[tn, tw], [ts, te]], true);
      return;
    }
    if (!v.set) { this.legend([], null); return; }
    const gridStep = this.drawGrid();
    const [tilesDrawn, tilesFailed, tilesWanted] = this.drawTiles();
    if (this.opts.underlay) this.opts.underlay(this);
    const fenceParts = [];
    for (const f of L.fences) fenceParts.push(...this.drawFence(f));
    for (const t of L.tracks) this.drawTrack(t);
    let numbered = 0;
    for (const r of L.routes) numbered += this.drawRoute(r);
    for (const h of L.homes) this.drawHome(h);
    for (const veh of L.vehicles) this.drawVehicle(veh);
    if (this.opts.overlay) this.opts.overlay(this);
    cv.dataset.fence = fenceParts.join("+");
    cv.dataset.home = String(L.homes.length);
    cv.dataset.waypoints = String(numbered);
    cv.dataset.vehicles = String(L.vehicles.length);
    // Scale bar in the page's unit.
    const len = this.niceLen(120 / v.scale), px = len * v.scale;
    ctx.strokeStyle = "#fff"; ctx.fillStyle = "#fff"; ctx.lineWidth = 2; ctx.font = "12px system-ui, sans-serif";
    ctx.beginPath(); ctx.moveTo(12, cv.height - 14); ctx.lineTo(12 + px, cv.height - 14); ctx.stroke();
    ctx.fillText(this.metres(len), 14, cv.height - 20);
    // What the tiles did, in words: a map that is not there says why.
    const t = this.tiles;
    let status;
    if (!t) status = `no map tiles: a ${this.metres(gridStep)} grid`;
    else if (!this.tilesShown) status = `map tiles hidden: a ${this.metres(gridStep)} grid`;
    else if (tilesFailed && !tilesDrawn) status = `map tiles unreachable (offline?): showing a ${this.metres(gridStep)} grid; for a map without internet start the station with --tiles FILE.mbtiles`;
    else if (!tilesWanted) status = `map tiles not drawn at this zoom: a ${this.metres(gridStep)} grid`;
    else status = t.attribution ? `map tiles ${t.attribution}` : "map tiles";
    if (tilesFailed && !tilesDrawn) cv.dataset.tiles = "unreachable";
    if (this.opts.status && this.opts.status.textContent !== status) this.opts.status.textContent = status;
    this.legend([
      L.vehicles.length && ["vehicle", "▲", "#f44", "vehicle (grey: not heard lately)"],
      L.homes.length && ["home", "H", "#ffd23f", "home (the autopilot's)"],
      L.routes.some((r) => (r.points || []).length) && ["plan", "—", "#58a", "plan (green: the current leg)"],
      numbered && ["waypoints", "1 2 3", "#fff", "waypoints, numbered in flying order"],
      L.tracks.some((t2) => (t2.points || []).length > 1) && ["track", "┄", "#fc6", "track flown"],
      fenceParts.length && ["fence", "╌", "#f5a623", "fence (" + [...new Set(fenceParts)].join(" and ") + ")"],
    ].filter(Boolean), gridStep);
  }

  legend(items, gridStep) {
    const el = this.opts.legend;
    if (!el) return;
    const html = items.map(([key, sym, colour, text]) =>
      `<li data-key="${key}"><b style="color:${colour}">${mapEsc(sym)}</b> ${mapEsc(text)}</li>`).join("")
      + (gridStep ? `<li data-key="grid"><b style="color:#4a6">#</b> grid: ${mapEsc(this.metres(gridStep))}</li>` : "");
    if (el.dataset.html !== html) { el.innerHTML = html; el.dataset.html = html; }
  }
}

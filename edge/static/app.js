// The live page: one WebSocket (/ws), JSON states (at most 10 a second) and JPEG thumbnails.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const CELL = 60;
const MOVES = { up: [-1, 0], down: [1, 0], left: [0, -1], right: [0, 1] };
const GROUP_COLOURS = ["#1f77b4", "#9467bd", "#17becf", "#8c564b", "#e377c2", "#bcbd22"];
let config = null;
let lastState = 0;
let states = [];

function el(name, attrs = {}, parent = null, text = null) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text !== null) node.textContent = text;
  if (parent) parent.appendChild(node);
  return node;
}

function centre(cell) {
  return [cell[1] * CELL + CELL / 2, cell[0] * CELL + CELL / 2];
}

function arrow(parent, x0, y0, x1, y1, cls) {
  el("line", { x1: x0, y1: y0, x2: x1, y2: y1, class: cls }, parent);
  const a = Math.atan2(y1 - y0, x1 - x0);
  const s = 9;
  const pts = [[x1, y1], [x1 - s * Math.cos(a - 0.5), y1 - s * Math.sin(a - 0.5)],
               [x1 - s * Math.cos(a + 0.5), y1 - s * Math.sin(a + 0.5)]];
  el("polygon", { points: pts.map((p) => p.join(",")).join(" "), class: cls + " head" }, parent);
}

function drawArena(state) {
  const svg = document.getElementById("arena");
  const rows = config.rows, cols = config.cols;
  svg.setAttribute("viewBox", `0 0 ${cols * CELL} ${rows * CELL}`);
  svg.dataset.stepT = state.step_t_ns || "";
  svg.replaceChildren();
  for (const [kind, cells] of Object.entries(state.static || {})) {
    for (const [r, c] of cells) {
      el("rect", { x: c * CELL, y: r * CELL, width: CELL, height: CELL, class: "cell " + kind,
                   "data-kind": kind }, svg);
    }
  }
  for (let r = 0; r <= rows; r++) el("line", { x1: 0, y1: r * CELL, x2: cols * CELL, y2: r * CELL, class: "grid" }, svg);
  for (let c = 0; c <= cols; c++) el("line", { x1: c * CELL, y1: 0, x2: c * CELL, y2: rows * CELL, class: "grid" }, svg);
  const where = Object.fromEntries(state.cars.map((car) => [car.id, car.cell]));
  state.groups.forEach((group, g) => {
    const [lx, ly] = centre(where[group[0]] || [0, 0]);
    for (const member of group.slice(1)) {
      if (!(member in where)) continue;
      const [mx, my] = centre(where[member]);
      el("line", { x1: lx, y1: ly, x2: mx, y2: my, class: "group",
                   stroke: GROUP_COLOURS[g % GROUP_COLOURS.length] }, svg);
    }
  });
  for (const car of state.cars) {
    const [x, y] = centre(car.cell);
    const g = el("g", { class: "car" + (car.uncertain ? " uncertain" : ""),
                        "data-car": car.id, "data-row": car.cell[0], "data-col": car.cell[1],
                        "data-uncertain": car.uncertain, "data-leader": car.leader,
                        "data-command": car.command || "" }, svg);
    if (car.command in MOVES) {
      const [dr, dc] = MOVES[car.command];
      arrow(g, x + dc * 20, y + dr * 20, x + dc * 46, y + dr * 46, "command " + (car.outcome || ""));
    }
    if (car.leader) el("circle", { cx: x, cy: y, r: 24, class: "ring" }, g);
    el("circle", { cx: x, cy: y, r: 18, class: "body" }, g);
    if (car.heading !== null) {
      const a = (car.heading * Math.PI) / 180;
      el("line", { x1: x, y1: y, x2: x + 18 * Math.sin(a), y2: y - 18 * Math.cos(a), class: "heading" }, g);
    }
    el("text", { x: x, y: y }, g, car.uncertain ? car.id + "?" : String(car.id));
    el("title", {}, g, `car ${car.id}: cell (${car.cell}), ${car.command || "-"} (${car.outcome || "-"})`);
  }
}

function drawLatency(latency) {
  const svg = document.getElementById("latency");
  const w = 480, h = 140, pad = 18;
  svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
  svg.replaceChildren();
  const n = latency.counts.length;
  const most = Math.max(1, ...latency.counts);
  const bw = (w - 2 * pad) / n;
  latency.counts.forEach((count, i) => {
    const bh = ((h - 2 * pad) * count) / most;
    const deadline = i < latency.le_ms.length && latency.le_ms[i] > config.deadline_ms;
    el("rect", { x: pad + i * bw + 1, y: h - pad - bh, width: bw - 2, height: bh,
                 fill: deadline || i === latency.le_ms.length ? "#c04040" : "#4a7ab0" }, svg);
    const label = i < latency.le_ms.length ? "≤" + latency.le_ms[i] : "more";
    el("text", { x: pad + i * bw + bw / 2, y: h - 4, "font-size": 8, "text-anchor": "middle" }, svg, label);
    if (count) el("text", { x: pad + i * bw + bw / 2, y: h - pad - bh - 2, "font-size": 9, "text-anchor": "middle" }, svg, String(count));
  });
}

function row(cells) {
  const tr = document.createElement("tr");
  for (const c of cells) {
    const td = document.createElement("td");
    td.textContent = c;
    tr.appendChild(td);
  }
  return tr;
}

function drawTables(state) {
  const d = state.deadline;
  const share = d.share === null ? "-" : (100 * d.share).toFixed(2) + " %";
  document.getElementById("deadline").replaceChildren(
    row(["on time", d.on_time]), row(["missed", d.missed]), row(["share on time", share]),
    row(["sent late", d.late_sends]), row(["executed late", d.late_executions]),
    row(["last decision", state.decision_ms === null ? "-" : state.decision_ms + " ms"]),
    row(["last frame → all received", state.loop_ms === null ? "-" : state.loop_ms + " ms"]));
  const byId = Object.fromEntries(state.cars.map((car) => [car.id, car]));
  document.querySelector("#links tbody").replaceChildren(...state.links.map((l) => {
    const car = byId[l.id];
    return row([l.id, l.joined ? "yes" : "no", car ? car.cell.join(",") : "-",
                car && car.command ? car.command : "-", l.sent, l.on_time, l.missed, l.late]);
  }));
}

function render(state) {
  drawArena(state);
  drawLatency(state.latency);
  drawTables(state);
  const score = state.score === null ? "-" : state.score.toFixed(2);
  document.getElementById("summary").textContent =
    `cars ${state.cars.length} (fleet ${state.fleet.length}) | steps ${state.step} | ` +
    `episodes ${state.episodes} | score ${score} | frames ${state.frames}` +
    (state.frame_age_ms === null ? "" : ` | frame age ${state.frame_age_ms.toFixed(1)} ms`);
  const status = document.getElementById("status");
  if (state.stopped) {
    status.textContent = `STOPPED (${state.remote_estops} stop(s) from this page)`;
    status.className = "status stopped";
  }
}

function updateStatus() {
  const status = document.getElementById("status");
  if (status.classList.contains("stopped") || status.classList.contains("down")) return;
  const now = performance.now();
  states = states.filter((t) => now - t < 2000);
  const stale = now - lastState > 2000;
  status.textContent = stale ? "no update for " + ((now - lastState) / 1000).toFixed(0) + " s"
                             : `live, ${(states.length / 2).toFixed(1)} updates/s`;
  status.className = "status " + (stale ? "stale" : "live");
}

let thumbnailUrl = null;

function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.binaryType = "blob";
  ws.onmessage = (event) => {
    if (typeof event.data !== "string") {
      if (thumbnailUrl) URL.revokeObjectURL(thumbnailUrl);
      thumbnailUrl = URL.createObjectURL(new Blob([event.data], { type: "image/jpeg" }));
      document.getElementById("camera").src = thumbnailUrl;
      document.getElementById("camera-caption").textContent = "camera, detections drawn by the vision";
      return;
    }
    const message = JSON.parse(event.data);
    if (message.kind === "hello") {
      config = message;
      const button = document.getElementById("estop");
      button.disabled = !config.estop;
      button.title = config.estop ? "stop every car now" : "off: start udan-edge with --web-token";
      document.getElementById("token").hidden = !config.estop;
    } else if (message.kind === "state") {
      lastState = performance.now();
      states.push(lastState);
      render(message);
    }
  };
  ws.onclose = () => {
    const status = document.getElementById("status");
    if (!status.classList.contains("stopped")) {
      status.textContent = "disconnected; retrying";
      status.className = "status down";
    }
    setTimeout(() => { status.classList.remove("down"); connect(); }, 1000);
  };
}

document.getElementById("estop-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const result = document.getElementById("estop-result");
  result.textContent = "stopping…";
  try {
    const response = await fetch("/estop", {
      method: "POST",
      headers: { Authorization: "Bearer " + document.getElementById("token").value },
    });
    const body = await response.json();
    result.textContent = response.ok ? `stop sent to ${body.cars} car(s)` : body.error;
  } catch (err) {
    result.textContent = "the edge did not answer: " + err;
  }
});

setInterval(updateStatus, 500);
connect();

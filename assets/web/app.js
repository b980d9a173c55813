// The spectator page: room list and replay list (#/), a live room (#/room/<id>) and a
// replay (#/replay/<id>, optionally ?t=<seconds>). Plain ES modules served by the game
// server; nothing is fetched from anywhere else.

import { OrbitCamera, project } from "./camera.js";
import { Connection } from "./net.js";
import { decodeMesh, decodeHeader, MESH } from "./protocol.js";
import { Renderer, SEAT_COLORS } from "./render.js";
import { Playback, fetchReplay } from "./replay.js";

const $ = (id) => document.getElementById(id);
const EDGES = ["north", "east", "south", "west"];
const STATE_TEXT = {
  waiting: "waiting for players", countdown: "countdown", playing: "playing", round_over: "round over", over: "match over",
};

const stats = { meshFrames: 0, decodeUploadMs: [], badFrames: 0 };
const app = {
  route: null, conn: null, renderer: null, camera: null, room: null, roomInfo: null,
  geometry: null, events: [], replay: null, playback: null, stats, lastMesh: null,
  liveRooms: [], replays: [], error: null,
};
window.clothball = app;
app.banner = (text, cls, ms) => banner(text, cls, ms); // for tests

// --- small DOM helpers ------------------------------------------------------------------

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k === "dataset") Object.assign(e.dataset, v);
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

function show(section) {
  for (const id of ["lobby", "watch", "message"]) $(id).hidden = id !== section;
}

function fmtTime(s) { return `${s.toFixed(2)} s`; }

function fmtDate(epoch) {
  const d = new Date(epoch * 1000);
  return d.toLocaleString(undefined, { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit", second: "2-digit" });
}

function seatName(seats, i) {
  const s = seats?.[i];
  if (!s || s.kind === "empty") return `${EDGES[i]} (empty)`;
  return s.name || `seat ${i}`;
}

function showMessage(title, text, extra = null) {
  show("message");
  $("message-title").textContent = title;
  $("message-text").textContent = text;
  const box = $("message-extra");
  box.replaceChildren();
  if (extra) box.append(extra);
  app.error = { title, text };
}

// --- connection -------------------------------------------------------------------------

function wsUrl() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return `${proto}//${location.host}/ws`;
}

function setConnState(state, detail = {}) {
  const box = $("conn");
  box.dataset.state = state;
  let text = {
    idle: "not connected", connecting: "connecting…", open: "connected",
    offline: "offline: waiting for the network",
  }[state];
  if (state === "reconnecting") {
    text = detail.retryIn > 0.05
      ? `server unreachable: retrying in ${Math.ceil(detail.retryIn)} s (attempt ${detail.attempt})`
      : `reconnecting (attempt ${detail.attempt})…`;
  }
  $("conn-text").textContent = text;
  const live = app.route?.view === "room";
  $("notice").hidden = !(live && state !== "open");
  $("notice").textContent = state === "open" ? "" : `Connection lost: ${text}`;
}

function onWelcome(msg) {
  app.liveRooms = msg.rooms || [];
  renderRoomList();
  if (app.route?.view === "room") joinRoom(app.route.id);
}

function onJson(msg) {
  switch (msg.type) {
    case "rooms":
      app.liveRooms = msg.rooms || [];
      renderRoomList();
      break;
    case "room":
      if (app.route?.view === "room" && msg.id === app.room) {
        app.roomInfo = msg;
        renderScoreboard(msg.scores, msg);
      }
      break;
    case "event":
      if (app.route?.view === "room" && msg.room === app.room) onEvent(msg);
      break;
    case "error":
      console.warn("server error", msg.code, msg.message);
      break;
    default:
      break;
  }
}

// MESH frames are inflated asynchronously (the browser's DecompressionStream): each starts
// as it arrives, and one chain applies them in the order they came.
let meshChain = Promise.resolve();

function onBinary(buf) {
  if (app.route?.view !== "room" || !app.renderer || app.frozen) return;
  const t0 = performance.now();
  let decoded;
  try {
    if (decodeHeader(buf).type !== MESH) return;
    decoded = decodeMesh(buf);
  } catch (e) {
    stats.badFrames += 1;
    console.warn("bad binary frame", e.message);
    return;
  }
  decoded.catch(() => {});  // handled below, in order; not an unhandled rejection meanwhile
  meshChain = meshChain.then(() => decoded).then((mesh) => {
    if (app.route?.view !== "room" || !app.renderer || app.frozen) return;
    app.renderer.uploadMesh(mesh);
    const dt = performance.now() - t0;
    stats.meshFrames += 1;
    stats.decodeUploadMs.push(dt);
    if (stats.decodeUploadMs.length > 600) stats.decodeUploadMs.shift();
    app.lastMesh = mesh;
  }, (e) => {
    stats.badFrames += 1;
    console.warn("bad binary frame", e.message);
  });
}

async function joinRoom(id) {
  const conn = app.conn;
  if (!conn.open) return; // joined again on the next welcome
  const reply = await conn.request({ type: "join", role: "spectator", room: id, mesh: true });
  if (reply.type === "redirect") return; // the room lives elsewhere: joined there on its welcome
  if (app.route?.view !== "room" || app.route.id !== id) {
    if (reply.type === "joined") conn.send({ type: "leave" });
    return;
  }
  if (reply.type === "joined") {
    app.room = reply.room;
    app.geometry = reply.geometry;
    app.roomInfo = reply.state;
    app.events = [];
    $("events").replaceChildren();
    $("view-title").textContent = reply.state.name;
    startRenderer(reply.geometry);
    renderScoreboard(reply.state.scores, reply.state);
    addEventLine(`watching ${reply.state.name} (${reply.state.scene}, ${reply.geometry.n}×${reply.geometry.n})`);
  } else if (reply.code === "unknown_room") {
    const list = el("ul", { class: "room-links" });
    for (const r of app.liveRooms) {
      list.append(el("li", {}, el("a", { href: `#/room/${encodeURIComponent(r.id)}` }, `${r.name} (${r.id})`)));
    }
    showMessage("No such room",
      `Room "${id}" does not exist on this server: it may have closed, or the server may have restarted (rooms get new ids).`
      + (app.liveRooms.length ? " Live rooms now:" : " No room is live now."), list);
  } else if (reply.code !== "closed") {
    showMessage("Cannot watch this room", `${reply.code}: ${reply.message}`);
  }
}

function leaveRoom() {
  if (app.room && app.conn?.open) app.conn.send({ type: "leave" });
  app.room = null;
  app.roomInfo = null;
  app.lastMesh = null;
}

// --- the 3-D view -----------------------------------------------------------------------

function startRenderer(geometry) {
  if (!app.renderer) {
    try {
      app.renderer = new Renderer($("view"));
    } catch (e) {
      showMessage("Cannot draw the cloth", e.message);
      return;
    }
    app.camera = new OrbitCamera();
    app.camera.attach($("view"));
    requestAnimationFrame(frame);
  }
  app.renderer.hasMesh = false;
  app.renderer.setGeometry(geometry);
  app.camera.frame(geometry.size || 1, geometry.height ?? 1);
}

function frame() {
  requestAnimationFrame(frame);
  const r = app.renderer;
  if (!r || $("watch").hidden) return;
  const seats = app.route?.view === "replay" ? app.replay?.header.players : app.roomInfo?.seats;
  r.setSeatColors([0, 1, 2, 3].map((e) => seats?.[e] && seats[e].kind !== "empty"));
  r.draw(app.camera);
  placeLabels(seats);
}

function placeLabels(seats) {
  const box = $("labels");
  const r = app.renderer;
  if (box.children.length !== 4) {
    box.replaceChildren(...[0, 1, 2, 3].map((e) => el("div", { class: "label", dataset: { seat: e } })));
  }
  const w = $("view").clientWidth, h = $("view").clientHeight;
  for (let e = 0; e < 4; e++) {
    const lab = box.children[e];
    const p = r.hasMesh && r.corners ? project(r.viewProjection, r.corners[e], w, h) : null;
    if (!p) { lab.hidden = true; continue; }
    lab.hidden = false;
    // near the right edge the label goes to the left of its corner, so it stays on screen
    const flip = p[0] > w - (lab.offsetWidth || 60) - 16 ? " translateX(calc(-100% - 16px))" : "";
    lab.style.transform = `translate(${p[0].toFixed(1)}px, ${p[1].toFixed(1)}px)${flip}`;
    lab.style.borderColor = SEAT_COLORS[e];
    const text = seatName(seats, e);
    if (lab.textContent !== text) lab.textContent = text;
  }
}

/** Hold the live view still (frames are dropped while frozen): for tests and screenshots. */
app.frozen = false;
app.freeze = (on) => { app.frozen = Boolean(on); };

/** Screen points (CSS px in the page) of cloth nodes as last drawn, for the tests. */
app.screenPoints = (ij) => {
  const r = app.renderer, m = app.lastMesh || app.shownMesh;
  if (!r || !m) return null;
  const w = $("view").clientWidth, h = $("view").clientHeight;
  const rect = $("view").getBoundingClientRect();
  return ij.map(([i, j]) => {
    const p = project(r.viewProjection, r.node(m, i, j), w, h);
    return p ? [p[0] + rect.left, p[1] + rect.top] : null;
  });
};

// --- scoreboard and events --------------------------------------------------------------

// The round a room's info names: during a countdown, the round it leads to (the info's
// `round` counts the rounds begun, so it still names the last one, already over).
function shownRound(info) {
  return info.state === "countdown" && Number.isInteger(info.round) ? info.round + 1 : info.round;
}

function renderScoreboard(scores, info) {
  const box = $("scoreboard");
  box.dataset.scores = scores.join(",");
  const seats = info.seats || [];
  const rows = [0, 1, 2, 3].map((i) => {
    const s = seats[i] || { kind: "empty" };
    const badge = s.kind === "bot" ? "bot" : s.kind === "human" ? (s.connected === false ? "away" : "player") : "";
    return el("tr", { class: `seat seat-${i} ${s.kind}`, dataset: { seat: i } },
      el("td", {}, el("span", { class: "swatch", style: `background:${SEAT_COLORS[i]}` })),
      el("td", { class: "edge" }, EDGES[i]),
      el("td", { class: "name" }, s.kind === "empty" ? "—" : s.name, badge ? el("span", { class: "badge" }, badge) : null),
      el("td", { class: "score" }, String(scores[i] ?? 0)));
  });
  const winners = info.winners?.length ? ` · won by ${info.winners.map((w) => seatName(seats, w)).join(" & ")}` : "";
  box.replaceChildren(
    el("div", { class: "match" },
      el("strong", {}, info.name || info.room_name || ""),
      el("span", {}, ` round ${shownRound(info) ?? "?"} · first to ${info.first_to ?? "?"} · ${STATE_TEXT[info.state] || info.state || ""}${winners}`)),
    el("table", {}, el("tbody", {}, ...rows)));
}

function eventText(ev, seats) {
  const who = (i) => seatName(seats, i);
  switch (ev.event) {
    case "countdown": return `next round in ${ev.seconds}…`;
    case "round_start": return `round ${ev.round}: ball in play`;
    case "score": {
      const by = ev.conceded_by === null || ev.conceded_by === undefined ? `the ${ev.edge_name || EDGES[ev.edge]} edge (unguarded)` : `${who(ev.conceded_by)} (${EDGES[ev.edge]})`;
      const sc = (ev.scorers || []).map(who).join(", ");
      return `round ${ev.round}: ${by} conceded${sc ? `; a point to ${sc}` : ""}`;
    }
    case "match_start": return `match started: first to ${ev.first_to}`;
    case "match_end": return `match over: ${(ev.winners || []).map(who).join(" & ") || "no winner"} won (${(ev.scores || []).join("–")})`;
    case "match_abort": return `match stopped: ${ev.reason}`;
    case "seat": {
      const place = `${EDGES[ev.seat]} seat`;
      if (ev.kind === "empty") return `${place} is free (${ev.reason || "left"})`;
      if (ev.held_for) return `${ev.name || place} disconnected; seat held ${ev.held_for} s`;
      const why = { replaced_bot: " (the bot made way)", backfill: " (an empty seat filled)" }[ev.reason] || "";
      return `${ev.name || ev.kind} ${ev.resumed ? "is back in" : "took"} the ${place}${why}`;
    }
    case "replay_saved": return `round ${ev.round} saved as a replay`;
    case "replay_failed": return `round ${ev.round} not recorded: ${ev.reason}`;
    case "room_stopped": return `room stopped: ${ev.reason}`;
    case "cannot_start": return `cannot start: ${ev.reason}`;
    default: return ev.event;
  }
}

function addEventLine(text, link = null, cls = "") {
  const list = $("events");
  const li = el("li", { class: cls }, text);
  if (link) li.append(" ", el("a", { href: link }, "watch"));
  list.prepend(li);
  while (list.children.length > 40) list.lastChild.remove();
}

let bannerTimer = 0;
function banner(text, cls = "", ms = 2500) {
  const b = $("banner");
  // a name such as "bot-2" must not wrap at its hyphen: U+2011 is a non-breaking hyphen
  b.textContent = text.replace(/-/g, "\u2011");
  b.className = cls;
  b.hidden = false;
  clearTimeout(bannerTimer);
  if (ms) bannerTimer = setTimeout(() => { b.hidden = true; }, ms);
}

function onEvent(ev) {
  const seats = app.roomInfo?.seats;
  app.events.push(ev);
  if (app.events.length > 200) app.events.shift();
  if (ev.event === "countdown") {
    banner(String(ev.seconds), "countdown", 1100);
    if (ev.seconds === 3 || !app.events.slice(-2, -1).some((e) => e.event === "countdown")) {
      addEventLine(eventText(ev, seats));
    }
    return;
  }
  if (ev.event === "score") {
    if (app.roomInfo) app.roomInfo.scores = ev.scores;
    renderScoreboard(ev.scores, { ...(app.roomInfo || {}), scores: ev.scores });
    banner(`${seatName(seats, ev.conceded_by ?? ev.edge)} conceded!`, "score");
  } else if (ev.event === "round_start") {
    banner(`Round ${ev.round}`, "round", 900);
  } else if (ev.event === "match_end") {
    banner(eventText(ev, seats), "end", 4000);
  }
  const link = ev.event === "replay_saved" ? `#/replay/${encodeURIComponent(ev.id)}` : null;
  addEventLine(eventText(ev, seats), link, `ev-${ev.event}`);
}

// --- lobby: rooms and replays ----------------------------------------------------------

// Which corners a human can take (empty, or a bot's: bots are backfill) and the command
// that takes one; this page only watches, the desktop client plays.
function seatHint(room) {
  const open = (room.seats || []).map((s, i) => [s, i]).filter(([s]) => s.open ?? s.kind === "empty");
  if (!open.length) return el("div", { class: "seat-hint" }, "Every corner has a player.");
  const corners = open.map(([s, i]) => `${s.edge || EDGES[i]} (${s.kind === "bot" ? `${s.name}, a bot, makes way` : "free"})`);
  const ws = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
  return el("div", { class: "seat-hint" },
    `To play, take a corner: ${corners.join(", ")}. `,
    el("code", {}, `clothball play --server ${ws} --room ${room.id} --seat ${open[0][1]}`));
}

function renderRoomList() {
  const list = $("rooms");
  list.replaceChildren();
  if (!app.liveRooms.length) {
    list.append(el("li", { class: "empty" }, app.conn?.open ? "No live rooms." : "Not connected."));
  }
  for (const r of app.liveRooms) {
    const seats = el("span", { class: "seats" }, ...r.seats.map((s, i) => el("span", {
      class: `chip ${s.kind}`, style: `border-color:${SEAT_COLORS[i]}`,
    }, `${s.kind === "empty" ? "empty" : s.name} ${r.scores[i]}`)));
    list.append(el("li", { class: "room" },
      el("a", { href: `#/room/${encodeURIComponent(r.id)}`, class: "room-link" },
        el("strong", {}, r.name), ` ${r.scene} · ${r.n}×${r.n} · ${STATE_TEXT[r.state] || r.state}`
        + ` · round ${shownRound(r)} · first to ${r.first_to} · ${r.spectators} watching`),
      seats, seatHint(r)));
  }
  // room filter options: live rooms and rooms seen in replays
  const sel = $("replay-room");
  const keep = sel.value;
  const names = new Map();
  for (const r of app.replays) names.set(r.room_id, r.room_name);
  for (const r of app.liveRooms) names.set(r.id, r.name);
  sel.replaceChildren(el("option", { value: "" }, "all rooms"),
    ...[...names].map(([id, name]) => el("option", { value: id }, `${name} (${id})`)));
  sel.value = names.has(keep) ? keep : "";
}

async function loadReplays() {
  const room = $("replay-room").value;
  try {
    const r = await fetch(`/api/replays?limit=500${room ? `&room=${encodeURIComponent(room)}` : ""}`);
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const body = await r.json();
    app.replays = body.replays;
    $("replay-status").textContent = `${body.total} recorded round${body.total === 1 ? "" : "s"}`;
  } catch (e) {
    $("replay-status").textContent = `cannot list replays: ${e.message}`;
  }
  renderReplayList();
}

function renderReplayList() {
  const q = $("replay-player").value.trim().toLowerCase();
  const room = $("replay-room").value;
  const list = $("replays");
  list.replaceChildren();
  const rows = app.replays.filter((r) => (!room || r.room_id === room)
    && (!q || r.players.some((p) => [p, ...(p.held_by || [])]
      .some((h) => (h.name || "").toLowerCase().includes(q)))
      || r.room_name.toLowerCase().includes(q)));
  if (!rows.length) list.append(el("li", { class: "empty" }, app.replays.length ? "No replay matches." : "No rounds recorded yet."));
  for (const r of rows.slice(0, 200)) {
    const conceded = r.conceded_by === null || r.conceded_by === undefined ? "void" : `${r.players[r.conceded_by]?.name || "?"} conceded`;
    list.append(el("li", { class: "replay", dataset: { id: r.id } },
      el("a", { href: `#/replay/${encodeURIComponent(r.id)}` },
        el("strong", {}, `${r.room_name} · round ${r.round}`),
        ` ${conceded} · ${r.duration_s.toFixed(1)} s · ${fmtDate(r.ended_at)}`),
      el("span", { class: "players" }, r.players.filter((p) => p.kind !== "empty").map((p) => p.name).join(", "))));
  }
}

let lobbyTimer = 0;
function startLobby() {
  show("lobby");
  $("view-title").textContent = "";
  leaveRoom();
  renderRoomList();
  loadReplays();
  clearInterval(lobbyTimer);
  lobbyTimer = setInterval(() => {
    if (app.route?.view !== "lobby") return;
    if (app.conn.open) app.conn.send({ type: "list_rooms" });
    loadReplays();
  }, 2500);
}

// --- replay view ------------------------------------------------------------------------

async function startReplay(id, t0) {
  leaveRoom();
  show("watch");
  $("transport").hidden = false;
  $("view-title").textContent = `replay ${id}`;
  $("events").replaceChildren();
  $("notice").hidden = true;
  $("transport").dataset.state = "loading";
  let replay;
  try {
    replay = await fetchReplay(id);
  } catch (e) {
    if (app.route?.view !== "replay" || app.route.id !== id) return;
    if (e.status === 404) showMessage("No such replay", `Replay "${id}" is not on this server.`);
    else showMessage("Cannot play this replay", e.message);
    return;
  }
  if (app.route?.view !== "replay" || app.route.id !== id) return;
  app.replay = replay;
  replay.onMesh = () => app.playback?.seek(app.playback.time);  // show it once inflated
  const hd = replay.header;
  $("view-title").textContent = `replay: ${hd.room_name} round ${hd.round}`;
  startRenderer(hd.geometry);
  const seek = $("seek");
  seek.max = String(replay.duration);
  seek.step = "0.001";
  $("share").href = `${location.origin}${location.pathname}#/replay/${encodeURIComponent(id)}`;
  $("share-url").value = $("share").href;
  let shownEvents = -1;
  app.playback = new Playback(replay.duration, (t) => {
    // the cloth between its 30 Hz frames: a blend of the two around t (smooth slow motion)
    const { i, j, alpha } = replay.meshPairAt(t);
    const mesh = replay.mesh(i);
    app.renderer.showBlend(mesh, replay.mesh(j), alpha);
    app.shownMesh = mesh;
    const tr = replay.trackAt(t);
    if (tr && app.renderer.ball) {
      app.renderer.ball = { position: tr.ballPosition, radius: app.renderer.ball.radius };
      app.renderer.hips = tr.hips;
    }
    const evs = replay.eventsUntil(t);
    if (evs.length !== shownEvents) {
      shownEvents = evs.length;
      $("events").replaceChildren();
      for (const e of evs) if (e.msg.event !== "countdown") addEventLine(eventText(e.msg, hd.players), null, `ev-${e.msg.event}`);
      const last = evs[evs.length - 1]?.msg;
      if (last?.event === "score") banner(`${seatName(hd.players, last.conceded_by ?? last.edge)} conceded!`, "score", 0);
      else $("banner").hidden = true;
      renderScoreboard(replay.scoresAt(t), {
        name: hd.room_name, round: hd.round, first_to: hd.first_to, seats: hd.players,
        // a replay is one round: "match over" only where the match did end in it
        state: evs.some((e) => e.msg.event === "match_end") ? "over"
          : evs.some((e) => e.msg.event === "score") ? "round_over" : "playing",
      });
    }
    seek.value = String(t);
    $("clock").textContent = `${fmtTime(t)} / ${fmtTime(replay.duration)}`;
    $("play").textContent = app.playback?.playing ? "❚❚ Pause" : "▶ Play";
    $("transport").dataset.state = app.playback?.playing ? "playing" : "paused";
    $("transport").dataset.time = t.toFixed(4);
  });
  app.playback.setSpeed(Number($("speed").value));
  app.playback.seek(Math.min(t0 || 0, replay.duration));
  if (!t0) app.playback.play();
}

function stopReplay() {
  if (app.playback) app.playback.stop();
  app.playback = null;
  app.replay = null;
  app.shownMesh = null;
  $("transport").hidden = true;
  $("banner").hidden = true;
}

// --- routing ----------------------------------------------------------------------------

export function parseRoute(hash) {
  const h = hash.replace(/^#\/?/, "");
  const [path, query = ""] = h.split("?");
  const params = new URLSearchParams(query);
  const parts = path.split("/").filter(Boolean).map(decodeURIComponent);
  if (parts[0] === "room" && parts[1]) return { view: "room", id: parts[1] };
  if (parts[0] === "replay" && parts[1]) return { view: "replay", id: parts[1], t: Number(params.get("t")) || 0 };
  return { view: "lobby" };
}

// The host of the room being watched went away (the connection had moved there): back to
// the lobby, which the connection reaches again at the page's own host, saying why.
function onHostGone(url) {
  if (app.route?.view !== "room") return;
  const id = app.route.id;
  history.replaceState(null, "", "#/");
  app.route = { view: "lobby" };
  startLobby();
  const notice = $("lobby-notice");
  notice.textContent = `The host of room ${id} (${url}) went away; the room is gone with it.`;
  notice.hidden = false;
}

function onRoute() {
  $("lobby-notice").hidden = true;
  const route = parseRoute(location.hash);
  const prev = app.route;
  app.route = route;
  app.error = null;
  if (prev?.view === "replay" && !(route.view === "replay" && route.id === prev.id)) stopReplay();
  if (route.view === "lobby") {
    startLobby();
  } else if (route.view === "room") {
    stopReplay();
    if (prev?.view === "room" && prev.id !== route.id) leaveRoom();
    show("watch");
    $("transport").hidden = true;
    $("events").replaceChildren();
    $("scoreboard").replaceChildren();
    $("view-title").textContent = `room ${route.id}`;
    setConnState(app.conn.state);
    if (app.renderer) app.renderer.hasMesh = false;
    joinRoom(route.id);
  } else if (route.view === "replay") {
    if (!(prev?.view === "replay" && prev.id === route.id)) startReplay(route.id, route.t);
  }
}

function init() {
  $("play").addEventListener("click", () => app.playback?.toggle());
  $("seek").addEventListener("input", (e) => app.playback?.seek(Number(e.target.value)));
  $("speed").addEventListener("change", (e) => app.playback?.setSpeed(Number(e.target.value)));
  $("copy-link").addEventListener("click", async () => {
    const url = $("share-url").value;
    try {
      await navigator.clipboard.writeText(url);
      $("copy-link").textContent = "Copied";
    } catch {
      $("share-url").select();
      $("copy-link").textContent = "Select + copy";
    }
    setTimeout(() => { $("copy-link").textContent = "Copy link"; }, 1500);
  });
  $("replay-room").addEventListener("change", loadReplays);
  $("replay-player").addEventListener("input", renderReplayList);
  window.addEventListener("keydown", (e) => {
    if (!app.playback || e.target.tagName === "INPUT" || e.target.tagName === "SELECT") return;
    if (e.key === " ") { e.preventDefault(); app.playback.toggle(); }
    if (e.key === "ArrowLeft") app.playback.seek(app.playback.time - 1);
    if (e.key === "ArrowRight") app.playback.seek(app.playback.time + 1);
  });
  app.conn = new Connection(wsUrl(), {
    onState: setConnState, onWelcome, onJson, onBinary,
    onClose: () => { if (app.route?.view === "lobby") renderRoomList(); },
    onHostGone,
  }, "spectator");
  window.addEventListener("hashchange", onRoute);
  app.conn.start();
  onRoute();
}

init();

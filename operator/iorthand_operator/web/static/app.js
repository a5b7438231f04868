// The iorthand console in a browser. The deadman, end to end:
// - a timer sends one twist at the server's rate (its hello's twist_hz) while this page holds control, deadman
//   held or not; the server forwards each one at once and never repeats one, so if this page stops (closed,
//   frozen, offline) the edge's own timeout stops the robot;
// - the deadman is held only while a finger (or the mouse, Space, a gamepad shoulder button) is on it: lifting
//   it, a touchcancel, the page hidden or frozen (or not run for longer than a state stays current), the window
//   losing focus, the network lost, the screen's layout changing (a rotation) or the socket closing all release
//   it, and the release is sent at once, not on the next tick (a browser throttles the timers of a hidden or busy
//   page);
// - a release (those, the e-stop, releasing control) holds until the input is let go and pressed anew: a held
//   Space's auto-repeat, a gamepad's shoulder button still down, a key still down never take it back.
// Velocities: left stick right = +x, up = +y; right stick up = +z, sideways = turn about z (base frame), scaled
// to the speed profile's limits that the edge reports (it clips them anyway).
import { createViewer } from "/static/viewer.js";

const DEADZONE = 0.08;
const $ = (id) => document.getElementById(id);

const ui = {
  robot: $("robot"), link: $("link"), who: $("who"), force: $("force"), forceLabel: $("force-label"),
  forceDetail: $("force-detail"), status: $("status"), reason: $("reason"), control: $("control"), vitals: $("vitals"),
  profile: $("profile"), estop: $("estop"), deadman: $("deadman"), events: $("events"), camera: $("camera"),
  ultrasound: $("ultrasound"), poseList: $("pose-list"), verdict: $("pose-verdict"), goto: $("goto"), pace: $("pace"),
  cameraState: $("camera-state"), torchState: $("torch-state"), stateAge: $("state-age"), markersNote: $("markers-note"),
  actuators: $("actuators"),
};

// What tests and benchmarks read (window.iorthand): the page's own view of its round trips and video delays.
const stats = { sent: 0, echoes: [], video: { camera: [], ultrasound: [] }, videoBytes: 0, refused: [],
  socket: "connecting" };
window.iorthand = stats;

let ws = null;
let hello = null;
let lastState = null;
let lastStateAt = 0;
let mine = false;
let seq = 0;
const sentAt = new Map();
let posesToken = "";
let frame = "base"; // of the twists: the robot's base frame, or the probe's ("tool": about its tip)

// ---------------------------------------------------------------------------------------------- inputs

const input = { deadman: { pointer: false, key: false, pad: false }, left: [0, 0], right: [0, 0], keys: new Set() };
// After a release, a Space or a shoulder button still down counts only once it has been let go: a keyboard's
// auto-repeat (a keydown every ~33 ms while Space is held) re-engaged the deadman right after an e-stop clicked
// with the mouse, and the edge's STOP latch cleared on the release and new press it saw (red team, e8).
let spaceDown = false; // Space is down as far as this page knows (its keydown came, its keyup not yet)
let spaceLocked = false; // a release came while Space was down: ignore it until its keyup
let padLocked = false; // a release came: ignore the gamepad's shoulder buttons until none is pressed

function deadmanHeld() {
  return input.deadman.pointer || input.deadman.key || input.deadman.pad;
}

function releaseAll(why) {
  const was = deadmanHeld();
  input.deadman.pointer = input.deadman.key = input.deadman.pad = false;
  if (spaceDown) spaceLocked = true;
  padLocked = true;
  input.left = [0, 0];
  input.right = [0, 0];
  input.keys.clear();
  for (const s of sticks) s.centre();
  ui.deadman.classList.remove("held");
  if (was) sendTwist();
  if (was && why) logEvent({ kind: "input", status: "deadman_released", reason: `deadman released: ${why}` });
}

class Stick {
  constructor(el, onMove) {
    this.el = el;
    this.knob = el.querySelector(".knob");
    this.onMove = onMove;
    this.pointer = null;
    this.geometry = null; // the stick's centre and radius when the finger touched down
    el.addEventListener("pointerdown", (e) => this.start(e));
    el.addEventListener("pointermove", (e) => this.move(e));
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) el.addEventListener(type, (e) => this.end(e));
  }
  start(e) {
    if (this.pointer !== null) return;
    this.pointer = e.pointerId;
    // Deflection is measured from where the stick was when the finger touched it: the page's content reflowing
    // under a resting thumb (a status line wrapping) does not move the robot. A rotation moves the finger's own
    // coordinates too: that releases everything (layoutChanged).
    const r = this.el.getBoundingClientRect();
    this.geometry = { x: r.left + r.width / 2, y: r.top + r.height / 2, radius: r.width / 2 };
    this.el.setPointerCapture(e.pointerId);
    this.move(e);
    e.preventDefault();
  }
  move(e) {
    if (e.pointerId !== this.pointer || !this.geometry) return;
    const { radius } = this.geometry;
    let x = (e.clientX - this.geometry.x) / radius;
    let y = -(e.clientY - this.geometry.y) / radius; // screen up = +
    const n = Math.hypot(x, y);
    if (n > 1) { x /= n; y /= n; }
    this.knob.style.transform = `translate(${x * radius * 0.6}px, ${-y * radius * 0.6}px)`;
    this.onMove(Math.abs(x) < DEADZONE ? 0 : x, Math.abs(y) < DEADZONE ? 0 : y);
  }
  end(e) {
    if (e.pointerId !== this.pointer) return;
    this.pointer = null;
    this.centre();
  }
  centre() {
    this.pointer = null;
    this.geometry = null;
    this.knob.style.transform = "";
    this.onMove(0, 0);
  }
}

const sticks = [
  new Stick($("stick-left"), (x, y) => { input.left = [x, y]; }),
  new Stick($("stick-right"), (x, y) => { input.right = [x, y]; }),
];

let deadmanPointer = null;
ui.deadman.addEventListener("pointerdown", (e) => {
  e.preventDefault();
  if (offline()) { // what it sends waits in the socket and reaches the edge late: the press counts once online
    logEvent({ kind: "refused", status: "offline", reason: "no network: HOLD does nothing until it is back" });
    return;
  }
  deadmanPointer = e.pointerId;
  ui.deadman.setPointerCapture(e.pointerId);
  input.deadman.pointer = true;
  ui.deadman.classList.add("held");
});
for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
  ui.deadman.addEventListener(type, (e) => {
    if (e.pointerId !== deadmanPointer) return;
    deadmanPointer = null;
    input.deadman.pointer = false;
    ui.deadman.classList.remove("held");
    if (!deadmanHeld()) sendTwist();
  });
}
// A touch the browser cancels (a system gesture, a call) ends every hold, whichever element it was on.
window.addEventListener("touchcancel", () => releaseAll("touch cancelled"), { capture: true });
document.addEventListener("visibilitychange", () => {
  if (document.hidden) releaseAll("page hidden");
  else { // a hidden page's timers were throttled on purpose: watch its pace, and its gaps, anew
    pace.restart();
    lastTickAt = 0;
  }
});
window.addEventListener("pagehide", () => releaseAll("page closed"));
// A phone freezes a page in the background or under a locked screen (no timer runs: the edge's timeout stops the
// robot). The hold ends there; on return the page does not take it back, even with the finger still down.
document.addEventListener("freeze", () => releaseAll("the browser froze this page (screen locked, or in the background)"));
document.addEventListener("resume", () => logEvent({ kind: "warning", status: "resumed",
  reason: "this page runs again after being frozen: nothing moves until HOLD is pressed anew" }));
// The network lost: what the page sends waits in its socket and would reach the server in a burst on return. The
// hold ends at once, and a hold cannot start until the network is back (a finger, Space or button held since then
// counts only when pressed anew).
function offline() { return navigator.onLine === false; }
window.addEventListener("offline", () => {
  releaseAll("this device lost its network");
  logEvent({ kind: "warning", status: "offline", reason: "no network: the robot stops (the edge's timeout); "
    + "HOLD does nothing until it is back" });
});
window.addEventListener("online", () => logEvent({ kind: "info", status: "online",
  reason: "network back: press HOLD anew to move" }));
// Restored from the back-forward cache, the page would hold what it had when left (its socket closed then, its
// control released on the server): it starts afresh, as on a reload.
window.addEventListener("pageshow", (e) => { if (e.persisted) location.reload(); });
window.addEventListener("blur", () => releaseAll("window lost focus"));
// A rotation (or any change of the viewport) moves the sticks and the deadman from under the fingers, and the
// fingers' own coordinates with them: a thumb resting on a stick's centre read as a full deflection. Everything is
// let go (the robot stops); the operator presses again on the new layout.
function layoutChanged() { releaseAll("screen layout changed"); }
window.addEventListener("resize", layoutChanged);
window.addEventListener("orientationchange", layoutChanged);
screen.orientation?.addEventListener?.("change", layoutChanged);
document.addEventListener("contextmenu", (e) => e.preventDefault()); // a long press is not a menu

const KEYS = { KeyD: [0, 1], KeyA: [0, -1], KeyW: [1, 1], KeyS: [1, -1], KeyR: [2, 1], KeyF: [2, -1], KeyQ: [5, 1], KeyE: [5, -1] };
window.addEventListener("keydown", (e) => {
  if (e.code === "Space") spaceDown = true;
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  if (e.code === "Space") {
    e.preventDefault();
    // Only a press: never the auto-repeat of a held key, nor a Space held since a release (an e-stop, a blur).
    if (!e.repeat && !spaceLocked && !offline()) input.deadman.key = true;
    else if (!e.repeat && !input.deadman.key) {
      logEvent({ kind: "input", status: "deadman", reason: "let go of Space and press it again to hold the deadman" });
    }
  }
  else if (e.code === "KeyX") { estop(); }
  else if (e.code === "KeyB" && !e.repeat) { toggleFrame(); }
  else if (e.code === "KeyH" && !e.repeat) { toggleContact(); }
  else if (KEYS[e.code] && !e.repeat) input.keys.add(e.code); // a key held since a release counts once pressed anew
});
window.addEventListener("keyup", (e) => {
  if (e.code === "Space") {
    spaceDown = false;
    spaceLocked = false;
    if (input.deadman.key) {
      input.deadman.key = false;
      if (!deadmanHeld()) sendTwist();
    }
  }
  input.keys.delete(e.code);
});
window.addEventListener("gamepaddisconnected", () => releaseAll("gamepad disconnected"));

function readGamepad() {
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter(Boolean) : [];
  if (!pads.length) { input.deadman.pad = false; return null; }
  const p = pads[0];
  const dz = (v) => (Math.abs(v) < 0.12 ? 0 : v);
  const pressed = !!(p.buttons[4]?.pressed || p.buttons[5]?.pressed); // a shoulder button, held
  if (!pressed) padLocked = false; // let go since the last release: the next press counts
  else if (offline()) padLocked = true; // pressed with no network: counts once let go and pressed again
  input.deadman.pad = pressed && !padLocked;
  return { lx: dz(p.axes[0] || 0), ly: -dz(p.axes[1] || 0), rx: dz(p.axes[2] || 0), ry: -dz(p.axes[3] || 0) };
}

function twistNow(pad) {
  const safety = lastState?.safety;
  const lin = safety?.linear_limit || 0.008;
  const ang = safety?.angular_limit || 0.1;
  const v = [0, 0, 0, 0, 0, 0];
  v[0] = input.left[0] + (pad?.lx || 0);
  v[1] = input.left[1] + (pad?.ly || 0);
  v[2] = input.right[1] + (pad?.ry || 0);
  v[5] = -input.right[0] - (pad?.rx || 0);
  for (const code of input.keys) { const [axis, sign] = KEYS[code]; v[axis] += sign; }
  const clamp = (x) => Math.max(-1, Math.min(1, x));
  return {
    linear: [clamp(v[0]) * lin, clamp(v[1]) * lin, clamp(v[2]) * lin],
    angular: [clamp(v[3]) * ang, clamp(v[4]) * ang, clamp(v[5]) * ang],
  };
}

// One twist, sent now: the fixed-rate stream's tick, and a deadman let go (sent at once by the release).
function sendTwist() {
  // The gamepad first: its shoulder button is the deadman, and only this reads it (a pad has no events).
  const pad = readGamepad();
  const held = deadmanHeld() && !document.hidden;
  ui.deadman.classList.toggle("held", held);
  if (!ws || ws.readyState !== WebSocket.OPEN || !mine) return;
  const t = held ? twistNow(pad) : { linear: [0, 0, 0], angular: [0, 0, 0] };
  const round = (a) => a.map((x) => Math.round(x * 1e6) / 1e6);
  seq += 1;
  sentAt.set(seq, performance.now());
  if (sentAt.size > 600) sentAt.delete(sentAt.keys().next().value);
  ws.send(JSON.stringify({ type: "twist", id: seq, linear: round(t.linear), angular: round(t.angular), deadman: held,
    seen: lastState?.t || 0, frame }));
  stats.sent += 1;
}
// The fixed-rate stream: a timer at the server's rate, never input events (a release aside).
let stream = null;
let lastTickAt = 0;
function startStream(hz) {
  clearInterval(stream);
  pace.restart();
  lastTickAt = 0;
  stream = setInterval(() => {
    // A page that did not run for longer than its screen's bound for a current state (frozen by the browser with no
    // freeze event, the device asleep) acted on nothing in that time: the hold ends, and needs a fresh press.
    const now = performance.now();
    const gap = lastTickAt ? now - lastTickAt : 0;
    lastTickAt = now;
    if (hello && gap > hello.state_stale_s * 1000) {
      releaseAll(`this page did not run for ${(gap / 1000).toFixed(1)} s (frozen, or the device asleep)`);
    }
    pace.tick();
    sendTwist();
  }, 1000 / hz);
}

// The page's own pace. A busy page (slow drawing on a weak phone) runs the stream's timer late, and the edge stops
// the robot at every gap longer than its command timeout (150 ms by default): the operator sees motion stop and
// start. Over the last second of holding control, fewer than PACE_SLOW of the configured ticks, or a gap of
// PACE_GAP_MS or more, says so on the page, with what helps.
const PACE_WINDOW_MS = 1000;
const PACE_SLOW = 0.75;
const PACE_GAP_MS = 100;
// Late this long without a break, the page draws its 3D view at one pixel per CSS pixel: on a phone's 2–3× screen
// that is a quarter to a ninth of the pixels, and what made the page late in the measurements (README).
const PACE_LOWER_3D_MS = 2000;
const pace = {
  ticks: [], since: 0, slow: false, slowSince: 0, lowered: false,
  restart() { this.ticks = []; this.since = performance.now(); },
  tick() {
    const now = performance.now();
    this.ticks.push(now);
    while (this.ticks.length > 1 && now - this.ticks[1] > PACE_WINDOW_MS) this.ticks.shift(); // one before the window
  },
  // Ticks a second and the longest gap (ms, the one still open included), once a whole window was watched.
  measure(now) {
    if (!mine || document.hidden || now - this.since < PACE_WINDOW_MS) return null;
    const inWindow = this.ticks.filter((t) => now - t <= PACE_WINDOW_MS).length;
    let gap = this.ticks.length ? now - this.ticks[this.ticks.length - 1] : now - this.since;
    for (let i = 1; i < this.ticks.length; i++) gap = Math.max(gap, this.ticks[i] - this.ticks[i - 1]);
    return { rate: (inWindow * 1000) / PACE_WINDOW_MS, gap };
  },
};
function showPace() {
  const hz = hello?.twist_hz || 0;
  const now = performance.now();
  const m = hz ? pace.measure(now) : null;
  const slow = !!m && (m.rate < PACE_SLOW * hz || m.gap >= PACE_GAP_MS);
  stats.pace = m ? { rate: m.rate, gap: m.gap, slow } : null;
  ui.pace.hidden = !slow;
  if (slow) {
    const sent = `${Math.round(m.rate)} of ${Math.round(hz)} commands`;
    const gaps = `gaps up to ${Math.round(m.gap)} ms: the robot stops at every gap over the edge's timeout`;
    ui.pace.textContent = `page ${Math.round(m.rate)}/${Math.round(hz)}`; // short on a phone's bar; details in its title
    ui.pace.title = `this page sent ${sent} in the last second, with ${gaps}`;
    if (!pace.slow) {
      pace.slowSince = now;
      logEvent({ kind: "warning", status: "slow page", reason: `this device sends ${sent} a second (${gaps}). `
        + "Turning off the 3D view or the video helps." });
    }
    if (!pace.lowered && viewer && want3d.checked && (window.devicePixelRatio || 1) > 1
        && now - pace.slowSince >= PACE_LOWER_3D_MS) {
      pace.lowered = true;
      viewer.setPixelRatio(1);
      logEvent({ kind: "warning", status: "slow page", reason: "the 3D view is now drawn at a lower resolution, "
        + "to keep the commands on time" });
    }
  }
  pace.slow = slow;
}

// ---------------------------------------------------------------------------------------------- the socket

function connect() {
  const robot = new URLSearchParams(location.search).get("robot") || "";
  ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${robot ? `?robot=${encodeURIComponent(robot)}` : ""}`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => {
    stats.socket = "open";
    ws.send(JSON.stringify({ type: "view", video: $("want-video").checked }));
  };
  ws.onmessage = (e) => (typeof e.data === "string" ? onMessage(JSON.parse(e.data)) : onVideo(e.data));
  ws.onclose = (e) => {
    stats.socket = "closed";
    mine = false;
    releaseAll("connection to the console's server lost");
    if (e.code === 4429) { // too many pages of this log-in or user: said why; tried again now and then
      stats.socket = "refused";
      setStatus("refused", e.reason || "too many pages open", "red");
      setTimeout(connect, 10_000);
      return;
    }
    setStatus("disconnected", `connection closed (${e.code}${e.reason ? `: ${e.reason}` : ""}): reconnecting…`, "grey");
    fetch("/api/me").then((r) => { if (r.status === 401) location.assign("/login"); else setTimeout(connect, 1000); })
      .catch(() => setTimeout(connect, 2000));
  };
}

function onMessage(m) {
  switch (m.type) {
    case "hello":
      hello = m;
      startStream(m.twist_hz);
      ui.robot.textContent = m.robot;
      ui.who.textContent = `${m.user} (${m.role})`;
      document.body.classList.toggle("viewer", !m.may_command);
      // The deployment's profiles, in its order (the console settings the terminal console cycles through).
      ui.profile.replaceChildren(...m.profiles.map((p) => new Option(p, p)));
      if (lastState?.safety?.profile) ui.profile.value = lastState.safety.profile;
      $("viewer-note").hidden = m.may_command;
      break;
    case "state": onState(m); break;
    case "echo": {
      const t0 = sentAt.get(m.id);
      if (t0 !== undefined) {
        sentAt.delete(m.id);
        stats.echoes.push([m.id, performance.now() - t0, m.accepted]);
        if (stats.echoes.length > 20000) stats.echoes.splice(0, 10000);
      }
      break;
    }
    case "refused":
      stats.refused.push(m);
      logEvent({ kind: "refused", status: m.kind, reason: m.reason });
      break;
    case "reply":
      logEvent({ kind: m.ok ? "info" : "refused", status: m.to, reason: m.reason });
      if (m.to === "preview") {
        ui.verdict.textContent = `${m.name}: ${m.reason}`;
        ui.verdict.className = `verdict ${m.ok ? "ok" : "bad"}`;
        posesToken = m.ok ? m.token : "";
        ui.goto.disabled = !posesToken;
      }
      break;
    case "poses":
      ui.poseList.replaceChildren(...m.poses.map((p) => new Option(p, p)));
      break;
    default: break;
  }
}

const VIDEO_NAMES = ["camera", "ultrasound"];
const HEADER_BYTES = 14; // stream u8, capture time u64 (ns), sequence u32, flags u8 (1: H.264, 2: keyframe, 4: failure)
const objectUrls = {};
// When each stream's picture on screen arrived (performance.now(); 0: none shown, or a failure notice in its place).
const pictureAt = { camera: 0, ultrasound: 0 };
const decoders = {}; // per stream: the WebCodecs H.264 decoder and the capture times of the frames in it

function recordDelay(name, captureMs, bytes) {
  const delayMs = Date.now() - captureMs;
  const list = stats.video[name];
  list.push(delayMs);
  stats.videoBytes += bytes;
  if (list.length > 5000) list.splice(0, 2500);
  $(`${name}-age`).textContent = `${Math.max(0, delayMs).toFixed(0)} ms`;
  $(`${name}-age`).closest("figure").classList.remove("failed", "not-live");
  pictureAt[name] = performance.now();
}

// A stream that goes silent with no failure notice (a dead link, frames lost on the way) leaves its last picture on
// screen: past the server's bound for that stream (three of its frame periods, at least a second) it is dimmed and
// crossed out, and says for how long there has been no picture; the next picture makes it live again.
function showPictureAges(now) {
  for (const name of VIDEO_NAMES) {
    const bound = lastState?.picture_stale_s?.[name];
    const quiet = (now - pictureAt[name]) / 1000;
    if (!pictureAt[name] || !bound || quiet <= bound) continue;
    const note = `no picture for ${quiet.toFixed(1)} s`;
    $(`${name}-age`).textContent = note;
    ui[name].alt = `${name}: ${note}: the picture shown is from before`;
    ui[name].closest("figure").classList.add("not-live");
  }
}

// No picture, and why (the edge's reason, as text): in place of the last one, which would read as live.
function showNoPicture(name, reason) {
  const img = ui[name];
  img.removeAttribute("src");
  img.hidden = false;
  $(`${name}-video`).hidden = true;
  img.alt = `${name}: no picture: ${reason}`;
  $(`${name}-age`).textContent = `no picture: ${reason}`;
  img.closest("figure").classList.add("failed");
  img.closest("figure").classList.remove("not-live");
  pictureAt[name] = 0;
}

function h264Decoder(name) {
  if (decoders[name]) return decoders[name];
  const canvas = $(`${name}-video`);
  const entry = { captured: new Map(), ready: false, failed: "" };
  entry.decoder = new VideoDecoder({
    output: (frame) => {
      const capture = entry.captured.get(frame.timestamp);
      entry.captured.delete(frame.timestamp);
      if (canvas.width !== frame.displayWidth) { canvas.width = frame.displayWidth; canvas.height = frame.displayHeight; }
      canvas.getContext("2d").drawImage(frame, 0, 0);
      frame.close();
      // Shown once a frame is drawn: after a failure notice the canvas still holds the picture from before it.
      ui[name].hidden = true;
      canvas.hidden = false;
      if (capture) recordDelay(name, capture.ms, capture.bytes);
    },
    error: (e) => { entry.failed = e.message; entry.ready = false; delete decoders[name]; },
  });
  // Annex B (no description): the stream carries its SPS/PPS at every keyframe.
  entry.decoder.configure({ codec: "avc1.42E01E", optimizeForLatency: true });
  decoders[name] = entry;
  return entry;
}

function onVideo(buffer) {
  const view = new DataView(buffer);
  const name = VIDEO_NAMES[view.getUint8(0)];
  const tNs = view.getBigUint64(1);
  const flags = view.getUint8(13);
  const data = buffer.slice(HEADER_BYTES);
  const img = ui[name];
  const canvas = $(`${name}-video`);
  if (flags & 4) { // the edge's failure notice: the source gives no frames, and the data says why
    showNoPicture(name, new TextDecoder().decode(data));
    return;
  }
  if (!data.byteLength) {
    showNoPicture(name, "an empty frame");
    return;
  }
  const captureMs = Number(tNs / 1000000n);
  if (flags & 1) { // H.264: decoded by the browser, drawn on the canvas
    if (typeof VideoDecoder === "undefined") {
      img.hidden = false;
      canvas.hidden = true;
      img.alt = `${name}: this browser cannot decode H.264 video (WebCodecs)`;
      return;
    }
    const entry = h264Decoder(name);
    const key = (flags & 2) !== 0;
    if (!entry.ready && !key) return; // a decoder starts at a keyframe
    entry.ready = true;
    const timestamp = Number(tNs / 1000n); // µs
    entry.captured.set(timestamp, { ms: captureMs, bytes: buffer.byteLength });
    if (entry.captured.size > 120) entry.captured.delete(entry.captured.keys().next().value);
    entry.decoder.decode(new EncodedVideoChunk({ type: key ? "key" : "delta", timestamp, data }));
    return;
  }
  recordDelay(name, captureMs, buffer.byteLength); // JPEG: a picture of its own
  img.hidden = false;
  img.alt = name;
  canvas.hidden = true;
  const url = URL.createObjectURL(new Blob([data], { type: "image/jpeg" }));
  const old = objectUrls[name];
  objectUrls[name] = url;
  img.src = url;
  if (old) URL.revokeObjectURL(old);
}

// ---------------------------------------------------------------------------------------------- drawing

let viewer = null;
try { viewer = createViewer($("view3d")); } catch (e) { $("view3d").replaceWith(`3D view unavailable: ${e.message}`); }

function setStatus(code, reason, colour) {
  ui.status.textContent = code;
  ui.status.className = `status-code ${colour || ""}`;
  ui.reason.textContent = reason || "";
}

// A value whose source went quiet, as the terminal console shows it: "pan +5° tilt -3° (stale 2.2 s)", greyed. The
// server says which are old and how old (the client's rules); "" while current.
function aged(text, stale) {
  return stale ? `${text} (${stale})` : text;
}

function degrees(rad) {
  const d = Math.round((rad * 180) / Math.PI);
  return `${d >= 0 ? "+" : ""}${d}°`;
}

function showActuators(s) {
  const servo = s.servo;
  ui.cameraState.textContent = servo ? aged(`camera pan ${degrees(servo.pan)} tilt ${degrees(servo.tilt)}`, servo.stale)
    : "camera —";
  ui.cameraState.classList.toggle("stale", !!servo?.stale);
  const torch = s.torch;
  ui.torchState.textContent = torch
    ? aged(`torch ${torch.on ? "on" : "off"} ${Math.round(torch.brightness * 100)} %`, torch.stale) : "torch —";
  ui.torchState.classList.toggle("stale", !!torch?.stale);
}

function onState(s) {
  lastState = s;
  lastStateAt = performance.now();
  document.body.classList.remove("no-feed");
  if (!!s.control?.mine !== mine) pace.restart();
  mine = !!s.control?.mine;
  const sf = s.safety;
  const old = sf?.stale || ""; // the safety status behind status, reason, armed, owner, profile and contact
  if (!s.online) setStatus("edge offline", "the robot's edge agent is not connected", "grey");
  else if (sf) {
    const c = s.commanded || [0, 0, 0];
    const speed = Math.hypot(c[0], c[1], c[2]) * 1000;
    // Said only from a current state: an old one's speed is not how the robot moves now.
    const moving = speed > 0.05 && !s.state_stale
      ? `moving at ${speed.toFixed(1)} mm/s (limit ${(sf.linear_limit * 1000).toFixed(0)} mm/s, ${sf.profile})` : "";
    const reason = s.hint || sf.reason || moving || (sf.armed ? "" : "not armed");
    // Old: never green nor red as if current, and its age said.
    setStatus(aged(sf.status, old), reason, old ? "grey" : HALTS.has(sf.status) ? "red" : sf.status === "ok" ? "green" : "");
  }
  ui.stateAge.hidden = !s.state_stale;
  ui.stateAge.textContent = s.state_stale ? `robot state ${s.state_stale}: the arm is shown where it was then` : "";
  ui.markersNote.textContent = s.markers_note ? `· markers: ${s.markers_note}` : "";
  ui.markersNote.classList.toggle("failed", !!s.markers_failed); // the camera failed: not "no marker in view"
  showActuators(s);
  const f = s.force || {};
  ui.force.className = `force ${f.colour || "grey"}`;
  ui.forceLabel.textContent = f.label || "NO DATA";
  ui.forceDetail.textContent = f.detail || "";
  ui.vitals.textContent = s.vitals ? `patient: ${s.vitals}` : "";
  if (s.link) {
    const fmt = (v) => (v == null ? "—" : v.toFixed(1));
    // A dead link says so: its last round trips are not how it is now.
    const rtt = `RTT ${fmt(s.link.rtt_p50)}/${fmt(s.link.rtt_p95)} ms`;
    ui.link.textContent = s.link.no_state
      ? `no robot state for ${s.link.no_state.toFixed(1)} s${s.link.rtt_old ? ` (${rtt} ${s.link.rtt_old.toFixed(1)} s ago)` : ""}`
      : `${rtt} · loss ${((s.link.loss_up || 0) * 100).toFixed(1)} %`;
    ui.link.className = `pill ${s.link.colour}`;
  }
  const owner = sf?.owner || "";
  // Another page of this console holds it (this user's other device or tab, or another user's): said as such.
  const other = s.control?.elsewhere || "";
  const elsewhere = `controlled by ${other === hello?.user ? "you" : other} on another page`;
  ui.control.textContent = mine ? "Release control" : other ? elsewhere
    : owner ? aged(`controlled by ${owner}`, old) : "Take control";
  ui.control.classList.toggle("mine", mine);
  ui.control.classList.toggle("stale", !!old && !mine);
  if (sf?.profile && document.activeElement !== ui.profile) ui.profile.value = sf.profile;
  ui.profile.classList.toggle("stale", !!old);
  ui.deadman.disabled = !mine;
  const contact = sf?.contact ?? -1;
  $("contact").textContent = contact >= 0 ? aged(`contact ${contact} N`, old) : "contact";
  $("contact").classList.toggle("on", contact >= 0 && !old);
  if (sf?.task) ui.reason.textContent = aged(sf.task, old);
  for (const e of s.events || []) logEvent(e);
  if (viewer && want3d.checked) viewer.update(s);
}

const HALTS = new Set(["disarmed", "command_timeout", "force_danger", "force_stale", "stopped", "fault", "owner_lost", "link_gap", "stale_view"]);

// Never green without fresh data: with nothing from the console's server for its bound (the hello's state_stale_s,
// the terminal console's), every value on the page is that old: the light, the status and the rows go grey, aged.
setInterval(() => {
  showPace();
  showPictureAges(performance.now());
  const quiet = (performance.now() - lastStateAt) / 1000;
  if (lastState && hello && quiet > hello.state_stale_s) {
    const note = `no data from the console's server for ${quiet.toFixed(1)} s`;
    document.body.classList.add("no-feed");
    ui.force.className = "force grey";
    ui.forceLabel.textContent = "STALE";
    ui.forceDetail.textContent = note;
    setStatus(aged(lastState.safety?.status || "no data", `stale ${quiet.toFixed(1)} s`),
      `${note}: every value shown is at least that old`, "grey");
  }
}, 100);

function logEvent(e) {
  const li = document.createElement("li");
  li.className = e.kind;
  const t = e.t ? new Date(e.t * 1000) : new Date();
  li.textContent = `${t.toLocaleTimeString()} ${e.status}: ${e.reason}`;
  ui.events.prepend(li);
  while (ui.events.children.length > 60) ui.events.lastChild.remove();
}

// ---------------------------------------------------------------------------------------------- buttons

function send(obj) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj));
}

function estop() {
  releaseAll("");
  send({ type: "stop" });
  logEvent({ kind: "stop", status: "stopped", reason: "e-stop sent" });
}

ui.estop.addEventListener("click", estop);
function toggleFrame() {
  frame = frame === "base" ? "tool" : "base";
  $("frame").textContent = frame === "tool" ? "probe" : "base";
  $("frame").classList.toggle("tool", frame === "tool");
  logEvent({ kind: "info", status: "frame", reason: frame === "tool" ? "moving in the probe's frame (about its tip)"
    : "moving in the robot's base frame" });
}
$("frame").addEventListener("click", toggleFrame);
function toggleContact() {
  const on = (lastState?.safety?.contact ?? -1) >= 0;
  send({ type: on ? "contact_off" : "contact_on" });
}
$("contact").addEventListener("click", toggleContact);
ui.control.addEventListener("click", () => {
  if (mine) { releaseAll(""); send({ type: "release" }); } else send({ type: "acquire", profile: ui.profile.value });
});
ui.profile.addEventListener("change", () => { if (mine) send({ type: "acquire", profile: ui.profile.value }); });
// One step of the deployment's pan_tilt_step_deg (its hello's) in the button's direction.
for (const b of document.querySelectorAll("[data-pan],[data-tilt]")) {
  const step = (direction) => (Number(direction || 0) * (hello?.pan_tilt_step_deg || 0) * Math.PI) / 180;
  b.addEventListener("click", () => send({ type: "camera", pan: step(b.dataset.pan), tilt: step(b.dataset.tilt) }));
}
$("torch").addEventListener("click", () => send({ type: "camera", torch: !(lastState?.torch?.on) }));
$("poses").addEventListener("click", () => send({ type: "poses" }));
$("preview").addEventListener("click", () => { if (ui.poseList.value) send({ type: "preview", name: ui.poseList.value }); });
ui.goto.addEventListener("click", () => {
  send({ type: "goto", name: ui.poseList.value, token: posesToken });
  ui.goto.disabled = true;
  posesToken = "";
});
// What to draw: a slow link or a tired phone can do without video or the 3D view (remembered on this device).
const want3d = $("want-3d");
for (const [box, key] of [[$("want-video"), "iorthand.video"], [want3d, "iorthand.3d"]]) {
  box.checked = localStorage.getItem(key) !== "off";
  box.addEventListener("change", () => {
    localStorage.setItem(key, box.checked ? "on" : "off");
    send({ type: "view", video: $("want-video").checked });
    $("view3d").closest("figure").hidden = !want3d.checked;
    for (const name of VIDEO_NAMES) ui[name].closest("figure").hidden = !$("want-video").checked;
    if (!$("want-video").checked) for (const name of VIDEO_NAMES) delete decoders[name]; // restart at a keyframe
  });
  box.dispatchEvent(new Event("change"));
}

$("logout").addEventListener("click", async () => {
  releaseAll("");
  await fetch("/api/logout", { method: "POST" });
  location.assign("/login");
});

connect();

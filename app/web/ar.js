// slloc AR client (served at /ar): localizes the live camera through the API every few
// seconds or on demand, shows the pose and its confidence, and draws the map's reference
// cameras over the video at the localized pose with three.js.
//
// Conventions. The API's cam_from_world is COLMAP's (x_cam = R·x_world + t; camera x right,
// y down, z forward); the page asks for `output.frames: ["opengl"]` as well and places the
// three.js camera with that world_from_cam (camera x right, y up, z backward, the map frame
// as it is), so no axis flip is done here. The projection is the pinhole of the intrinsics
// sent (COLMAP pixels: the image spans [0, width] × [0, height], the centre of the top-left
// pixel is (0.5, 0.5)), mapped onto the overlay, which covers the video's box exactly.
//
// Every answer is appended to window.arLog with a thumbnail of its frame (and dispatched as
// an "ar-answer" event).
// Query string: ?map=ID&key=KEY&interval=SECONDS&focal=PX&depth=FRUSTUM_DEPTH&auto=0 (the key
// is moved into the tab's sessionStorage and taken out of the address bar).

import { rotation, toWorld } from "./geometry.js";

const KEY_STORAGE = "slloc.apiKey"; // shared with the viewer
const MAX_IMAGES = 5000; // reference frusta drawn per map
const MAX_LOG = 1000; // answers kept in window.arLog
const MAX_THUMBNAILS = 100; // of them, the last ones keep their frame (a small JPEG)
const THUMB_WIDTH = 160; // px
const JPEG_QUALITY = 0.9;
const MIN_INTERVAL_S = 0.2;
const DEFAULT_DEPTH = 0.75; // of the frusta, × the references' median distance from their centre
const COLORS = { reference: [0.0, 0.9, 1.0], inliers: [0.2, 1.0, 0.3] };

const $ = (id) => document.getElementById(id);
const state = {
  mapId: null,
  images: [], // the map's reference images, in frustum order
  imageIndex: new Map(), // image id → index in `images`
  referenceCamera: null,
  stream: null,
  canvas: null, // the frame at full size, encoded for the upload
  thumb: null, // its thumbnail
  inFlight: false,
  lastStart: -Infinity,
  timer: null,
  seq: 0,
  overlay: null,
  lastAnswer: null, // the last localized answer, drawn in the overlay
};
window.arLog = [];

// --- API --------------------------------------------------------------------------------

function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const key = sessionStorage.getItem(KEY_STORAGE);
  if (key) headers.set("X-API-Key", key);
  return fetch(path, { ...options, headers });
}

// "HTTP 401 Unauthorized: missing or unknown X-API-Key" from a problem+json answer
async function problemText(response) {
  let detail = response.statusText;
  try {
    const problem = await response.json();
    detail = `${problem.title}: ${problem.detail}`;
  } catch (_) { /* not a problem document */ }
  return `HTTP ${response.status} ${detail}`;
}

async function apiJson(path) {
  const response = await api(path);
  if (!response.ok) throw new Error(await problemText(response));
  return response.json();
}

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

// --- intrinsics -------------------------------------------------------------------------

function pinhole(camera) {
  const p = camera.params;
  // COLMAP parameter order: SIMPLE_* and RADIAL start with one focal length f, cx, cy
  if (camera.model.startsWith("SIMPLE") || camera.model === "RADIAL") {
    return { fx: p[0], fy: p[0], cx: p[1], cy: p[2] };
  }
  return { fx: p[0], fy: p[1], cx: p[2], cy: p[3] };
}

// the camera most of the map's references share
function commonCamera(images) {
  const counts = new Map();
  for (const image of images) {
    const key = JSON.stringify(image.camera);
    counts.set(key, (counts.get(key) || 0) + 1);
  }
  let best = null;
  let bestCount = 0;
  for (const [key, count] of counts) {
    if (count > bestCount) [best, bestCount] = [key, count];
  }
  return best ? JSON.parse(best) : null;
}

// The camera sent with a frame of width × height (null: the service estimates the focal
// length). "reference": the map's reference camera as it is for frames of its size, scaled for
// a uniform resize of it, else its horizontal field of view with the principal point centred.
function queryCamera(width, height) {
  const mode = $("intrinsics").value;
  if (mode === "estimate") return null;
  if (mode === "focal") {
    const f = Number($("focal").value);
    if (!(f > 0)) throw new Error("give a focal length in pixels, or pick another intrinsics source");
    return { model: "PINHOLE", width, height, params: [f, f, width / 2, height / 2] };
  }
  const reference = state.referenceCamera;
  if (!reference) return null;
  if (reference.width === width && reference.height === height) return reference;
  const { fx, fy, cx, cy } = pinhole(reference);
  const sx = width / reference.width;
  if (Math.abs(reference.height * sx - height) <= 1) {
    const sy = height / reference.height;
    return { model: "PINHOLE", width, height, params: [fx * sx, fy * sy, cx * sx, cy * sy] };
  }
  return { model: "PINHOLE", width, height, params: [fx * sx, fy * sx, width / 2, height / 2] };
}

// --- overlay (three.js) -----------------------------------------------------------------

async function loadThree() {
  try {
    return await import("three");
  } catch (error) {
    $("overlay-note").textContent =
      "Overlay off: three.js is not installed on the server (run scripts/build_web.sh). " +
      "Localization still works.";
    return null;
  }
}

// OpenGL projection of a pinhole camera (fx, fy, cx, cy) over a width × height image, looking
// along −z: pixel u ∈ [0, width] ↦ NDC x ∈ [−1, 1], v ∈ [0, height] (down) ↦ NDC y ∈ [1, −1].
function projectionMatrix(THREE, camera, near, far) {
  const { fx, fy, cx, cy } = pinhole(camera);
  const { width: w, height: h } = camera;
  return new THREE.Matrix4().set(
    (2 * fx) / w, 0, 1 - (2 * cx) / w, 0,
    0, (2 * fy) / h, (2 * cy) / h - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
}

function setUpOverlay(THREE) {
  const container = $("overlay");
  const renderer = new THREE.WebGLRenderer({ antialias: true, alpha: true, preserveDrawingBuffer: true });
  renderer.setClearColor(0x000000, 0);
  renderer.setPixelRatio(window.devicePixelRatio);
  container.append(renderer.domElement);
  const scene = new THREE.Scene();
  const camera = new THREE.Camera();
  const overlay = { THREE, renderer, scene, camera, frusta: null, intrinsics: null, scale: 1 };
  overlay.render = () => renderer.render(scene, camera);
  const resize = () => {
    renderer.setSize(Math.max(container.clientWidth, 1), Math.max(container.clientHeight, 1), false);
    overlay.render();
  };
  new ResizeObserver(resize).observe(container);
  // the page's own projection, for checks: pixel (u, v) of a world point under the shown pose
  window.arOverlay = {
    project(point) {
      if (!overlay.intrinsics) return null;
      const v = new THREE.Vector3(...point).project(camera);
      const { width, height } = overlay.intrinsics;
      return [((v.x + 1) / 2) * width, ((1 - v.y) / 2) * height, v.z];
    },
  };
  return overlay;
}

// one LineSegments of every reference's frustum (apex to the image corners at the depth the
// user gives, by default DEFAULT_DEPTH × the references' median distance from their mean
// centre, and the rim), in coordinates relative to that centre (float32 keeps its precision).
// Seen from among the references, frusta only reach into the view when they are about as deep
// as the scene is far.
function drawFrusta(overlay, images) {
  const { THREE, scene } = overlay;
  if (overlay.frusta) {
    scene.remove(overlay.frusta);
    overlay.frusta.geometry.dispose();
    overlay.frusta = null;
  }
  $("overlay").dataset.frusta = "0";
  if (!images.length) return;
  const poses = images.map((image) => {
    const R = rotation(image.cam_from_world.rotation);
    return { R, t: image.cam_from_world.translation, camera: image.camera };
  });
  const centres = poses.map(({ R, t }) => toWorld(R, t, [0, 0, 0]));
  const mid = [0, 1, 2].map((k) => centres.reduce((s, c) => s + c[k], 0) / centres.length);
  const spread = centres.map((c) => Math.hypot(c[0] - mid[0], c[1] - mid[1], c[2] - mid[2]))
    .sort((a, b) => a - b);
  const radius = Math.max(spread[Math.floor(spread.length / 2)], 1e-3);
  overlay.scale = radius;
  const defaultDepth = DEFAULT_DEPTH * radius;
  $("depth").placeholder = defaultDepth.toPrecision(2);
  const given = Number($("depth").value);
  const depth = $("depth").value && given > 0 ? given : defaultDepth;
  $("overlay").dataset.depth = String(depth);
  const positions = new Float32Array(images.length * 16 * 3);
  const colors = new Float32Array(images.length * 16 * 3);
  let n = 0;
  poses.forEach(({ R, t, camera }) => {
    const { fx, fy, cx, cy } = pinhole(camera);
    const corners = [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]];
    const apex = toWorld(R, t, [0, 0, 0]);
    const rim = corners.map(([u, v]) =>
      toWorld(R, t, [((u - cx) / fx) * depth, ((v - cy) / fy) * depth, depth]));
    for (let i = 0; i < 4; i++) {
      for (const p of [apex, rim[i], rim[i], rim[(i + 1) % 4]]) {
        positions.set([p[0] - mid[0], p[1] - mid[1], p[2] - mid[2]], n * 3);
        colors.set(COLORS.reference, n * 3);
        n++;
      }
    }
  });
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
  overlay.frusta = new THREE.LineSegments(
    geometry, new THREE.LineBasicMaterial({ vertexColors: true }));
  overlay.frusta.position.set(...mid);
  overlay.frusta.frustumCulled = false;
  scene.add(overlay.frusta);
  $("overlay").dataset.frusta = String(images.length);
}

// references with inliers in the answer in their own colour
function highlight(overlay, retrieved) {
  if (!overlay.frusta) return;
  const attribute = overlay.frusta.geometry.getAttribute("color");
  const colors = attribute.array;
  for (let n = 0; n < colors.length / 3; n++) colors.set(COLORS.reference, n * 3);
  for (const ref of retrieved || []) {
    const index = state.imageIndex.get(ref.image_id);
    if (index === undefined || !(ref.num_inliers > 0)) continue;
    for (let n = index * 16; n < (index + 1) * 16; n++) colors.set(COLORS.inliers, n * 3);
  }
  attribute.needsUpdate = true;
}

// the overlay's camera at the answer's pose: projection from the intrinsics the frame was
// localized with, placement from its OpenGL world_from_cam
function showPose(overlay, answer, intrinsics) {
  const { THREE, camera } = overlay;
  const pose = answer.world_from_cam && answer.world_from_cam.opengl;
  if (!pose || !intrinsics) {
    $("overlay").dataset.shown = "false";
    return;
  }
  const near = overlay.scale / 1000;
  const far = overlay.scale * 1000;
  camera.projectionMatrix.copy(projectionMatrix(THREE, intrinsics, near, far));
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  new THREE.Matrix4().set(...pose.matrix.flat())
    .decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
  overlay.intrinsics = intrinsics;
  highlight(overlay, answer.retrieved);
  overlay.render();
  $("overlay").dataset.shown = "true";
}

function hideOverlay() {
  $("overlay").dataset.shown = "false";
}

// --- camera -----------------------------------------------------------------------------

async function startCamera() {
  if (!navigator.mediaDevices || !navigator.mediaDevices.getUserMedia) {
    setStatus("no camera: this browser gives pages one only over https or on localhost", true);
    return;
  }
  try {
    state.stream = await navigator.mediaDevices.getUserMedia({
      audio: false,
      video: { facingMode: { ideal: "environment" }, width: { ideal: 640 }, height: { ideal: 480 } },
    });
  } catch (error) {
    setStatus(`camera: ${error.name}: ${error.message}`, true);
    return;
  }
  const video = $("video");
  video.srcObject = state.stream;
  await new Promise((resolve) => {
    if (video.readyState >= 1) resolve();
    else video.addEventListener("loadedmetadata", resolve, { once: true });
  });
  await video.play().catch(() => {});
  video.dataset.size = `${video.videoWidth}x${video.videoHeight}`;
}

// the current video frame as a JPEG at the video's own size
async function captureFrame() {
  const video = $("video");
  const width = video.videoWidth;
  const height = video.videoHeight;
  if (!width || !height) throw new Error("the camera gives no frames yet");
  const canvas = state.canvas || (state.canvas = document.createElement("canvas"));
  canvas.width = width;
  canvas.height = height;
  canvas.getContext("2d").drawImage(video, 0, 0, width, height);
  const capturedAt = Date.now();
  const blob = await new Promise((resolve, reject) => canvas.toBlob(
    (b) => (b ? resolve(b) : reject(new Error("the frame could not be encoded"))),
    "image/jpeg", JPEG_QUALITY));
  // a small copy of the frame, shown beside its answer and kept with it in the log
  const thumb = state.thumb || (state.thumb = document.createElement("canvas"));
  thumb.width = THUMB_WIDTH;
  thumb.height = Math.round((THUMB_WIDTH * height) / width);
  thumb.getContext("2d").drawImage(canvas, 0, 0, thumb.width, thumb.height);
  const thumbnail = thumb.toDataURL("image/jpeg", 0.8);
  return { blob, width, height, capturedAt, thumbnail };
}

// --- localize ---------------------------------------------------------------------------

function record(entry) {
  window.arLog.push(entry);
  if (window.arLog.length > MAX_LOG) window.arLog.splice(0, window.arLog.length - MAX_LOG);
  const old = window.arLog[window.arLog.length - 1 - MAX_THUMBNAILS];
  if (old) old.frame = null;
  window.dispatchEvent(new CustomEvent("ar-answer", { detail: entry }));
}

async function localizeOnce(trigger) {
  if (state.inFlight || !state.mapId || !state.stream) return;
  state.inFlight = true;
  state.lastStart = performance.now();
  const mapId = state.mapId;
  const entry = {
    seq: ++state.seq, trigger, map_id: mapId, captured_at: null, width: null, height: null,
    frame: null,
    camera: null, http_status: null, request_id: null, latency_ms: null, localized: false,
    reason: null, confidence: null, num_inliers: null, cam_from_world: null,
    camera_center: null, world_from_cam: null, error: null,
  };
  $("localize-now").disabled = true;
  setOutcome("busy", "Localizing…");
  try {
    const frame = await captureFrame();
    Object.assign(entry, {
      captured_at: frame.capturedAt, width: frame.width, height: frame.height,
      frame: frame.thumbnail,
    });
    $("frame").src = frame.thumbnail;
    const camera = queryCamera(frame.width, frame.height);
    entry.camera = camera;
    const params = { output: { frames: ["opengl"] } };
    if (camera) params.camera = camera;
    const form = new FormData();
    form.append("image", frame.blob, "frame.jpg");
    form.append("params", JSON.stringify(params));
    const start = performance.now();
    const response = await api(`/v1/maps/${mapId}/localize`, { method: "POST", body: form });
    entry.http_status = response.status;
    entry.request_id = response.headers.get("X-Request-ID");
    if (!response.ok) throw new Error(await problemText(response));
    const answer = await response.json();
    entry.latency_ms = performance.now() - start;
    Object.assign(entry, {
      localized: answer.localized, reason: answer.reason, confidence: answer.confidence,
      num_inliers: answer.num_inliers, cam_from_world: answer.cam_from_world,
      camera_center: answer.camera_center, world_from_cam: answer.world_from_cam,
      estimator_used: answer.estimator_used, retrieved: answer.retrieved,
      camera_used: answer.camera,
    });
    if (mapId === state.mapId) showAnswer(entry, answer);
  } catch (error) {
    entry.error = error.message;
    if (mapId === state.mapId) showFailure(`Failed: ${error.message}`);
  } finally {
    record(entry);
    state.inFlight = false;
    $("localize-now").disabled = !state.mapId;
  }
}

function setOutcome(kind, text) {
  $("outcome").dataset.state = kind;
  $("outcome").textContent = text;
}

function showFailure(text) {
  setOutcome("failed", text);
  $("pose").replaceChildren();
  hideOverlay();
}

function showAnswer(entry, answer) {
  const latency = `${entry.latency_ms.toFixed(0)} ms`;
  if (!answer.localized) {
    const hint = answer.candidate
      ? ` (a candidate pose had confidence ${answer.confidence.toFixed(2)})` : "";
    showFailure(`Not localized: ${answer.reason}${hint}; ${latency}`);
    return;
  }
  setOutcome("localized",
    `Localized, confidence ${answer.confidence.toFixed(2)} (${answer.num_inliers} inliers, ` +
    `${answer.estimator_used || answer.estimator}, ${latency})`);
  const gl = answer.world_from_cam.opengl;
  const fmt = (values, digits) => `[${values.map((v) => v.toFixed(digits)).join(", ")}]`;
  const rows = [
    ["position (map)", fmt(gl.position, 3)],
    ["orientation (OpenGL camera, w x y z)", fmt(gl.rotation, 4)],
    ["cam_from_world rotation", fmt(answer.cam_from_world.rotation, 4)],
    ["cam_from_world translation", fmt(answer.cam_from_world.translation, 3)],
  ];
  if (answer.uncertainty) {
    rows.push(["uncertainty", `${(answer.uncertainty.position_m * 100).toFixed(1)} cm, ` +
      `${answer.uncertainty.rotation_deg.toFixed(2)}°`]);
  }
  const camera = answer.camera || entry.camera;
  if (camera) {
    rows.push(["camera", `${camera.model} ${camera.width}×${camera.height} ` +
      `${fmt(camera.params, 1)}${answer.camera_source === "estimated" ? " (estimated)" : ""}`]);
  }
  $("pose").replaceChildren(...rows.flatMap(([term, value]) => {
    const dt = document.createElement("dt");
    const dd = document.createElement("dd");
    dt.textContent = term;
    dd.textContent = value;
    return [dt, dd];
  }));
  state.lastAnswer = answer;
  if (state.overlay) showPose(state.overlay, answer, camera);
}

function intervalMs() {
  const seconds = Number($("interval").value);
  return 1000 * Math.max(Number.isFinite(seconds) ? seconds : 1, MIN_INTERVAL_S);
}

// the next automatic localize: one interval after the last one started, never two at once
function schedule() {
  clearTimeout(state.timer);
  if (!$("auto").checked || !state.mapId || !state.stream) return;
  const wait = Math.max(0, state.lastStart + intervalMs() - performance.now());
  state.timer = setTimeout(async () => {
    await localizeOnce("timer");
    schedule();
  }, wait);
}

// --- maps -------------------------------------------------------------------------------

async function loadMaps(preselect) {
  const select = $("map");
  const previous = preselect || select.value;
  select.replaceChildren(new Option("(no map)", ""));
  try {
    const page = await apiJson("/v1/maps?limit=1000");
    for (const map of page.items) {
      select.append(new Option(`${map.name} (${map.image_count} images)`, map.id));
    }
    setStatus(`${page.total} map(s)`);
  } catch (error) {
    setStatus(`maps: ${error.message}`, true);
  }
  if (previous && [...select.options].some((o) => o.value === previous)) {
    select.value = previous;
  } else if (preselect) {
    setStatus(`map ${preselect} is not among the maps this key may read`, true);
  }
  await selectMap(select.value || null);
}

async function selectMap(mapId) {
  clearTimeout(state.timer);
  state.mapId = null;
  state.images = [];
  state.imageIndex.clear();
  state.referenceCamera = null;
  state.lastAnswer = null;
  $("localize-now").disabled = true;
  hideOverlay();
  if (!mapId) {
    if (state.overlay) drawFrusta(state.overlay, []);
    return;
  }
  try {
    let total = Infinity;
    while (state.images.length < Math.min(total, MAX_IMAGES)) {
      const limit = Math.min(1000, MAX_IMAGES - state.images.length);
      const page = await apiJson(
        `/v1/maps/${mapId}/images?offset=${state.images.length}&limit=${limit}`);
      total = page.total;
      if (!page.items.length) break;
      state.images.push(...page.items);
    }
    state.images.forEach((image, i) => state.imageIndex.set(image.id, i));
    state.referenceCamera = commonCamera(state.images);
    if (state.referenceCamera) {
      $("focal").placeholder = pinhole(state.referenceCamera).fx.toFixed(0);
    }
    const shown = total > MAX_IMAGES ? ` (the first ${MAX_IMAGES} of ${total} drawn)` : "";
    setStatus(`${state.images.length} reference cameras${shown}`);
  } catch (error) {
    setStatus(`images: ${error.message}`, true);
  }
  if (state.overlay) drawFrusta(state.overlay, state.images);
  state.mapId = mapId;
  $("localize-now").disabled = !state.stream;
  schedule();
}

// --- start ------------------------------------------------------------------------------

function readQuery() {
  const query = new URLSearchParams(window.location.search);
  if (query.has("key")) {
    const key = query.get("key").trim();
    if (key) sessionStorage.setItem(KEY_STORAGE, key);
    query.delete("key"); // not kept in the address bar or the history
    const rest = query.toString();
    history.replaceState(null, "", window.location.pathname + (rest ? `?${rest}` : ""));
  }
  if (query.has("interval")) $("interval").value = query.get("interval");
  if (query.has("focal")) {
    $("focal").value = query.get("focal");
    $("intrinsics").value = "focal";
  }
  if (query.get("auto") === "0") $("auto").checked = false;
  if (query.has("depth")) $("depth").value = query.get("depth");
  return query.get("map");
}

async function main() {
  const preselect = readQuery();
  $("api-key").value = sessionStorage.getItem(KEY_STORAGE) || "";
  $("save-key").addEventListener("click", () => {
    const key = $("api-key").value.trim();
    if (key) sessionStorage.setItem(KEY_STORAGE, key);
    else sessionStorage.removeItem(KEY_STORAGE);
    loadMaps();
  });
  $("map").addEventListener("change", () => selectMap($("map").value || null));
  $("localize-now").addEventListener("click", async () => {
    await localizeOnce("button");
    schedule();
  });
  $("auto").addEventListener("change", schedule);
  $("depth").addEventListener("change", () => {
    if (!state.overlay) return;
    drawFrusta(state.overlay, state.images);
    if (state.lastAnswer) highlight(state.overlay, state.lastAnswer.retrieved);
    state.overlay.render();
  });
  $("interval").addEventListener("change", schedule);
  const THREE = await loadThree();
  if (THREE) state.overlay = setUpOverlay(THREE);
  await startCamera();
  document.body.dataset.ready = "true";
  await loadMaps(preselect);
}

main();

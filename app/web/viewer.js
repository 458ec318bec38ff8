// slloc map viewer: lists maps, draws a map's reference camera frusta in 3D (three.js), and
// localizes a query image through the API, drawing its frustum and its inlier matches.
// Poses are cam_from_world (x_cam = R·x_world + t), quaternions [w, x, y, z]; pixel
// coordinates follow COLMAP (the centre of the top-left pixel is (0.5, 0.5)), which is also the
// canvas convention, so they are drawn without an offset.

const KEY_STORAGE = "slloc.apiKey";
const MAX_IMAGES = 5000; // frusta drawn per map
const MAX_LINES = 300; // inlier lines drawn per reference
const MATCH_HEIGHT = 240; // px, height of each image in a match view
const COLORS = { reference: 0x7f8c9a, retrieved: 0xf39c12, inliers: 0x27ae60, query: 0xe74c3c };

const $ = (id) => document.getElementById(id);
const state = { mapId: null, images: new Map(), frusta: new Map(), query: null, three: null };

// --- API --------------------------------------------------------------------------------

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const key = sessionStorage.getItem(KEY_STORAGE);
  if (key) headers.set("X-API-Key", key);
  const response = await fetch(path, { ...options, headers });
  if (!response.ok) {
    let detail = response.statusText;
    try {
      const problem = await response.json();
      detail = `${problem.title}: ${problem.detail}`;
    } catch (_) { /* not a problem document */ }
    throw new Error(`HTTP ${response.status} ${detail}`);
  }
  return response;
}

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

// --- geometry ---------------------------------------------------------------------------

function rotation([w, x, y, z]) {
  // row-major 3×3 rotation of a unit quaternion
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

// world point of camera point p: Rᵀ (p − t)
function toWorld(R, t, p) {
  const d = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
  return [0, 1, 2].map((j) => R[0][j] * d[0] + R[1][j] * d[1] + R[2][j] * d[2]);
}

function pinhole(camera) {
  const p = camera.params;
  // COLMAP parameter order: SIMPLE_* and RADIAL start with one focal length f, cx, cy
  if (camera.model.startsWith("SIMPLE") || camera.model === "RADIAL") {
    return { fx: p[0], fy: p[0], cx: p[1], cy: p[2] };
  }
  return { fx: p[0], fy: p[1], cx: p[2], cy: p[3] };
}

// apex and the four image-corner rays at `depth` in front of the camera, in world coordinates
function frustumCorners(camera, pose, depth) {
  const R = rotation(pose.rotation);
  const t = pose.translation;
  const { fx, fy, cx, cy } = pinhole(camera);
  const corners = [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]];
  const apex = toWorld(R, t, [0, 0, 0]);
  const rim = corners.map(([u, v]) =>
    toWorld(R, t, [((u - cx) / fx) * depth, ((v - cy) / fy) * depth, depth]));
  return { apex, rim };
}

// --- 3D view ----------------------------------------------------------------------------

async function loadThree() {
  try {
    const THREE = await import("three");
    const { OrbitControls } = await import("three/addons/controls/OrbitControls.js");
    return { THREE, OrbitControls };
  } catch (error) {
    $("scene-note").textContent =
      "3D view off: three.js is not installed on the server (run scripts/build_web.sh). " +
      "Maps, localization and matches still work.";
    $("scene-note").className = "error";
    return null;
  }
}

function setUpScene({ THREE, OrbitControls }) {
  const container = $("scene");
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  container.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf7f7f7);
  const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1e5);
  camera.up.set(0, -1, 0); // COLMAP worlds usually have y pointing down
  const controls = new OrbitControls(camera, renderer.domElement);
  const render = () => renderer.render(scene, camera);
  controls.addEventListener("change", render);
  const resize = () => {
    const { clientWidth: w, clientHeight: h } = container;
    renderer.setSize(w, h);
    camera.aspect = w / Math.max(h, 1);
    camera.updateProjectionMatrix();
    render();
  };
  new ResizeObserver(resize).observe(container);
  return { THREE, scene, camera, controls, render, group: null, depth: 1 };
}

function frustumObject(three, camera, pose, color) {
  const { THREE } = three;
  const { apex, rim } = frustumCorners(camera, pose, three.depth);
  const points = [];
  for (let i = 0; i < 4; i++) {
    points.push(apex, rim[i], rim[i], rim[(i + 1) % 4]);
  }
  const geometry = new THREE.BufferGeometry().setFromPoints(
    points.map((p) => new THREE.Vector3(...p)));
  return new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color }));
}

function centre(pose) {
  return toWorld(rotation(pose.rotation), pose.translation, [0, 0, 0]);
}

function drawReferences() {
  const three = state.three;
  const images = [...state.images.values()];
  $("scene").dataset.referenceFrusta = "0";
  $("scene").dataset.queryFrustum = "0";
  state.frusta.clear();
  state.query = null;
  if (!three) return;
  if (three.group) three.scene.remove(three.group);
  three.group = new three.THREE.Group();
  three.scene.add(three.group);
  const centres = images.map((image) => centre(image.cam_from_world));
  const mid = [0, 1, 2].map((k) => centres.reduce((s, c) => s + c[k], 0) / Math.max(centres.length, 1));
  const spread = centres.map((c) => Math.hypot(c[0] - mid[0], c[1] - mid[1], c[2] - mid[2]))
    .sort((a, b) => a - b);
  const radius = spread.length ? Math.max(spread[Math.floor(spread.length / 2)], 1e-3) : 1;
  three.depth = 0.15 * radius;
  for (const image of images) {
    const object = frustumObject(three, image.camera, image.cam_from_world, COLORS.reference);
    object.name = image.id;
    three.group.add(object);
    state.frusta.set(image.id, object);
  }
  $("scene").dataset.referenceFrusta = String(state.frusta.size);
  three.controls.target.set(...mid);
  three.camera.position.set(mid[0], mid[1] - 2 * radius, mid[2] - 3 * radius);
  three.camera.near = radius / 100;
  three.camera.far = radius * 1000;
  three.camera.updateProjectionMatrix();
  three.controls.update();
  three.render();
}

// --- maps -------------------------------------------------------------------------------

async function loadMaps() {
  const list = $("maps");
  list.replaceChildren();
  try {
    const page = await (await api("/v1/maps?limit=1000")).json();
    for (const map of page.items) {
      const button = document.createElement("button");
      button.type = "button";
      button.dataset.mapId = map.id;
      button.textContent = `${map.name} (${map.image_count} images)`;
      button.setAttribute("aria-pressed", "false");
      button.addEventListener("click", () => selectMap(map, button));
      const item = document.createElement("li");
      item.append(button);
      list.append(item);
    }
    setStatus(`${page.total} map(s)`);
  } catch (error) {
    setStatus(`maps: ${error.message}`, true);
  }
}

async function selectMap(map, button) {
  for (const other of $("maps").querySelectorAll("button")) {
    other.setAttribute("aria-pressed", String(other === button));
  }
  state.mapId = map.id;
  state.images.clear();
  setStatus(`loading ${map.name}…`);
  try {
    let total = Infinity;
    while (state.images.size < Math.min(total, MAX_IMAGES)) {
      const limit = Math.min(1000, MAX_IMAGES - state.images.size);
      const url = `/v1/maps/${map.id}/images?offset=${state.images.size}&limit=${limit}`;
      const page = await (await api(url)).json();
      total = page.total;
      if (!page.items.length) break;
      for (const image of page.items) state.images.set(image.id, image);
    }
    const shown = total > MAX_IMAGES ? ` (the first ${MAX_IMAGES} of ${total} shown)` : "";
    setStatus(`${map.name}: ${state.images.size} reference images${shown}`);
  } catch (error) {
    setStatus(`images: ${error.message}`, true);
  }
  drawReferences();
  $("localize").disabled = false;
}

// --- localize ---------------------------------------------------------------------------

function queryCamera(params, width, height) {
  if (params.camera) return params.camera;
  // the engine's documented default when no intrinsics are sent: f = 1.2 × the longer side
  const f = 1.2 * Math.max(width, height);
  return { model: "PINHOLE", width, height, params: [f, f, width / 2, height / 2] };
}

async function localize(event) {
  event.preventDefault();
  const file = $("query-image").files[0];
  if (!file || !state.mapId) return;
  let params;
  try {
    params = JSON.parse($("params").value || "{}");
  } catch (error) {
    setStatus(`params: ${error.message}`, true);
    return;
  }
  params.return_inliers = true;
  const form = new FormData();
  form.append("image", file);
  form.append("params", JSON.stringify(params));
  setStatus("localizing…");
  $("localize").disabled = true;
  try {
    const result = await (await api(`/v1/maps/${state.mapId}/localize`, {
      method: "POST", body: form })).json();
    const bitmap = await createImageBitmap(file);
    showResult(result, bitmap, queryCamera(params, bitmap.width, bitmap.height));
    setStatus(`localized in ${result.timings_ms.total.toFixed(0)} ms (engine)`);
  } catch (error) {
    setStatus(`localize: ${error.message}`, true);
  } finally {
    $("localize").disabled = false;
  }
}

function showResult(result, bitmap, camera) {
  const outcome = $("outcome");
  outcome.replaceChildren();
  outcome.dataset.localized = String(result.localized);
  const verdict = result.localized
    ? `Localized (${result.estimator}), confidence ${result.confidence.toFixed(2)}, centre ` +
      `[${result.camera_center.map((v) => v.toFixed(3)).join(", ")}]`
    : `Not localized: ${result.reason}`;
  const inliers = document.createElement("span");
  inliers.id = "num-inliers";
  inliers.textContent = String(result.num_inliers);
  outcome.append(`${verdict}; inliers: `, inliers);

  const retrieved = $("retrieved");
  retrieved.replaceChildren();
  for (const ref of result.retrieved) {
    const item = document.createElement("li");
    item.className = "retrieved";
    item.dataset.imageId = ref.image_id;
    item.textContent = `${ref.name}: score ${ref.score.toFixed(3)}, ` +
      `${ref.num_matches} matches, ${ref.num_inliers} inliers`;
    retrieved.append(item);
  }
  highlight(result);
  drawMatches(result, bitmap);
  drawQuery(result, camera);
}

function highlight(result) {
  for (const object of state.frusta.values()) object.material.color.setHex(COLORS.reference);
  for (const ref of result.retrieved) {
    const object = state.frusta.get(ref.image_id);
    if (object) object.material.color.setHex(ref.num_inliers > 0 ? COLORS.inliers : COLORS.retrieved);
  }
  if (state.three) state.three.render();
}

function drawQuery(result, camera) {
  const three = state.three;
  if (!three) return;
  if (state.query) three.group.remove(state.query);
  state.query = null;
  $("scene").dataset.queryFrustum = "0";
  if (result.localized) {
    state.query = frustumObject(three, camera, result.cam_from_world, COLORS.query);
    state.query.name = "query";
    three.group.add(state.query);
    $("scene").dataset.queryFrustum = "1";
    $("scene").dataset.queryCentre = JSON.stringify(centre(result.cam_from_world));
  }
  three.render();
}

async function referenceBitmap(image) {
  try {
    const blob = await (await api(
      `/v1/maps/${state.mapId}/images/${image.id}/preview`)).blob();
    return await createImageBitmap(blob);
  } catch (error) {
    return null; // stored without a preview: a grey box of the image's size stands in
  }
}

async function drawMatches(result, queryBitmap) {
  const container = $("matches");
  container.replaceChildren();
  delete container.dataset.ready;
  for (const pair of result.inliers || []) {
    const image = state.images.get(pair.image_id);
    if (!image) continue;
    const reference = await referenceBitmap(image);
    const qs = MATCH_HEIGHT / queryBitmap.height;
    const rs = MATCH_HEIGHT / image.camera.height;
    const qw = queryBitmap.width * qs;
    const canvas = document.createElement("canvas");
    canvas.className = "match-view";
    canvas.dataset.imageId = image.id;
    canvas.dataset.inliers = String(pair.query_xy.length);
    canvas.width = Math.round(qw + image.camera.width * rs);
    canvas.height = MATCH_HEIGHT;
    const ctx = canvas.getContext("2d");
    ctx.drawImage(queryBitmap, 0, 0, qw, MATCH_HEIGHT);
    ctx.fillStyle = "#bbb";
    ctx.fillRect(qw, 0, image.camera.width * rs, MATCH_HEIGHT);
    if (reference) ctx.drawImage(reference, qw, 0, image.camera.width * rs, MATCH_HEIGHT);
    ctx.strokeStyle = "rgba(39, 174, 96, 0.8)";
    ctx.lineWidth = 1;
    const step = Math.max(1, Math.ceil(pair.query_xy.length / MAX_LINES));
    ctx.beginPath();
    for (let i = 0; i < pair.query_xy.length; i += step) {
      const [qx, qy] = pair.query_xy[i];
      const [rx, ry] = pair.reference_xy[i];
      ctx.moveTo(qx * qs, qy * qs);
      ctx.lineTo(qw + rx * rs, ry * rs);
    }
    ctx.stroke();
    const figure = document.createElement("figure");
    const caption = document.createElement("figcaption");
    caption.textContent = `query ↔ ${image.name}: ${pair.query_xy.length} inliers`;
    figure.append(canvas, caption);
    container.append(figure);
  }
  container.dataset.ready = "true";
}

// --- start ------------------------------------------------------------------------------

async function main() {
  $("api-key").value = sessionStorage.getItem(KEY_STORAGE) || "";
  $("save-key").addEventListener("click", () => {
    const key = $("api-key").value.trim();
    if (key) sessionStorage.setItem(KEY_STORAGE, key);
    else sessionStorage.removeItem(KEY_STORAGE);
    loadMaps();
  });
  $("reload-maps").addEventListener("click", loadMaps);
  $("localize-form").addEventListener("submit", localize);
  const modules = await loadThree();
  if (modules) state.three = setUpScene(modules);
  document.body.dataset.ready = "true";
  await loadMaps();
}

main();

// slloc map viewer: lists maps, draws a map's reference cameras in 3D (three.js) as frusta with
// their previews on the image planes, over a ground grid (and a compass on geo-registered
// maps), and localizes a query image through the API, drawing its frustum (or, for a
// low-confidence answer, the candidate pose dashed), its GeoPose and its inlier matches.
// When the map has a finished self-evaluation, its held-out references are coloured by their
// held-out position error and a side panel shows what it measured; another lists the map's
// capture sessions (admin key only) with their alignment. The map's coverage cells lie on its
// references' ground plane, weak ones in red.
// Poses are cam_from_world (x_cam = R·x_world + t), quaternions [w, x, y, z]; pixel
// coordinates follow COLMAP (the centre of the top-left pixel is (0.5, 0.5)), which is also the
// canvas convention, so they are drawn without an offset.

import { directionToWorld, rotation, toWorld } from "./geometry.js";

const KEY_STORAGE = "slloc.apiKey";
const MAX_IMAGES = 5000; // frusta drawn per map
const MAX_THUMBNAILS = 64; // previews textured on image planes per map (GPU memory bound)
const THUMBNAIL_SIDE = 192; // px, longer side of a texture
const THUMBNAIL_LOADS = 4; // previews fetched at once
const MAX_LINES = 50; // inlier lines drawn per match figure
const MATCH_HEIGHT = 320; // px, height of each image in a match figure
const COLORS = {
  reference: 0x7f8c9a, retrieved: 0xf39c12, inliers: 0x27ae60, query: 0xe74c3c,
  candidate: 0x8e44ad, grid: 0xb8c0c8, gridCentre: 0x8a939c, north: 0x1f5fbf, east: 0x6c7a89,
  weakCell: 0xd62728, cell: 0x8fa89a, stale: 0xc2185b,
};
const STALE_LISTED = 20; // stale references the panel names
// a held-out reference's colour by its position error in the map's latest self-evaluation
// (metres; the last band also takes the references that were not localized)
const ERROR_BANDS = [
  { band: "under-5cm", below: 0.05, color: 0x1e9e4a, label: "< 5 cm" },
  { band: "under-25cm", below: 0.25, color: 0xd4ac0d, label: "< 25 cm" },
  { band: "under-1m", below: 1.0, color: 0xe8730c, label: "< 1 m" },
  { band: "over-1m", below: Infinity, color: 0xa31515, label: "≥ 1 m or not localized" },
];
const EVALUATION_REFRESHES = 20; // looks at a queued / running evaluation, then a button
const EVALUATION_REFRESH_S = [4, 30]; // first wait, growing ×1.25 up to the second
const MARKER_PX = 9; // the dot at a held-out camera's centre (px; 15 when picked)
const PICK_PX = 12; // a pointer this close to a dot hovers / picks it

const $ = (id) => document.getElementById(id);
const state = {
  mapId: null,
  images: new Map(),
  frusta: new Map(), // image id → { group, lines, rim, plane, base colour }
  query: null, // the query's (or candidate's) frustum
  three: null,
  geo: null, // the map's geo-registration, null when it has none
  frame: null, // { mid, up, north, radius, ground } of the drawn map
  thumbnails: { queue: [], running: 0, loaded: 0, requested: new Set(), generation: 0 },
  matches: { pairs: [], index: 0, queryBitmap: null, token: 0 },
  // the map's self-evaluation: the finished one shown (with its references), the one still
  // running, the held-out references by image id, their dots in 3D and the refresh timer
  evaluation: {
    token: 0, done: null, active: null, configuration: null, heldOut: new Map(),
    markers: new Map(), selected: null, timer: null, refreshes: 0,
  },
  // the map's capture sessions (newest first) and their refresh timer
  sessions: { token: 0, map: null, timer: null, refreshes: 0, active: new Set(), grown: false },
  // the map's coverage cells: their squares in 3D (a group in the map's group)
  coverage: { token: 0, map: null, group: null },
};

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
    const error = new Error(`HTTP ${response.status} ${detail}`);
    error.status = response.status;
    throw error;
  }
  return response;
}

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

// --- geometry ---------------------------------------------------------------------------

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const add = (a, b, s = 1) => [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]];
const cross = (a, b) =>
  [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
function normalize(v) {
  const n = Math.hypot(...v);
  return n > 1e-9 ? v.map((x) => x / n) : null;
}

function pinhole(camera) {
  const p = camera.params;
  // COLMAP parameter order: SIMPLE_* and RADIAL start with one focal length f, cx, cy
  if (camera.model.startsWith("SIMPLE") || camera.model === "RADIAL") {
    return { fx: p[0], fy: p[0], cx: p[1], cy: p[2] };
  }
  return { fx: p[0], fy: p[1], cx: p[2], cy: p[3] };
}

// apex and the four image corners (top-left, top-right, bottom-right, bottom-left) at `depth`
// in front of the camera, in world coordinates
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

function centre(pose) {
  return toWorld(rotation(pose.rotation), pose.translation, [0, 0, 0]);
}

// The map's up direction: East-North-Up's up through the geo-registration when there is one
// (x_enu = s·R·x_map + t, so a map direction is Rᵀ of an ENU one), else the mean of the
// reference cameras' "up" (−y in COLMAP's camera axes), else COLMAP's usual −y.
function mapFrame(images, geo) {
  let up = null;
  let north = null;
  if (geo) {
    const R = rotation(geo.enu_from_map.rotation);
    up = directionToWorld(R, [0, 0, 1]);
    north = directionToWorld(R, [0, 1, 0]);
  } else {
    let sum = [0, 0, 0];
    for (const image of images) {
      sum = add(sum, directionToWorld(rotation(image.cam_from_world.rotation), [0, -1, 0]));
    }
    // cameras that disagree (sum much shorter than the count) say little about up
    up = images.length && Math.hypot(...sum) > 0.3 * images.length ? normalize(sum) : null;
  }
  up = up || [0, -1, 0];
  return { up, north };
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
  const three = {
    THREE, OrbitControls, renderer, scene, camera, controls: null, group: null, depth: 1,
  };
  three.render = () => {
    renderer.render(scene, camera);
    updateCompass();
  };
  three.controls = makeControls(three);
  const resize = () => {
    const { clientWidth: w, clientHeight: h } = container;
    renderer.setSize(w, h);
    camera.aspect = w / Math.max(h, 1);
    camera.updateProjectionMatrix();
    three.render();
  };
  new ResizeObserver(resize).observe(container);
  return three;
}

// OrbitControls read camera.up when made: made again whenever a map sets its up direction
function makeControls(three) {
  if (three.controls) three.controls.dispose();
  const controls = new three.OrbitControls(three.camera, three.renderer.domElement);
  controls.addEventListener("change", three.render);
  return controls;
}

function disposeTree(object) {
  object.traverse((node) => {
    if (node.geometry) node.geometry.dispose();
    if (node.material) {
      if (node.material.map) {
        node.material.map.image?.close?.(); // an ImageBitmap's memory goes at once
        node.material.map.dispose();
      }
      node.material.dispose();
    }
  });
}

function frustumLines(three, camera, pose, color, { dashed = false, scale = 1 } = {}) {
  const { THREE } = three;
  const depth = scale * three.depth;
  const { apex, rim } = frustumCorners(camera, pose, depth);
  const points = [];
  for (let i = 0; i < 4; i++) points.push(apex, rim[i], rim[i], rim[(i + 1) % 4]);
  // a tick above the top edge marks the image's "up"
  const topMid = rim[0].map((v, k) => (v + rim[1][k]) / 2);
  const bottomMid = rim[3].map((v, k) => (v + rim[2][k]) / 2);
  const upward = normalize(add(topMid, bottomMid, -1)) || [0, 0, 0];
  points.push(topMid, add(topMid, upward, 0.2 * depth));
  const geometry = new THREE.BufferGeometry().setFromPoints(
    points.map((p) => new THREE.Vector3(...p)));
  const material = dashed
    ? new THREE.LineDashedMaterial({ color, dashSize: 0.12 * depth, gapSize: 0.08 * depth })
    : new THREE.LineBasicMaterial({ color });
  const lines = new THREE.LineSegments(geometry, material);
  if (dashed) lines.computeLineDistances();
  return { lines, rim };
}

function drawReferences() {
  const three = state.three;
  const images = [...state.images.values()];
  $("scene").dataset.referenceFrusta = "0";
  $("scene").dataset.queryFrustum = "0";
  $("scene").dataset.candidateFrustum = "0";
  $("scene").dataset.thumbnails = "0";
  state.frusta.clear();
  state.evaluation.markers.clear(); // disposed with the group below
  state.coverage.group = null; // so are the coverage cells
  $("scene").dataset.coverageCells = "0";
  state.query = null;
  resetThumbnails();
  if (!three) return;
  if (three.group) {
    three.scene.remove(three.group);
    disposeTree(three.group);
  }
  three.group = new three.THREE.Group();
  three.scene.add(three.group);
  const centres = images.map((image) => centre(image.cam_from_world));
  const mid = [0, 1, 2].map((k) => centres.reduce((s, c) => s + c[k], 0) / Math.max(centres.length, 1));
  const spread = centres.map((c) => Math.hypot(c[0] - mid[0], c[1] - mid[1], c[2] - mid[2]))
    .sort((a, b) => a - b);
  const radius = spread.length ? Math.max(spread[Math.floor(spread.length / 2)], 1e-3) : 1;
  three.depth = 0.22 * radius;
  let staleFrusta = 0;
  for (const image of images) {
    // a stale reference: dashed, in its own colour (a self-evaluation's band overrides the
    // colour, never the dashes)
    const base = image.stale ? COLORS.stale : COLORS.reference;
    const { lines, rim } = frustumLines(three, image.camera, image.cam_from_world, base,
      { dashed: Boolean(image.stale) });
    const group = new three.THREE.Group();
    group.name = image.id;
    group.add(lines);
    three.group.add(group);
    state.frusta.set(image.id, { group, lines, rim, plane: null, base });
    staleFrusta += image.stale ? 1 : 0;
  }
  $("scene").dataset.referenceFrusta = String(state.frusta.size);
  $("scene").dataset.staleFrusta = String(staleFrusta);

  const { up, north } = mapFrame(images, state.geo);
  const heights = centres.map((c) => dot(c, up));
  const lowest = heights.length ? Math.min(...heights) : 0;
  const midHeight = dot(mid, up);
  // the ground: below the lowest camera by half the cameras' median distance from their centre
  const ground = add(mid, up, lowest - 0.5 * radius - midHeight);
  const extent = Math.max(...centres.map((c) => {
    const d = add(c, mid, -1);
    return Math.hypot(...add(d, up, -dot(d, up)));
  }), radius);
  state.frame = { mid, up, north, radius, ground };
  drawGround(three, ground, up, north, extent);
  if (north) drawCompass(three, ground, up, north, radius);
  $("scene").dataset.up = JSON.stringify(up.map((v) => +v.toFixed(6)));
  $("scene").dataset.compass = north ? "1" : "0";
  $("compass").hidden = !north;

  // look at the cameras from above and behind their mean viewing direction
  let forward = [0, 0, 0];
  for (const image of images) {
    forward = add(forward, directionToWorld(rotation(image.cam_from_world.rotation), [0, 0, 1]));
  }
  forward = normalize(add(forward, up, -dot(forward, up))) || normalize(cross(up, [1, 0, 0])) ||
    normalize(cross(up, [0, 1, 0]));
  three.camera.up.set(...up);
  three.controls = makeControls(three);
  three.controls.target.set(...mid);
  three.camera.position.set(...add(add(mid, up, 2 * radius), forward, -3 * radius));
  three.camera.near = radius / 100;
  three.camera.far = radius * 1000;
  three.camera.updateProjectionMatrix();
  three.controls.update();
  three.render();
  queueThumbnails(images);
}

// a grid on the ground, its lines along East and North on a geo-registered map, and the map
// frame's axes at its origin (x red, y green, z blue)
function drawGround(three, ground, up, north, extent) {
  const { THREE } = three;
  const step = niceStep(extent / 5);
  const divisions = 2 * Math.max(4, Math.ceil((1.3 * extent) / step));
  const grid = new THREE.GridHelper(divisions * step, divisions, COLORS.gridCentre, COLORS.grid);
  const y = new THREE.Vector3(...up);
  const x = new THREE.Vector3(...(north ? cross(north, up) : normalize(
    Math.abs(up[0]) < 0.9 ? add([1, 0, 0], up, -up[0]) : add([0, 0, 1], up, -up[2]))));
  x.sub(y.clone().multiplyScalar(x.dot(y))).normalize();
  const z = new THREE.Vector3().crossVectors(x, y);
  grid.quaternion.setFromRotationMatrix(new THREE.Matrix4().makeBasis(x, y, z));
  grid.position.set(...ground);
  grid.material.transparent = true;
  grid.material.opacity = 0.6;
  grid.name = "ground";
  three.group.add(grid);
  const axes = new THREE.AxesHelper(step);
  axes.name = "map axes";
  three.group.add(axes);
  $("scene").dataset.gridStep = String(step);
}

function niceStep(x) {
  const p = 10 ** Math.floor(Math.log10(Math.max(x, 1e-6)));
  return [1, 2, 5, 10].map((m) => m * p).find((s) => s >= x);
}

function labelSprite(three, text, color, size) {
  const { THREE } = three;
  const canvas = document.createElement("canvas");
  canvas.width = canvas.height = 64;
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = `#${color.toString(16).padStart(6, "0")}`;
  ctx.font = "bold 44px system-ui, sans-serif";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  ctx.fillText(text, 32, 34);
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: texture, depthTest: false }));
  sprite.scale.set(size, size, 1);
  return sprite;
}

// the local East-North plane on a geo-registered map: a North arrow and an East arrow on the
// ground, labelled
function drawCompass(three, ground, up, north, radius) {
  const { THREE } = three;
  const origin = new THREE.Vector3(...add(ground, up, 0.01 * radius));
  const east = cross(north, up);
  const compass = new THREE.Group();
  compass.name = "compass";
  const length = 0.8 * radius;
  for (const [dir, color, text, scale] of [
    [north, COLORS.north, "N", 1], [east, COLORS.east, "E", 0.6]]) {
    const arrow = new THREE.ArrowHelper(
      new THREE.Vector3(...dir), origin, length * scale, color, 0.2 * length, 0.1 * length);
    compass.add(arrow);
    const label = labelSprite(three, text, color, 0.25 * radius);
    label.position.copy(origin).addScaledVector(new THREE.Vector3(...dir), length * scale * 1.15);
    compass.add(label);
  }
  three.group.add(compass);
}

// the corner compass needle: the screen direction of North at the ground's centre
function updateCompass() {
  const three = state.three;
  const needle = $("compass-needle");
  if (!three || !state.frame || !state.frame.north || !needle) return;
  const { THREE, camera } = three;
  const { ground, north, radius } = state.frame;
  const a = new THREE.Vector3(...ground).project(camera);
  const b = new THREE.Vector3(...add(ground, north, radius)).project(camera);
  const { clientWidth: w, clientHeight: h } = $("scene");
  const angle = Math.atan2((b.x - a.x) * w, (b.y - a.y) * h); // clockwise from screen up
  needle.style.transform = `rotate(${angle.toFixed(4)}rad)`;
  $("compass").dataset.angleDeg = (angle * 180 / Math.PI).toFixed(1);
}

// --- reference thumbnails ---------------------------------------------------------------

function resetThumbnails() {
  const thumbs = state.thumbnails;
  thumbs.generation += 1; // loads of an earlier map are dropped when they arrive
  thumbs.queue = [];
  thumbs.loaded = 0;
  thumbs.requested = new Set();
}

// up to MAX_THUMBNAILS previews, spread evenly over the references, loaded a few at a time
// after the frusta are drawn
function queueThumbnails(images, first = false) {
  const thumbs = state.thumbnails;
  const room = MAX_THUMBNAILS - thumbs.requested.size;
  if (!state.three || room <= 0) return;
  const fresh = images.filter((image) => !thumbs.requested.has(image.id));
  const picked = spread(fresh.length, room).map((i) => fresh[i]);
  for (const image of picked) thumbs.requested.add(image.id);
  thumbs.queue = first ? [...picked, ...thumbs.queue] : [...thumbs.queue, ...picked];
  pumpThumbnails();
}

function pumpThumbnails() {
  const thumbs = state.thumbnails;
  while (thumbs.running < THUMBNAIL_LOADS && thumbs.queue.length) {
    const image = thumbs.queue.shift();
    const generation = thumbs.generation;
    thumbs.running += 1;
    loadThumbnail(image, generation).finally(() => {
      thumbs.running -= 1;
      pumpThumbnails();
    });
  }
}

async function loadThumbnail(image, generation) {
  const mapId = state.mapId;
  let bitmap;
  try {
    const blob = await (await api(`/v1/maps/${mapId}/images/${image.id}/preview`)).blob();
    const scale = THUMBNAIL_SIDE / Math.max(image.camera.width, image.camera.height);
    bitmap = await createImageBitmap(blob, {
      resizeWidth: Math.max(1, Math.round(image.camera.width * scale)),
      resizeHeight: Math.max(1, Math.round(image.camera.height * scale)),
      resizeQuality: "medium",
    });
  } catch (error) {
    return; // stored without a preview: the frustum stays a wireframe
  }
  const frustum = state.frusta.get(image.id);
  const three = state.three;
  if (generation !== state.thumbnails.generation || !frustum || frustum.plane || !three) {
    bitmap.close();
    return;
  }
  const { THREE } = three;
  const texture = new THREE.Texture(bitmap);
  texture.flipY = false; // ImageBitmaps are not flipped: uv (0, 0) is the top-left pixel
  texture.colorSpace = THREE.SRGBColorSpace;
  texture.needsUpdate = true;
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(frustum.rim.flat(), 3));
  geometry.setAttribute("uv", new THREE.Float32BufferAttribute([0, 0, 1, 0, 1, 1, 0, 1], 2));
  geometry.setIndex([0, 1, 2, 0, 2, 3]);
  const plane = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({
    map: texture, side: THREE.DoubleSide, transparent: true, opacity: 0.92 }));
  plane.name = `preview ${image.name}`;
  frustum.group.add(plane);
  frustum.plane = plane;
  state.thumbnails.loaded += 1;
  $("scene").dataset.thumbnails = String(state.thumbnails.loaded);
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
      // its feature configuration, and whether it follows its self-evaluation
      const features = `${map.features.preset}${map.features.auto ? ", auto" : ""}`;
      button.textContent = `${map.name} (${map.image_count} images, ${features})`;
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

async function loadGeoRegistration(mapId) {
  try {
    return await (await api(`/v1/maps/${mapId}/geo-registration`)).json();
  } catch (error) {
    if (error.status !== 404) setStatus(`geo-registration: ${error.message}`, true);
    return null; // 404: the map is not geo-registered
  }
}

async function selectMap(map, button) {
  for (const other of $("maps").querySelectorAll("button")) {
    other.setAttribute("aria-pressed", String(other === button));
  }
  state.mapId = map.id;
  state.images.clear();
  $("map-ready").dataset.ready = "false";
  setStatus(`loading ${map.name}…`);
  clearResult();
  const geo = loadGeoRegistration(map.id);
  const evaluation = openEvaluation(map); // read while the images load
  const sessions = openSessions(map);
  const cells = openCoverage(map);
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
  state.geo = await geo;
  showGeoRegistration(state.geo);
  drawReferences();
  showStale();
  showEvaluation(await evaluation, true);
  showCoverage(await cells);
  showSessions(await sessions);
  $("localize").disabled = false;
  $("map-ready").dataset.ready = "true";
}

function showGeoRegistration(geo) {
  const panel = $("geo");
  panel.dataset.registered = String(Boolean(geo));
  if (!geo) {
    $("geo-registration").textContent = "This map is not geo-registered.";
    return;
  }
  const o = geo.origin;
  const sigma = geo.source === "estimated"
    ? `, ±${geo.position_sigma_m.toFixed(2)} m / ${geo.rotation_sigma_deg.toFixed(2)}°` : "";
  $("geo-registration").textContent =
    `Geo-registered (${geo.source}${sigma}): origin ${o.latitude.toFixed(7)}°, ` +
    `${o.longitude.toFixed(7)}°, ${o.height.toFixed(2)} m; the arrows on the ground point ` +
    "North and East.";
}

// --- localize ---------------------------------------------------------------------------

function queryCamera(result, params, width, height) {
  if (result.camera) return result.camera; // the camera the engine used
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
    showResult(result, bitmap, queryCamera(result, params, bitmap.width, bitmap.height));
    if (result.localized) {
      setStatus(`localized in ${result.timings_ms.total.toFixed(0)} ms (engine)`);
    } else {
      const hint = result.candidate ? " (the candidate pose is drawn dashed)" : "";
      setStatus(`not localized: ${result.reason}${hint}`, true);
    }
  } catch (error) {
    setStatus(`localize: ${error.message}`, true);
  } finally {
    $("localize").disabled = false;
  }
}

function clearResult() {
  $("outcome").textContent = "Pick an image to localize.";
  delete $("outcome").dataset.localized;
  $("retrieved").replaceChildren();
  $("matches").hidden = true;
  state.matches = { pairs: [], index: 0, queryBitmap: null, token: state.matches.token + 1 };
  showGeoPose(null);
}

function fixed(values, digits) {
  return `[${values.map((v) => v.toFixed(digits)).join(", ")}]`;
}

function showResult(result, bitmap, camera) {
  const outcome = $("outcome");
  outcome.replaceChildren();
  outcome.dataset.localized = String(result.localized);
  let verdict;
  if (result.localized) {
    verdict = `Localized (${result.estimator_used}), confidence ${result.confidence.toFixed(3)}, ` +
      `centre ${fixed(result.camera_center, 3)}`;
  } else if (result.candidate) {
    verdict = `Not localized: ${result.reason}. Candidate pose (not an answer, dashed in ` +
      `purple): confidence ${result.confidence.toFixed(3)}, centre ` +
      `${fixed(centre(result.candidate), 3)}`;
  } else {
    verdict = `Not localized: ${result.reason}`;
  }
  const verdictSpan = document.createElement("strong");
  verdictSpan.className = result.localized ? "" : "error";
  verdictSpan.textContent = verdict;
  const inliers = document.createElement("span");
  inliers.id = "num-inliers";
  inliers.textContent = String(result.num_inliers);
  outcome.append(verdictSpan, "; inliers: ", inliers);

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
  showGeoPose(result);
  drawQuery(result, camera);
  setUpMatches(result, bitmap);
  // the retrieved references' previews come first among the thumbnails still to load
  queueThumbnails(result.retrieved.map((ref) => state.images.get(ref.image_id)).filter(Boolean), true);
}

function highlight(result) {
  for (const { lines, base } of state.frusta.values()) lines.material.color.setHex(base);
  for (const ref of result.retrieved) {
    const frustum = state.frusta.get(ref.image_id);
    if (frustum) {
      frustum.lines.material.color.setHex(ref.num_inliers > 0 ? COLORS.inliers : COLORS.retrieved);
    }
  }
  if (state.three) state.three.render();
}

function drawQuery(result, camera) {
  const three = state.three;
  const scene = $("scene");
  scene.dataset.queryFrustum = "0";
  scene.dataset.candidateFrustum = "0";
  delete scene.dataset.queryCentre;
  delete scene.dataset.candidateCentre;
  if (!three) return;
  if (state.query) {
    three.group.remove(state.query);
    disposeTree(state.query);
  }
  state.query = null;
  const pose = result.localized ? result.cam_from_world : result.candidate;
  if (pose) {
    const candidate = !result.localized;
    // drawn larger than the references' so that it stands out among them
    const { lines } = frustumLines(three, camera, pose,
      candidate ? COLORS.candidate : COLORS.query, { dashed: candidate, scale: 1.5 });
    lines.name = candidate ? "candidate" : "query";
    three.group.add(lines);
    state.query = lines;
    const key = candidate ? "candidate" : "query";
    scene.dataset[`${key}Frustum`] = "1";
    scene.dataset[`${key}Centre`] = JSON.stringify(centre(pose));
  }
  three.render();
}

// --- self-evaluation --------------------------------------------------------------------

const formatLength = (m) => (m === null || m === undefined ? "—"
  : m < 0.01 ? `${(m * 1000).toFixed(1)} mm` : m < 1 ? `${(m * 100).toFixed(1)} cm`
    : `${m.toFixed(2)} m`);
const formatShare = (x) => (x === null || x === undefined ? "—" : `${(100 * x).toFixed(0)}%`);
const hex = (color) => `#${color.toString(16).padStart(6, "0")}`;

function bandOf(ref) {
  const error = ref.localized ? ref.position_error_m : null;
  if (error === null || error === undefined) return ERROR_BANDS[ERROR_BANDS.length - 1];
  return ERROR_BANDS.find((b) => error < b.below);
}

// what one held-out reference's query gave, in words
function describeHeldOut(ref) {
  if (!ref.localized || ref.position_error_m === null) {
    return `not localized: ${ref.reason || "unknown"} (${ref.num_inliers} inliers, ` +
      `${ref.latency_ms.toFixed(0)} ms)`;
  }
  return `${formatLength(ref.position_error_m)}, ${ref.rotation_error_deg.toFixed(2)}° off; ` +
    `${ref.num_inliers} inliers, confidence ${ref.confidence.toFixed(2)}, ` +
    `${ref.latency_ms.toFixed(0)} ms`;
}

// the map's latest finished evaluation (with its references), the newest one still queued or
// running and the newest of all; evaluations are listed newest first
async function fetchEvaluations(mapId) {
  let active = null;
  let latest = null;
  let finished = null;
  for (let offset = 0, pages = 0; pages < 5 && !finished; pages += 1) {
    const page = await (await api(
      `/v1/maps/${mapId}/evaluations?offset=${offset}&limit=20`)).json();
    latest = latest || page.items[0] || null;
    active = active || page.items.find((e) => e.state === "queued" || e.state === "running") ||
      null;
    finished = page.items.find((e) => e.state === "done") || null;
    offset += page.items.length;
    if (!page.items.length || offset >= page.total) break;
  }
  let done = null;
  if (finished) {
    const shown = state.evaluation.done;
    done = shown && shown.id === finished.id ? shown
      : await (await api(`/v1/maps/${mapId}/evaluations/${finished.id}`)).json();
  }
  return { done, active, latest };
}

// a new map: forget the last one's evaluation and read this one's
async function openEvaluation(map) {
  const ev = state.evaluation;
  clearTimeout(ev.timer);
  Object.assign(ev, {
    token: ev.token + 1, done: null, active: null, configuration: null, heldOut: new Map(),
    selected: null, timer: null, refreshes: 0, map,
  });
  const panel = $("evaluation");
  panel.dataset.state = "loading";
  $("eval-summary").textContent = "Reading the map's self-evaluations…";
  $("eval-summary").className = "";
  for (const id of ["eval-progress", "eval-legend", "eval-table", "eval-refresh"]) $(id).hidden = true;
  $("eval-references").replaceChildren();
  showSelected(null);
  return readEvaluations(map.id, ev.token);
}

async function readEvaluations(mapId, token) {
  try {
    return { token, mapId, ...(await fetchEvaluations(mapId)) };
  } catch (error) {
    return { token, mapId, error };
  }
}

// fills the panel; `recolour`: the frusta were drawn anew (or the finished evaluation changed)
function showEvaluation(answer, recolour = false) {
  const ev = state.evaluation;
  if (answer.token !== ev.token) return; // another map was picked meanwhile
  const panel = $("evaluation");
  if (answer.error) {
    const where = ev.done ? $("eval-progress") : $("eval-summary"); // keep what was shown
    if (!ev.done) panel.dataset.state = "error";
    where.hidden = false;
    where.textContent = `Self-evaluations: ${answer.error.message}`;
    where.className = "error";
    $("eval-refresh").hidden = false;
    return;
  }
  $("eval-progress").className = "";
  $("eval-summary").className = "";
  const changed = (answer.done && answer.done.id) !== (ev.done && ev.done.id);
  ev.done = answer.done;
  ev.active = answer.active;
  if (changed || recolour) {
    const result = ev.done ? ev.done.result : null;
    const names = result ? Object.keys(result.configurations) : [];
    ev.configuration = result ? (names.includes(result.served) ? result.served : names[0]) : null;
    const refs = ev.configuration ? result.configurations[ev.configuration].references || [] : [];
    ev.heldOut = new Map(refs.map((ref) => [ref.image_id, ref]));
    ev.selected = ev.heldOut.has(ev.selected) ? ev.selected : null;
    colourHeldOut();
    showEvaluationResult();
    if (!recolour) refreshCoverage(); // a newer evaluation: the cells' weakness with it
  }
  panel.dataset.state = ev.done ? "done" : answer.latest ? answer.latest.state : "none";
  if (ev.done) panel.dataset.evaluationId = ev.done.id;
  else delete panel.dataset.evaluationId;
  if (!ev.done) showNoEvaluation(answer.latest);
  showProgress();
  scheduleEvaluationRefresh();
}

function showNoEvaluation(latest) {
  const summary = $("eval-summary");
  summary.replaceChildren();
  const map = state.evaluation.map;
  if (latest && latest.state === "failed") {
    summary.append(`The last self-evaluation failed: ${latest.error || "no reason given"}. `);
  } else if (latest && latest.state === "cancelled") {
    summary.append("The last self-evaluation was cancelled. ");
  } else {
    summary.append(`This map has no ${state.evaluation.active ? "finished " : ""}` +
      "self-evaluation yet. ");
  }
  if (state.evaluation.active) return; // the progress line says the rest
  const command = document.createElement("code");
  command.id = "eval-command";
  command.textContent = `slloc self-evaluate --url ${window.location.origin} --map ` +
    `${/\s/.test(map.name) ? JSON.stringify(map.name) : map.name} --api-key <admin key>`;
  const route = document.createElement("code");
  route.textContent = `POST /v1/maps/${map.id}/evaluations`;
  summary.append("To measure how well it localizes its own references, run ", command,
    " or call ", route, " with an admin key; this page only shows the result.");
}

function showProgress() {
  const ev = state.evaluation;
  const line = $("eval-progress");
  line.hidden = !ev.active;
  $("eval-refresh").hidden = !ev.active;
  if (!ev.active) {
    delete line.dataset.state;
    return;
  }
  const { done, total } = ev.active.progress;
  line.dataset.state = ev.active.state;
  line.dataset.done = String(done);
  line.dataset.total = String(total);
  const what = ev.done ? "A newer self-evaluation" : "A self-evaluation";
  // a queued one counts its queries when it starts
  line.textContent = ev.active.state === "queued" ? `${what} is queued; it has not started yet.`
    : `${what} is running: ${done} / ${total} held-out queries done.`;
  if (ev.refreshes >= EVALUATION_REFRESHES) line.append(" (Check again for news.)");
}

// a queued or running evaluation is looked at again a bounded number of times, less and less
// often; "Check again" starts another such series
function scheduleEvaluationRefresh() {
  const ev = state.evaluation;
  clearTimeout(ev.timer);
  ev.timer = null;
  if (!ev.active || ev.refreshes >= EVALUATION_REFRESHES) return;
  const [first, most] = EVALUATION_REFRESH_S;
  const wait = Math.min(first * 1.25 ** ev.refreshes, most);
  const { token } = ev;
  ev.timer = setTimeout(() => refreshEvaluation(token, true), wait * 1000);
}

async function refreshEvaluation(token, automatic) {
  const ev = state.evaluation;
  if (token !== ev.token || !ev.map) return;
  clearTimeout(ev.timer);
  ev.timer = null;
  ev.refreshes = automatic ? ev.refreshes + 1 : 0;
  showEvaluation(await readEvaluations(ev.map.id, token));
}

function showEvaluationResult() {
  const ev = state.evaluation;
  const table = $("eval-table");
  const legend = $("eval-legend");
  const list = $("eval-references");
  const panel = $("evaluation");
  list.replaceChildren();
  table.replaceChildren();
  table.hidden = legend.hidden = !ev.done;
  delete panel.dataset.configuration;
  delete panel.dataset.recommended;
  if (!ev.done) {
    showSelected(null);
    return;
  }
  const result = ev.done.result;
  panel.dataset.configuration = ev.configuration;
  panel.dataset.recommended = result.recommended || "";
  const when = new Date(ev.done.finished_at || ev.done.created_at);
  const summary = $("eval-summary");
  summary.replaceChildren();
  const date = document.createElement("time");
  date.id = "eval-date";
  date.dateTime = ev.done.finished_at || ev.done.created_at;
  date.textContent = when.toLocaleString();
  const measured = result.configurations[ev.configuration];
  const servedNote = ev.configuration === result.served ? "the configuration this server serves"
    : `this server serves ${result.served}, which it did not measure`;
  summary.append("Self-evaluation of ", date, `: ${measured.held_out} of the map's ` +
    `${result.references} references held out, each localized against the rest. Their frusta ` +
    `are coloured by the position error under ${ev.configuration} (${servedNote}).`);
  const recommended = document.createElement("p");
  recommended.id = "eval-recommended";
  recommended.textContent = result.recommended
    ? `Recommended: ${result.recommended}.`
    : "Recommended: none (no configuration localized a held-out reference).";
  summary.append(recommended);

  // recall at (5 cm, 5°) and (25 cm, 2°), median error and median latency per configuration
  const head = document.createElement("tr");
  for (const [title, hint] of [
    ["config", "feature configuration"],
    ["recall\n5\u00a0cm\u00a05°", "share within (5 cm, 5°)"],
    ["recall\n25\u00a0cm\u00a02°", "share within (25 cm, 2°)"],
    ["median\nerror", "median position error"],
    ["p50\nlatency", "median time of a held-out query"]]) {
    const th = document.createElement("th");
    th.textContent = title;
    th.title = hint;
    head.append(th);
  }
  table.append(head);
  for (const [name, c] of Object.entries(result.configurations)) {
    const row = document.createElement("tr");
    row.dataset.configuration = name;
    const marks = [name === result.served ? "served" : "", name === result.recommended ? "★" : ""]
      .filter(Boolean).join(", ");
    const cells = [marks ? `${name} (${marks})` : name, formatShare(c.recall["5cm_5deg"]),
      formatShare(c.recall["25cm_2deg"]), formatLength(c.position_error_m.median),
      c.latency_ms.median === null ? "—" : `${c.latency_ms.median.toFixed(0)} ms`];
    cells.forEach((text, k) => {
      const td = document.createElement("td");
      td.dataset.field = ["name", "recall-5cm-5deg", "recall-25cm-2deg", "median-error",
        "median-latency"][k];
      td.textContent = text;
      row.append(td);
    });
    table.append(row);
  }

  // the legend, with how many held-out references fall in each band
  const counts = new Map(ERROR_BANDS.map((b) => [b.band, 0]));
  for (const ref of ev.heldOut.values()) counts.set(bandOf(ref).band, counts.get(bandOf(ref).band) + 1);
  legend.replaceChildren("Held out:");
  for (const b of ERROR_BANDS) {
    const swatch = document.createElement("span");
    swatch.style.background = hex(b.color);
    const item = document.createElement("em");
    item.dataset.band = b.band;
    item.append(swatch, `${b.label} (${counts.get(b.band)})`);
    legend.append(item);
  }
  legend.append(" other references keep their grey; ★ recommended.");

  // the held-out references, worst first; a click picks one (as a click on its dot does)
  const refs = [...ev.heldOut.values()].sort((a, b) =>
    (b.localized ? b.position_error_m ?? Infinity : Infinity) -
    (a.localized ? a.position_error_m ?? Infinity : Infinity) || a.name.localeCompare(b.name));
  for (const ref of refs) {
    const item = document.createElement("li");
    item.dataset.imageId = ref.image_id;
    item.dataset.band = bandOf(ref).band;
    item.tabIndex = 0;
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = hex(bandOf(ref).color);
    item.append(swatch, `${ref.name}: ${describeHeldOut(ref)}`);
    item.addEventListener("click", () => selectHeldOut(ref.image_id));
    item.addEventListener("keydown", (event) => {
      if (event.key === "Enter" || event.key === " ") selectHeldOut(ref.image_id);
    });
    list.append(item);
  }
  showSelected(ev.selected);
}

// held-out frusta take their band's colour and a dot at the camera centre (drawn over
// everything, previews included, and keeping its colour when a query's highlight recolours
// the lines)
function colourHeldOut() {
  const ev = state.evaluation;
  const three = state.three;
  for (const marker of ev.markers.values()) {
    marker.parent?.remove(marker);
    marker.geometry.dispose();
    marker.material.dispose();
  }
  ev.markers.clear();
  const bands = {};
  for (const [id, frustum] of state.frusta) {
    const ref = ev.heldOut.get(id);
    const image = state.images.get(id);
    frustum.base = ref ? bandOf(ref).color : image?.stale ? COLORS.stale : COLORS.reference;
    frustum.lines.material.color.setHex(frustum.base);
    if (!ref || !three || !image) continue;
    const { THREE } = three;
    const point = centre(image.cam_from_world);
    const marker = new THREE.Points(
      new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(...point)]),
      new THREE.PointsMaterial({
        color: frustum.base, size: MARKER_PX, sizeAttenuation: false, depthTest: false,
        transparent: true })); // drawn with the previews, after them (renderOrder)
    marker.renderOrder = 2;
    marker.name = `held out ${ref.name}`;
    marker.userData.point = point;
    frustum.group.add(marker);
    ev.markers.set(id, marker);
    bands[id] = bandOf(ref).band;
  }
  $("scene").dataset.heldOutFrusta = String(ev.markers.size);
  $("scene").dataset.heldOut = JSON.stringify(bands);
  if (three) three.render();
}

// a point of the map in the page's (client) coordinates, null behind the camera
function onScreen(point) {
  const three = state.three;
  const p = new three.THREE.Vector3(...point).project(three.camera);
  if (!(Math.abs(p.z) <= 1)) return null;
  const rect = three.renderer.domElement.getBoundingClientRect();
  return [rect.left + ((p.x + 1) / 2) * rect.width, rect.top + ((1 - p.y) / 2) * rect.height];
}

// the held-out reference whose dot is nearest the pointer, within PICK_PX
function heldOutAt(x, y) {
  let best = null;
  let nearest = PICK_PX;
  for (const [id, marker] of state.evaluation.markers) {
    const at = onScreen(marker.userData.point);
    const d = at ? Math.hypot(at[0] - x, at[1] - y) : Infinity;
    if (d <= nearest) [best, nearest] = [id, d];
  }
  return best;
}

function selectHeldOut(id) {
  state.evaluation.selected = id;
  showSelected(id);
}

function showSelected(id) {
  const ev = state.evaluation;
  const line = $("eval-selected");
  const ref = id ? ev.heldOut.get(id) : null;
  for (const item of $("eval-references").children) {
    item.setAttribute("aria-current", String(item.dataset.imageId === id));
  }
  for (const [markerId, marker] of ev.markers) {
    marker.material.size = markerId === id ? MARKER_PX + 6 : MARKER_PX;
  }
  delete line.dataset.imageId;
  delete line.dataset.band;
  delete line.dataset.screen;
  line.textContent = ev.heldOut.size ? "Click a coloured dot (or a line below) for its error." : "";
  if (ref) {
    line.dataset.imageId = id;
    line.dataset.band = bandOf(ref).band;
    line.textContent = `${ref.name} held out: ${describeHeldOut(ref)}`;
    const marker = ev.markers.get(id);
    const at = marker && onScreen(marker.userData.point);
    if (at) line.dataset.screen = JSON.stringify(at.map((v) => Math.round(v)));
  }
  if (state.three) state.three.render();
}

// hovering a held-out dot names its error; a click (not a drag of the view) picks it
function watchHeldOutPointer(three) {
  const canvas = three.renderer.domElement;
  const tip = $("eval-tip");
  let down = null;
  canvas.addEventListener("pointermove", (event) => {
    const id = event.buttons ? null : heldOutAt(event.clientX, event.clientY);
    const ref = id ? state.evaluation.heldOut.get(id) : null;
    tip.hidden = !ref;
    canvas.style.cursor = ref ? "pointer" : "";
    if (!ref) return;
    const box = $("scene").getBoundingClientRect();
    tip.textContent = `${ref.name} held out: ${describeHeldOut(ref)}`;
    tip.dataset.imageId = id;
    tip.style.left = `${event.clientX - box.left + 14}px`;
    tip.style.top = `${event.clientY - box.top + 14}px`;
  });
  canvas.addEventListener("pointerleave", () => { tip.hidden = true; });
  canvas.addEventListener("pointerdown", (event) => { down = [event.clientX, event.clientY]; });
  canvas.addEventListener("pointerup", (event) => {
    if (!down || Math.hypot(event.clientX - down[0], event.clientY - down[1]) > 4) return;
    down = null;
    const id = heldOutAt(event.clientX, event.clientY);
    if (id) selectHeldOut(id);
  });
}

// --- stale references --------------------------------------------------------------------

// the references a capture session or a self-evaluation flagged stale, read from the images
// listed (their `stale`), with why
function showStale() {
  const stale = [...state.images.values()].filter((image) => image.stale)
    .sort((a, b) => a.name.localeCompare(b.name));
  const panel = $("stale");
  panel.dataset.count = String(stale.length);
  $("stale-summary").textContent = stale.length
    ? `${stale.length} of ${state.images.size} references flagged stale (dashed): they no ` +
      "longer match what capture sessions or self-evaluations saw there. Retire them with " +
      "DELETE …/images/{image_id}."
    : "No reference is flagged stale.";
  const items = stale.slice(0, STALE_LISTED).map((image) => {
    const item = element("li");
    item.dataset.imageId = image.id;
    item.append(element("strong", image.name, "name"), " ",
      element("span", `since ${image.stale.since}: ${image.stale.reason}`, "reason"));
    return item;
  });
  if (stale.length > STALE_LISTED) {
    items.push(element("li", `… and ${stale.length - STALE_LISTED} more`));
  }
  $("stale-list").replaceChildren(...items);
}

// --- capture sessions -------------------------------------------------------------------

const SESSIONS_SHOWN = 20; // the newest sessions listed
const ACTIVE_SESSION = new Set(["queued", "aligning", "adding"]); // refreshed while any is
const known = (x) => x !== null && x !== undefined;
const centimetres = (m) => (known(m) ? `${(m * 100).toFixed(1)} cm` : "—");

function element(tag, text, field) {
  const node = document.createElement(tag);
  if (known(text)) node.textContent = text;
  if (field) node.dataset.field = field;
  return node;
}

// a new map: forget the last one's sessions and read this one's (they need an admin key)
function openSessions(map) {
  const s = state.sessions;
  clearTimeout(s.timer);
  Object.assign(s, { token: s.token + 1, timer: null, refreshes: 0, map, active: new Set(),
    grown: false });
  $("sessions").dataset.state = "loading";
  $("sessions-summary").textContent = "Reading the map's capture sessions…";
  $("sessions-summary").className = "";
  $("sessions-list").replaceChildren();
  $("sessions-refresh").hidden = true;
  return readSessions(map.id, s.token);
}

async function readSessions(mapId, token) {
  try {
    const url = `/v1/maps/${mapId}/sessions?offset=0&limit=${SESSIONS_SHOWN}`;
    return { token, page: await (await api(url)).json() };
  } catch (error) {
    return { token, error };
  }
}

function showSessions(answer) {
  const s = state.sessions;
  if (answer.token !== s.token) return; // another map was picked meanwhile
  const panel = $("sessions");
  const summary = $("sessions-summary");
  clearTimeout(s.timer);
  s.timer = null;
  if (answer.error) { // keep the list shown, if any
    const forbidden = answer.error.status === 401 || answer.error.status === 403;
    panel.dataset.state = forbidden ? "forbidden" : "error";
    summary.textContent = forbidden ? "Capture sessions are shown to an admin key only."
      : `Capture sessions: ${answer.error.message}`;
    summary.className = forbidden ? "" : "error";
    $("sessions-refresh").hidden = forbidden;
    return;
  }
  const { items, total } = answer.page;
  const active = items.some((session) => ACTIVE_SESSION.has(session.state));
  // a session seen active, now added: the map has references this page has not drawn
  s.grown ||= items.some((session) => session.state === "added" && s.active.has(session.id));
  s.active = new Set(items.filter((x) => ACTIVE_SESSION.has(x.state)).map((x) => x.id));
  panel.dataset.state = !items.length ? "none" : active ? "active" : "decided";
  summary.className = "";
  summary.textContent = !items.length ? "This map has no capture sessions."
    : total > items.length ? `The newest ${items.length} of ${total} sessions:`
      : `${total} session${total === 1 ? "" : "s"}, newest first:`;
  if (active && s.refreshes >= EVALUATION_REFRESHES) summary.append(" (Check again for news.)");
  if (s.grown) summary.append(" New references were added: pick the map again to draw them.");
  $("sessions-list").replaceChildren(...items.map(sessionItem));
  $("sessions-refresh").hidden = !active;
  // as a running self-evaluation: looked at again a bounded number of times, less and less often
  if (!active || s.refreshes >= EVALUATION_REFRESHES) return;
  const [first, most] = EVALUATION_REFRESH_S;
  const { token } = s;
  s.timer = setTimeout(() => refreshSessions(token, true),
    Math.min(first * 1.25 ** s.refreshes, most) * 1000);
}

async function refreshSessions(token, automatic) {
  const s = state.sessions;
  if (token !== s.token || !s.map) return;
  clearTimeout(s.timer);
  s.timer = null;
  s.refreshes = automatic ? s.refreshes + 1 : 0;
  showSessions(await readSessions(s.map.id, token));
}

// one session: name, state and frames; its progress while active; once decided, its alignment
function sessionItem(session) {
  const item = element("li");
  item.dataset.sessionId = session.id;
  item.dataset.state = session.state;
  const head = element("div");
  head.append(element("strong", session.name, "name"), ": ",
    element("span", session.state, "state"),
    `, ${session.frames} frames${session.metric ? "" : ", scale unknown"}`);
  if (ACTIVE_SESSION.has(session.state) && session.progress.total) {
    head.append(element("span", ` (${session.progress.done} / ${session.progress.total})`,
      "progress"));
  }
  item.append(head);
  if (session.error) {
    const failed = element("div", session.error, "error");
    failed.className = "error";
    item.append(failed);
  }
  const a = session.alignment;
  if (!a) return item;
  const facts = [["mode", a.mode]];
  if (a.map_from_session) facts.push(["scale", `scale ${a.map_from_session.scale.toFixed(4)}`]);
  if (known(a.confident)) {
    facts.push(["agreeing", `${a.agreeing} of ${a.confident} confident agree`]);
  }
  if (known(a.rms_position_m)) facts.push(["rms", `RMS ${centimetres(a.rms_position_m)}`]);
  if (a.drift_correction_m) {
    facts.push(["drift", `drift corrected ≤ ${centimetres(a.drift_correction_m.max)}`]);
  }
  const line = element("div");
  facts.forEach(([field, text], k) => line.append(k ? ", " : "", element("span", text, field)));
  item.append(line);
  if (a.reason) item.append(element("div", `Refused: ${a.reason}`, "reason"));
  if (!a.checked.length) return item;
  const details = element("details");
  const table = element("table");
  table.className = "checked";
  const titles = element("tr");
  for (const [title, hint] of [["frame", ""], ["loc.", "localized"], ["conf.", "confidence"],
    ["error", "position, rotation error against the alignment"],
    ["agrees", "within the tolerance and 2°"]]) {
    titles.append(Object.assign(element("th", title), { title: hint }));
  }
  table.append(titles);
  for (const c of a.checked) {
    const row = element("tr");
    row.dataset.frame = c.frame;
    const degrees = known(c.rotation_error_deg) ? `${c.rotation_error_deg.toFixed(2)}°` : "—";
    const error = known(c.position_error_m) ? `${centimetres(c.position_error_m)}, ${degrees}`
      : "—";
    for (const text of [c.frame, c.localized ? "yes" : "no", c.confidence.toFixed(2), error,
      c.agrees ? "yes" : "no"]) row.append(element("td", text));
    table.append(row);
  }
  details.append(element("summary", `${a.checked.length} checked frames`), table);
  item.append(details);
  return item;
}

// --- coverage ---------------------------------------------------------------------------

const WEAK_LISTED = 10; // weak cells whose reasons the panel lists

// a new map: forget the last one's cells and read this one's (drawn once its frusta are)
function openCoverage(map) {
  const c = state.coverage;
  Object.assign(c, { token: c.token + 1, map });
  const panel = $("coverage");
  panel.dataset.state = "loading";
  panel.dataset.cells = panel.dataset.weak = "0";
  delete panel.dataset.evaluationId;
  $("coverage-summary").textContent = "Reading the map's coverage…";
  $("coverage-summary").className = "";
  $("coverage-weak").replaceChildren();
  return readCoverage(map.id, c.token);
}

async function readCoverage(mapId, token) {
  try {
    return { token, coverage: await (await api(`/v1/maps/${mapId}/coverage`)).json() };
  } catch (error) {
    return { token, error };
  }
}

async function refreshCoverage() {
  const c = state.coverage;
  if (!c.map) return;
  c.token += 1; // an earlier read still on its way is dropped
  showCoverage(await readCoverage(c.map.id, c.token));
}

function showCoverage(answer) {
  const c = state.coverage;
  if (answer.token !== c.token) return; // another map was picked meanwhile
  const panel = $("coverage");
  const summary = $("coverage-summary");
  if (answer.error) { // keep the cells drawn, if any
    const forbidden = answer.error.status === 401 || answer.error.status === 403;
    panel.dataset.state = forbidden ? "forbidden" : "error";
    summary.textContent = forbidden ? "Coverage: not shown to this key."
      : `Coverage: ${answer.error.message}`;
    summary.className = forbidden ? "" : "error";
    return;
  }
  const found = answer.coverage;
  const weak = found.cells.filter((cell) => cell.weak);
  panel.dataset.state = "done";
  panel.dataset.cells = String(found.cells.length);
  panel.dataset.weak = String(weak.length);
  if (found.evaluation_id) panel.dataset.evaluationId = found.evaluation_id;
  const n = found.cells.length;
  summary.textContent = `${n} cell${n === 1 ? "" : "s"}, ${weak.length} weak`;
  summary.append(` (squares of ${formatLength(found.cell_m)} on the references' plane, weak ` +
    "ones red)", found.evaluation_id ? "." : "; no finished self-evaluation: only cells with " +
    "a single reference are weak.");
  const items = weak.slice(0, WEAK_LISTED).map((cell) => {
    const item = element("li", `cell (${cell.i}, ${cell.j}): ${cell.why.join("; ")}`);
    Object.assign(item.dataset, { i: String(cell.i), j: String(cell.j) });
    return item;
  });
  if (weak.length > WEAK_LISTED) items.push(element("li", `… and ${weak.length - WEAK_LISTED} more`));
  $("coverage-weak").replaceChildren(...items);
  drawCoverage(found);
}

// one square per cell (a hair smaller, so that neighbours stay apart), spanned by the plane's
// u and v at the cell's centre, in the map's group; one geometry and two materials for all
function drawCoverage({ plane, cell_m: side, cells }) {
  const three = state.three;
  const c = state.coverage;
  if (c.group) {
    c.group.parent?.remove(c.group);
    disposeTree(c.group);
  }
  c.group = null;
  $("scene").dataset.coverageCells = "0";
  if (!three || !three.group) return;
  const { THREE } = three;
  const u = new THREE.Vector3(...plane.u);
  const v = new THREE.Vector3(...plane.v);
  const turn = new THREE.Quaternion().setFromRotationMatrix(
    new THREE.Matrix4().makeBasis(u, v, new THREE.Vector3().crossVectors(u, v)));
  const geometry = new THREE.PlaneGeometry(0.94 * side, 0.94 * side);
  const material = (color, opacity) => new THREE.MeshBasicMaterial({
    color, opacity, transparent: true, side: THREE.DoubleSide, depthWrite: false });
  const weak = material(COLORS.weakCell, 0.45);
  const fine = material(COLORS.cell, 0.18);
  c.group = new THREE.Group();
  c.group.name = "coverage";
  for (const cell of cells.slice(0, MAX_IMAGES)) {
    const square = new THREE.Mesh(geometry, cell.weak ? weak : fine);
    square.name = `cell ${cell.i},${cell.j}`;
    square.quaternion.copy(turn);
    square.position.set(...cell.center);
    c.group.add(square);
  }
  three.group.add(c.group);
  $("scene").dataset.coverageCells = String(c.group.children.length);
  three.render();
}

// --- GeoPose ----------------------------------------------------------------------------

// the heading (degrees clockwise from North) a GeoPose camera looks along: its quaternion
// turns OpenGL camera axes (looking along −z) into East-North-Up
function heading({ x, y, z, w }) {
  const east = -(2 * (x * z + w * y));
  const north = -(2 * (y * z - w * x));
  if (Math.hypot(east, north) < 1e-6) return null; // looking straight up or down
  return ((Math.atan2(east, north) * 180) / Math.PI + 360) % 360;
}

function showGeoPose(result) {
  const panel = $("geopose");
  panel.replaceChildren();
  delete panel.dataset.lat;
  delete panel.dataset.lon;
  if (!result) return;
  if (!result.geopose) {
    panel.textContent = state.geo
      ? `No GeoPose: ${result.localized ? "left out (not finite)" : "not localized"}.`
      : "";
    return;
  }
  const { position: p, quaternion: q } = result.geopose;
  panel.dataset.lat = String(p.lat);
  panel.dataset.lon = String(p.lon);
  const rows = [
    ["lat", `${p.lat.toFixed(8)}°`],
    ["lon", `${p.lon.toFixed(8)}°`],
    ["h", `${p.h.toFixed(3)} m`],
    ["quaternion", `x ${q.x.toFixed(4)}, y ${q.y.toFixed(4)}, z ${q.z.toFixed(4)}, w ${q.w.toFixed(4)}`],
  ];
  const yaw = heading(q);
  if (yaw !== null) rows.push(["heading", `${yaw.toFixed(1)}° from North`]);
  const a = result.geopose_accuracy;
  if (a) {
    rows.push(["1-σ", `${a.horizontal_m.toFixed(2)} m horizontal, ${a.vertical_m.toFixed(2)} m ` +
      `vertical, ${a.yaw_deg.toFixed(2)}° yaw`]);
  }
  const title = document.createElement("p");
  title.textContent = "GeoPose of the last answer (OGC Basic-Quaternion, camera axes OpenGL → ENU):";
  const list = document.createElement("dl");
  for (const [name, value] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = name;
    const dd = document.createElement("dd");
    dd.dataset.field = name;
    dd.textContent = value;
    list.append(dt, dd);
  }
  panel.append(title, list);
}

// --- match figures ----------------------------------------------------------------------

function setUpMatches(result, queryBitmap) {
  const pairs = (result.inliers || []).filter((pair) => state.images.has(pair.image_id));
  state.matches = { pairs, index: 0, queryBitmap, token: state.matches.token + 1 };
  const container = $("matches");
  container.hidden = pairs.length === 0;
  delete container.dataset.ready;
  if (!pairs.length) {
    container.dataset.ready = "true";
    return;
  }
  showFigure(0);
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

// `count` indices spread evenly over [0, n)
function spread(n, count) {
  if (n <= count) return [...Array(n).keys()];
  return [...Array(count).keys()].map((i) => Math.floor(((i + 0.5) * n) / count));
}

async function showFigure(index) {
  const matches = state.matches;
  const { pairs, queryBitmap } = matches;
  if (!pairs.length) return;
  index = ((index % pairs.length) + pairs.length) % pairs.length;
  matches.index = index;
  const token = ++matches.token;
  const container = $("matches");
  delete container.dataset.ready;
  const pair = pairs[index];
  const image = state.images.get(pair.image_id);
  $("match-position").textContent = `${index + 1} / ${pairs.length}`;
  $("match-prev").disabled = $("match-next").disabled = pairs.length < 2;
  const reference = await referenceBitmap(image);
  if (token !== state.matches.token) return; // another figure was asked for meanwhile

  const qs = MATCH_HEIGHT / queryBitmap.height;
  const rs = MATCH_HEIGHT / image.camera.height;
  const qw = queryBitmap.width * qs;
  const gap = 8;
  const canvas = document.createElement("canvas");
  canvas.className = "match-view";
  canvas.dataset.imageId = image.id;
  canvas.dataset.index = String(index);
  canvas.dataset.inliers = String(pair.query_xy.length);
  canvas.width = Math.round(qw + gap + image.camera.width * rs);
  canvas.height = MATCH_HEIGHT;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(queryBitmap, 0, 0, qw, MATCH_HEIGHT);
  const left = qw + gap;
  ctx.fillStyle = "#bbb";
  ctx.fillRect(left, 0, image.camera.width * rs, MATCH_HEIGHT);
  if (reference) {
    ctx.drawImage(reference, left, 0, image.camera.width * rs, MATCH_HEIGHT);
    reference.close();
  }
  const drawn = spread(pair.query_xy.length, MAX_LINES);
  ctx.lineWidth = 1.5;
  drawn.forEach((i, k) => {
    const [qx, qy] = pair.query_xy[i];
    const [rx, ry] = pair.reference_xy[i];
    const colour = `hsl(${Math.round((360 * k) / drawn.length)}, 85%, 50%)`;
    ctx.strokeStyle = colour;
    ctx.fillStyle = colour;
    ctx.beginPath();
    ctx.moveTo(qx * qs, qy * qs);
    ctx.lineTo(left + rx * rs, ry * rs);
    ctx.stroke();
    for (const [x, y] of [[qx * qs, qy * qs], [left + rx * rs, ry * rs]]) {
      ctx.beginPath();
      ctx.arc(x, y, 2.5, 0, 2 * Math.PI);
      ctx.fill();
    }
  });
  canvas.dataset.lines = String(drawn.length);
  const caption = $("match-caption");
  const shown = drawn.length < pair.query_xy.length ? `, ${drawn.length} drawn` : "";
  caption.textContent = `query ↔ ${image.name}: ${pair.query_xy.length} inliers${shown}`;
  $("match-canvas").replaceChildren(canvas);
  container.dataset.index = String(index);
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
  $("eval-refresh").addEventListener("click", () => refreshEvaluation(state.evaluation.token, false));
  $("sessions-refresh").addEventListener("click",
    () => refreshSessions(state.sessions.token, false));
  $("localize-form").addEventListener("submit", localize);
  $("match-prev").addEventListener("click", () => showFigure(state.matches.index - 1));
  $("match-next").addEventListener("click", () => showFigure(state.matches.index + 1));
  $("matches").addEventListener("keydown", (event) => {
    if (event.key === "ArrowLeft") showFigure(state.matches.index - 1);
    if (event.key === "ArrowRight") showFigure(state.matches.index + 1);
  });
  const modules = await loadThree();
  if (modules) {
    state.three = setUpScene(modules);
    watchHeldOutPointer(state.three);
  }
  document.body.dataset.ready = "true";
  await loadMaps();
}

main();

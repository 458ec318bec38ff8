// The TypeScript client against a live `slloc serve`: the README's demo flow (create a map,
// upload the references with their metadata, localize a query), problems as ProblemError, and
// Retry-After against a local HTTP server answering 503. Prints one JSON line with the pose and
// what it saw; tests/clients/test_typescript_client.py checks the pose against the ground truth.
//
//   node test/e2e.mjs <server URL> <`slloc synth` folder>
import assert from "node:assert/strict";
import { readFile, readdir } from "node:fs/promises";
import { createServer } from "node:http";
import { join } from "node:path";

import { Client, ProblemError } from "../dist/index.js";

const [url, demo] = process.argv.slice(2);
const slloc = new Client(url);

const health = await slloc.health();
assert.ok(["ok", "degraded"].includes(health.status));
// the server's own configuration by name: the map does not evaluate itself as it grows
const served = health.models.feature_configurations[0];
const map = await slloc.createMap({ name: "typescript-client", features: { preset: served } });
assert.equal(map.features.auto, false);
const metas = (await readdir(join(demo, "references"))).filter((f) => f.endsWith(".json")).sort();
for (const meta of metas) {
  const metadata = JSON.parse(await readFile(join(demo, "references", meta), "utf8"));
  const png = await readFile(join(demo, "references", meta.replace(/\.json$/, ".png")));
  // a Blob as a browser would send it (a Buffer works too)
  const added = await slloc.addImage(map.id, new Blob([png], { type: "image/png" }), metadata);
  assert.equal(added.name, metadata.name);
}
assert.equal((await slloc.getMap(map.id)).image_count, metas.length);
const changed = await slloc.updateMap(map.id, { description: "kitchen" });
assert.equal(changed.description, "kitchen");
assert.equal(changed.features.state, "ready");
assert.equal((await slloc.listImages(map.id, { limit: 1000 })).total, metas.length);

const params = JSON.parse(await readFile(join(demo, "queries", "query0000.params.json"), "utf8"));
const query = await readFile(join(demo, "queries", "query0000.png"));
const result = await slloc.localize(map.id, query, {
  camera: params.camera,
  params: { estimator: params.estimator, top_k: params.top_k },
});
assert.ok(result.localized, String(result.reason));

let notFound;
try {
  await slloc.getMap("00000000-0000-4000-8000-000000000000");
} catch (error) {
  notFound = error;
}
assert.ok(notFound instanceof ProblemError && notFound instanceof Error);
assert.equal(notFound.status, 404);
assert.ok(notFound.requestId);

// a self-evaluation with the server's configuration, two references held out
const started = await slloc.startEvaluation(map.id, { configurations: [served], sample_size: 2 });
assert.equal(started.state, "queued");
let evaluation = started;
for (let i = 0; i < 600 && ["queued", "running"].includes(evaluation.state); i += 1) {
  await new Promise((resolve) => setTimeout(resolve, 200));
  evaluation = await slloc.getEvaluation(map.id, started.id);
}
assert.equal(evaluation.state, "done", String(evaluation.error));
assert.equal(evaluation.result.configurations[served].held_out, 2);
assert.deepEqual((await slloc.listEvaluations(map.id)).items.map((e) => e.id), [started.id]);
await slloc.deleteEvaluation(map.id, started.id);
assert.equal((await slloc.listEvaluations(map.id)).total, 0);
await slloc.deleteMap(map.id);

// Retry-After: a server answering 503 twice, then an empty map page
let seen = 0;
const busy = createServer((request, response) => {
  seen += 1;
  if (seen <= 2) {
    response.writeHead(503, { "Content-Type": "application/problem+json", "Retry-After": "1" });
    response.end(JSON.stringify({ type: "https://slloc.dev/problems/busy", title: "Busy", status: 503 }));
  } else {
    response.writeHead(200, { "Content-Type": "application/json" });
    response.end(JSON.stringify({ items: [], total: 0, offset: 0, limit: 100 }));
  }
});
await new Promise((resolve) => busy.listen(0, "127.0.0.1", resolve));
const busyUrl = `http://127.0.0.1:${busy.address().port}`;
const waits = [];
const patient = new Client(busyUrl, { sleep: async (s) => void waits.push(s) });
assert.equal((await patient.listMaps()).total, 0);
assert.deepEqual(waits, [1, 1]);
seen = 0;
const impatient = new Client(busyUrl, { maxRetries: 1, sleep: async (s) => void waits.push(s) });
const refused = await impatient.listMaps().catch((error) => error);
assert.ok(refused instanceof ProblemError);
assert.equal(refused.status, 503);
assert.equal(refused.retryAfter, 1);
assert.equal(refused.type, "https://slloc.dev/problems/busy");
busy.close();

console.log(
  JSON.stringify({
    cam_from_world: result.cam_from_world,
    not_found: { type: notFound.type, status: notFound.status, request_id: notFound.requestId },
    retry_waits: waits,
  }),
);

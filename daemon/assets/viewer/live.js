// choreod live page: poses the rest-pose mannequin (/mannequin.glb) from the WebSocket's
// messages (wire version 2, see daemon/src/live/viewer.rs): `rest` sets every bone's offset
// from its parent (the session's rigid fit), a frame sets the root's position and every
// joint's rotation (global rotations on the wire; a bone's local one is its parent's inverse
// times its own).
//
// For tests and scripts: window.choreod.pose() gives { frame, joints } (every joint's world
// position as drawn, metres) of the frame on the screen.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { makeStage } from "/stage.js";

const WIRE_VERSION = 2;
const el = (id) => document.getElementById(id);
const stage = makeStage(el("view"));
// The mannequin's floor: live output stands on y = 0, less a capsule's radius.
stage.grid.position.y = -0.03;

let joints = [], parents = [], hips = null, shown = -1, received = 0, framed = false;
const global = [], inverse = new THREE.Quaternion();

function applyRest(rest) {
  rest.forEach((offset, k) => {
    if (parents[k] >= 0) joints[k].position.fromArray(offset);
  });
}

function applyFrame(m) {
  // Normalised: the wire's rounding leaves |q| within 2e-4 of 1, which would scale bones.
  m.rotations.forEach((q, k) => global[k].fromArray(q).normalize());
  joints.forEach((node, k) => {
    const p = parents[k];
    if (p < 0) node.quaternion.copy(global[k]);
    else node.quaternion.copy(inverse.copy(global[p]).invert().multiply(global[k]));
  });
  hips.position.fromArray(m.root);
  hips.parent.updateMatrixWorld(true);
  shown = m.frame;
  received += 1;
  el("frame").textContent = String(m.frame);
  el("received").textContent = String(received);
  if (!framed) {
    stage.frame(hips);
    hips.parent.visible = true;
    framed = true;
  }
}

function receive(ev) {
  const m = JSON.parse(ev.data);
  if (m.v !== WIRE_VERSION) {
    el("mode").textContent = `live · unknown message version ${m.v} (reload the page)`;
    return;
  }
  // A status (e.g. "waiting for audio") stands until frames come again.
  if (m.status) el("mode").textContent = `live · ${m.status}`;
  else if (m.rest) applyRest(m.rest);
  else if (m.rotations) {
    el("mode").textContent = "live";
    applyFrame(m);
  }
}

function tick() {
  stage.render(framed ? hips : null);
  requestAnimationFrame(tick);
}

async function start() {
  const skeleton = await (await fetch("/skeleton.json")).json();
  parents = skeleton.parents;
  el("joints").textContent = String(parents.length);
  const gltf = await new GLTFLoader().loadAsync("/mannequin.glb");
  joints = await Promise.all(skeleton.nodes.map((n) => gltf.parser.getDependency("node", n)));
  joints.forEach(() => global.push(new THREE.Quaternion()));
  hips = joints[parents.indexOf(-1)];
  // Hidden until the first frame poses it; never culled (its bounds are the rest pose's, at
  // the origin, and the dancer moves).
  gltf.scene.visible = false;
  gltf.scene.traverse((o) => { if (o.isMesh) o.frustumCulled = false; });
  stage.scene.add(gltf.scene);
  el("mode").textContent = "live";
  const ws = new WebSocket(`ws://${location.host}/ws`);
  ws.onmessage = receive;
  ws.onclose = () => { el("mode").textContent = "live (ended)"; };
  requestAnimationFrame(tick);
}

window.choreod = {
  pose() {
    const p = new THREE.Vector3();
    return { frame: shown, joints: joints.map((j) => j.getWorldPosition(p).toArray()) };
  },
};
start().catch((e) => {
  el("mode").textContent = `error: ${e.message || e}`;
  console.error(e);
});

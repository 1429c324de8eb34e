// choreod player: plays /motion.glb's animation on its mannequin, in step with /audio.wav.
//
// One clock: with a song, the audio element's currentTime is the time (so picture and sound
// cannot drift apart); without one, the page's own clock. The slider and the readout show that
// time; the frame is the motion's frame at that time (frame k spans [k, k + 1) / fps).
//
// For tests and scripts: `?t=SECONDS` opens paused at that time; window.choreod exposes
// { ready, time(), duration, fps, frames, seek(t), play(), pause() }.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const el = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const canvas = el("view");
const song = el("song");

const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setClearColor(0x16181d);
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x30343c, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 2.0);
sun.position.set(2, 4, 3);
scene.add(sun);
const grid = new THREE.GridHelper(10, 20, 0x4c566a, 0x2e3440);
scene.add(grid);
const camera = new THREE.PerspectiveCamera(40, 1, 0.05, 100);
const controls = new OrbitControls(camera, canvas);

function resize() {
  renderer.setSize(window.innerWidth, window.innerHeight, false);
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();

const clock = { playing: false, base: 0, since: 0 };
let mixer = null, hips = null, duration = 0, fps = 0, frames = 0, hasSong = false;

function now() {
  if (hasSong) return Math.min(song.currentTime, duration);
  if (!clock.playing) return clock.base;
  const t = clock.base + (performance.now() - clock.since) / 1000;
  return duration > 0 ? t % duration : t; // no song: loop
}

function seek(t) {
  t = Math.max(0, Math.min(duration, t));
  if (hasSong) song.currentTime = t;
  clock.base = t;
  clock.since = performance.now();
}

async function play() {
  if (hasSong) {
    if (song.currentTime >= duration) song.currentTime = 0;
    try {
      await song.play();
    } catch (e) {
      el("status").textContent = `press play to start with sound (${e.name})`;
      return;
    }
  } else {
    clock.base = now();
    clock.since = performance.now();
    clock.playing = true;
  }
  el("play").textContent = "pause";
  el("status").textContent = "";
}

function pause() {
  if (hasSong) song.pause();
  else {
    clock.base = now();
    clock.playing = false;
  }
  el("play").textContent = "play";
}

const playing = () => (hasSong ? !song.paused && !song.ended : clock.playing);

function fmt(t) {
  const m = Math.floor(t / 60);
  return `${m}:${(t - 60 * m).toFixed(2).padStart(5, "0")}`;
}

// The pose at time t: the clip repeats (a mixer stops a finished one-shot clip for good), so
// the last key is reached just before it would wrap.
function pose(t) {
  mixer.setTime(Math.min(t, duration - 1e-6));
}

let dragging = false;
function tick() {
  const t = now();
  if (mixer) {
    pose(t);
    // Follow the dancer: look at the hips, keep the camera's offset.
    hips.getWorldPosition(followed);
    const shift = followed.clone().sub(controls.target).setY(0);
    controls.target.add(shift);
    camera.position.add(shift);
    controls.update();
  }
  renderer.render(scene, camera);
  el("time").textContent = `${fmt(t)} / ${fmt(duration)}`;
  el("frame").textContent = String(Math.min(frames - 1, Math.floor(t * fps + 1e-6)));
  if (!dragging) el("scrub").value = String(t);
  if (hasSong && song.ended) el("play").textContent = "play";
  requestAnimationFrame(tick);
}
const followed = new THREE.Vector3();

el("play").addEventListener("click", () => (playing() ? pause() : play()));
window.addEventListener("keydown", (e) => {
  if (e.code === "Space") {
    e.preventDefault();
    playing() ? pause() : play();
  }
});
el("scrub").addEventListener("input", (e) => {
  dragging = true;
  seek(+e.target.value);
});
el("scrub").addEventListener("change", () => (dragging = false));

async function start() {
  const skeleton = await (await fetch("/skeleton.json")).json();
  fps = skeleton.fps;
  el("joints").textContent = String(skeleton.parents.length);
  el("fps").textContent = String(+fps.toFixed(3));
  const gltf = await new GLTFLoader().loadAsync("/motion.glb");
  scene.add(gltf.scene);
  const clip = gltf.animations[0];
  duration = clip.duration;
  frames = Math.round(duration * fps) + 1;
  el("frames").textContent = String(frames);
  mixer = new THREE.AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  // Node 0 is the root joint (choreod writes joints first, in the motion's order).
  hips = await gltf.parser.getDependency("node", 0);
  el("scrub").max = String(duration);
  // The floor under the lowest joint of the whole dance (a file's floor need not be y = 0),
  // less a capsule's radius; the camera at the hips' height.
  const joints = await Promise.all(skeleton.parents.map((_, i) => gltf.parser.getDependency("node", i)));
  let lowest = Infinity;
  const p = new THREE.Vector3();
  for (let s = 0; s <= 60; s++) {
    pose((duration * s) / 60);
    gltf.scene.updateMatrixWorld(true);
    for (const j of joints) lowest = Math.min(lowest, j.getWorldPosition(p).y);
  }
  grid.position.y = lowest - 0.03;
  pose(0);
  gltf.scene.updateMatrixWorld(true);
  hips.getWorldPosition(followed);
  controls.target.copy(followed);
  camera.position.set(followed.x + 2.2, followed.y + 0.5, followed.z + 3.3);
  controls.update();

  const audio = await fetch("/audio.wav");
  if (audio.ok) {
    // A blob URL: seeking works without range requests.
    song.src = URL.createObjectURL(await audio.blob());
    await new Promise((ok, fail) => {
      song.addEventListener("loadedmetadata", ok, { once: true });
      song.addEventListener("error", () => fail(song.error), { once: true });
    });
    hasSong = true;
    el("mode").textContent = "file with song";
  } else {
    el("mode").textContent = "file";
  }
  requestAnimationFrame(tick);
  if (params.has("t")) seek(+params.get("t"));
  else await play();
  window.choreod.ready = true;
}

window.choreod = { ready: false, time: now, seek, play, pause, playing,
  get duration() { return duration; }, get fps() { return fps; }, get frames() { return frames; } };
start().catch((e) => {
  el("mode").textContent = "error";
  el("status").textContent = `could not load the motion: ${e.message || e}`;
  console.error(e);
});

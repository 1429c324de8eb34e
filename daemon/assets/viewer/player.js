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
import { makeStage } from "/stage.js";

const el = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const canvas = el("view");
const song = el("song");

const stage = makeStage(canvas);

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
    el("status").textContent = "";
  } else {
    clock.base = now();
    clock.since = performance.now();
    clock.playing = true;
  }
  el("play").textContent = "pause";
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
  if (mixer) pose(t);
  stage.render(hips);
  el("time").textContent = `${fmt(t)} / ${fmt(duration)}`;
  el("frame").textContent = String(Math.min(frames - 1, Math.floor(t * fps + 1e-6)));
  if (!dragging) el("scrub").value = String(t);
  if (hasSong && song.ended) el("play").textContent = "play";
  requestAnimationFrame(tick);
}

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
  stage.scene.add(gltf.scene);
  const clip = gltf.animations[0];
  duration = clip.duration;
  frames = Math.round(duration * fps) + 1;
  el("frames").textContent = String(frames);
  mixer = new THREE.AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  // The skeleton's glTF nodes; the first root is the hips.
  const joints = await Promise.all(skeleton.nodes.map((n) => gltf.parser.getDependency("node", n)));
  hips = joints[Math.max(0, skeleton.parents.indexOf(-1))];
  el("scrub").max = String(duration);
  // The floor under the lowest joint of the whole dance (a file's floor need not be y = 0),
  // less a capsule's radius; the camera at the hips' height.
  let lowest = Infinity;
  const p = new THREE.Vector3();
  for (let s = 0; s <= 60; s++) {
    pose((duration * s) / 60);
    gltf.scene.updateMatrixWorld(true);
    for (const j of joints) lowest = Math.min(lowest, j.getWorldPosition(p).y);
  }
  stage.grid.position.y = lowest - 0.03;
  pose(0);
  gltf.scene.updateMatrixWorld(true);
  stage.frame(hips);

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
    // Why there is no song (e.g. the one beside the file is not the one it was made from).
    el("status").textContent = await audio.text();
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

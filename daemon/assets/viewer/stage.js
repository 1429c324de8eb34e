// choreod viewer pages' stage: a three.js renderer on #view, lights, a floor grid and a camera
// that follows the dancer's hips. Shared by the player (a file) and the live page.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

export function makeStage(canvas) {
  // preserveDrawingBuffer: tests and screenshots read the canvas between frames.
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
  const resize = () => {
    renderer.setSize(window.innerWidth, window.innerHeight, false);
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
  };
  window.addEventListener("resize", resize);
  resize();
  const followed = new THREE.Vector3();
  return {
    scene,
    grid,
    // Look at `hips` from 4 m, front-right and a little above.
    frame(hips) {
      hips.getWorldPosition(followed);
      controls.target.copy(followed);
      camera.position.set(followed.x + 2.2, followed.y + 0.5, followed.z + 3.3);
      controls.update();
    },
    // Follow `hips`: keep the camera's offset (the user may have orbited) and draw. Hips more
    // than 5 m from where the camera looks (a body far off the floor, as an untrained model's
    // can be) are framed afresh.
    render(hips) {
      if (hips) {
        hips.getWorldPosition(followed);
        if (followed.distanceTo(controls.target) > 5) this.frame(hips);
        const shift = followed.clone().sub(controls.target).setY(0);
        controls.target.add(shift);
        camera.position.add(shift);
        controls.update();
      }
      renderer.render(scene, camera);
    },
  };
}

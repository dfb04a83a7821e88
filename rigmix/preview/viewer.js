// rigmix preview: a glTF character with a clip selector, play/pause, a timeline and the
// skeleton overlay. Everything is local (three.js is copied next to this file).
//
// The page state is exposed as `window.rigmixViewer` for scripts and tests:
//   ready, error, clips (names), current, time, duration, playing,
//   select(name), setTime(seconds), play(), pause().
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const MODEL = './model.glb';

const view = document.getElementById('view');
const clipSelect = document.getElementById('clip');
const playButton = document.getElementById('play');
const timeline = document.getElementById('time');
const clock = document.getElementById('clock');
const bonesBox = document.getElementById('bones');
const errorBox = document.getElementById('error');

const state = {
  ready: false, error: null, clips: [], current: null, time: 0, duration: 0, playing: true,
  select, setTime, play, pause,
};
window.rigmixViewer = state;

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
renderer.outputColorSpace = THREE.SRGBColorSpace;
view.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color(0x30343c);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(1, 2, 3);
scene.add(sun);

const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
const controls = new OrbitControls(camera, renderer.domElement);
const timer = new THREE.Timer();
timer.connect(document);

let mixer = null;
let action = null;
let clips = [];
let helper = null;

function fail(message) {
  state.error = String(message);
  errorBox.textContent = state.error;
  console.error(message);
}

function resize() {
  const w = view.clientWidth || 1;
  const h = view.clientHeight || 1;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);

function frameObject(root) {
  // bounds of the posed meshes and of every bone (skinned bounds follow the current pose)
  root.updateMatrixWorld(true);
  const box = new THREE.Box3();
  const p = new THREE.Vector3();
  root.traverse((o) => {
    if (o.isSkinnedMesh) {
      o.computeBoundingBox();
      box.union(o.boundingBox.clone().applyMatrix4(o.matrixWorld));
    } else if (o.isMesh) {
      box.expandByObject(o);
    }
    if (o.isBone) box.expandByPoint(o.getWorldPosition(p));
  });
  if (box.isEmpty()) box.setFromCenterAndSize(new THREE.Vector3(), new THREE.Vector3(1, 1, 1));
  const center = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3()).length() || 1;
  camera.near = size / 1000;
  camera.far = size * 100;
  camera.position.copy(center).add(new THREE.Vector3(0.6, 0.35, 1.0).normalize().multiplyScalar(size * 1.3));
  camera.updateProjectionMatrix();
  controls.target.copy(center);
  controls.update();
}

function showClock() {
  clock.textContent = `${state.time.toFixed(3)} / ${state.duration.toFixed(3)} s`;
  timeline.value = String(state.duration > 0 ? state.time / state.duration : 0);
  document.body.dataset.clip = state.current || '';
  document.body.dataset.time = state.time.toFixed(4);
}

function render() {
  renderer.render(scene, camera);
}

function select(name) {
  const clip = clips.find((c) => c.name === name);
  if (!clip) throw new Error(`rigmix preview: no clip named ${JSON.stringify(name)}`);
  if (action) action.stop();
  action = mixer.clipAction(clip);
  action.play();
  action.paused = !state.playing;
  state.current = clip.name;
  state.duration = clip.duration;
  clipSelect.value = clip.name;
  setTime(0);
  return state.current;
}

function setTime(t) {
  if (!action) return 0;
  const d = state.duration;
  const time = d > 0 ? Math.min(Math.max(Number(t), 0), d) : 0;
  action.time = time;
  mixer.update(0);
  state.time = time;
  showClock();
  render();
  return time;
}

function play() {
  state.playing = true;
  if (action) action.paused = false;
  playButton.textContent = 'pause';
  timer.reset();
}

function pause() {
  state.playing = false;
  if (action) action.paused = true;
  playButton.textContent = 'play';
}

clipSelect.addEventListener('change', () => select(clipSelect.value));
playButton.addEventListener('click', () => (state.playing ? pause() : play()));
timeline.addEventListener('input', () => { pause(); setTime(Number(timeline.value) * state.duration); });
bonesBox.addEventListener('change', () => { if (helper) { helper.visible = bonesBox.checked; render(); } });

function loop(timestamp) {
  requestAnimationFrame(loop);
  timer.update(timestamp);
  const dt = timer.getDelta();
  if (mixer && action && state.playing) {
    mixer.update(dt);
    state.time = action.time % (state.duration || 1);
    showClock();
  }
  controls.update();
  render();
}

resize();
new GLTFLoader().load(
  MODEL,
  (gltf) => {
    const root = gltf.scene;
    scene.add(root);
    helper = new THREE.SkeletonHelper(root);
    helper.material.depthTest = false;
    helper.material.transparent = true;
    helper.renderOrder = 1;
    helper.visible = bonesBox.checked;
    scene.add(helper);
    mixer = new THREE.AnimationMixer(root);
    clips = gltf.animations;
    state.clips = clips.map((c) => c.name);
    for (const name of state.clips) {
      const option = document.createElement('option');
      option.value = name;
      option.textContent = name;
      clipSelect.appendChild(option);
    }
    frameObject(root);
    if (clips.length) select(clips[0].name);
    else { clipSelect.disabled = true; playButton.disabled = true; timeline.disabled = true; }
    state.ready = true;
    document.body.dataset.ready = 'true';
    loop();
  },
  undefined,
  (err) => fail(`rigmix preview: cannot load ${MODEL}: ${err && err.message ? err.message : err}`),
);

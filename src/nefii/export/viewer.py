"""``nefii view``'s page: the GLB under the recovered environment, in three.js, in one HTML file.

Everything is inline so the page opens offline from ``file://``: three.js modules as ``data:``
URLs in an import map (see ``three.py``), the GLB and the environment (a float EXR in the
docs/design.md mapping) as base64 blocks. three.js is Y-up like the GLB, and its equirectangular
lookup (``u = atan2(z, x) / 2 pi + 0.5``, ``v = asin(y) / pi + 0.5``, EXR rows bottom-up) is
exactly nefii's mapping once world (x, y, z) is stored as (x, z, -y): the light needs no rotation.

URL fragment options, for links and tests: ``#mode=shaded|albedo|roughness``, ``background=0``,
``ev=<exposure in stops>``. The page sets ``document.title`` to ``nefii view: ready`` after its
first frame, or ``nefii view: error: ...``; ``window.nefiiView`` holds the scene, camera and
controls for scripting.
"""
from __future__ import annotations

import base64
import html
import json
import math

import numpy as np

from .three import THREE_VERSION, ThreeSource, module_sources


def default_exposure(env: np.ndarray) -> float:
    """Stops that bring a grey diffuse surface lit by ``env`` to about mid-grey: ``-log2`` of the
    env's mean luminance over the sphere (solid-angle weighted)."""
    h = env.shape[0]
    theta = (np.arange(h) + 0.5) / h * math.pi
    lum = env[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    mean = float((lum.mean(1) * np.sin(theta)).sum() / np.sin(theta).sum())
    return float(np.clip(-math.log2(max(mean, 1e-8)), -20.0, 20.0))


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def build_page(glb: bytes, env_exr: bytes, exposure: float, title: str, three: ThreeSource) -> str:
    imports = {key: "data:text/javascript;base64," + _b64(text.encode("utf-8"))
               for key, text in module_sources(three).items()}
    return (_PAGE.replace("@TITLE@", html.escape(title))
            .replace("@THREE_VERSION@", THREE_VERSION)
            .replace("@EV@", f"{exposure:.3f}")
            .replace("@IMPORTMAP@", json.dumps({"imports": imports}))
            .replace("@GLB@", _b64(glb))
            .replace("@ENV@", _b64(env_exr)))


_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>nefii view: loading</title>
<style>
  html, body { margin: 0; height: 100%; overflow: hidden; background: #000; font: 13px system-ui, sans-serif; }
  canvas { display: block; }
  #panel { position: absolute; top: 8px; left: 8px; padding: 8px 10px; border-radius: 6px;
           background: rgba(20, 20, 20, 0.75); color: #eee; line-height: 1.7; }
  #panel b { font-weight: 600; }
  #status { color: #f88; white-space: pre-wrap; max-width: 40em; }
  label { margin-right: 8px; cursor: pointer; }
</style>
<script type="importmap">@IMPORTMAP@</script>
</head>
<body>
<div id="panel">
  <b>@TITLE@</b><br>
  <label><input type="radio" name="mode" value="shaded" checked> shaded</label>
  <label><input type="radio" name="mode" value="albedo"> albedo</label>
  <label><input type="radio" name="mode" value="roughness"> roughness</label><br>
  <label><input type="checkbox" id="background" checked> environment</label>
  <label>exposure <input type="range" id="ev" min="-6" max="6" step="0.25" value="0">
    <span id="evtext"></span></label><br>
  <small>drag: orbit &middot; right-drag: pan &middot; wheel: zoom &middot; three.js @THREE_VERSION@</small>
  <div id="status"></div>
</div>
<script id="glb" type="application/octet-stream">@GLB@</script>
<script id="env" type="application/octet-stream">@ENV@</script>
<script>
  function nefiiFail(msg) {
    document.title = 'nefii view: error: ' + msg;
    document.getElementById('status').textContent = String(msg);
  }
  window.addEventListener('error', (e) => nefiiFail(e.message));
  window.addEventListener('unhandledrejection', (e) => nefiiFail(e.reason && e.reason.message || e.reason));
</script>
<script type="module">
import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { EXRLoader } from 'three/examples/jsm/loaders/EXRLoader.js';

const DEFAULT_EV = @EV@;
const opts = new URLSearchParams(location.hash.slice(1));

function blobUrl(id) {
  const bin = atob(document.getElementById(id).textContent.trim());
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return URL.createObjectURL(new Blob([bytes]));
}

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.toneMapping = THREE.ACESFilmicToneMapping;
document.body.appendChild(renderer.domElement);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(35, window.innerWidth / window.innerHeight, 0.001, 1000);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;

// the recovered light: equirectangular, nefii's (= Blender's) mapping, which three.js shares in Y-up
const env = await new EXRLoader().setDataType(THREE.HalfFloatType).loadAsync(blobUrl('env'));
env.mapping = THREE.EquirectangularReflectionMapping;
const pmrem = new THREE.PMREMGenerator(renderer);
scene.environment = pmrem.fromEquirectangular(env).texture;

const gltf = await new GLTFLoader().loadAsync(blobUrl('glb'));
const model = gltf.scene;
scene.add(model);

// three looks at the one glTF material: as glTF shades it, its base colour, its roughness (G)
const looks = new Map();
model.traverse((o) => {
  if (!o.isMesh) return;
  const std = o.material;
  looks.set(o, {
    shaded: std,
    albedo: new THREE.MeshBasicMaterial({ map: std.map, toneMapped: false }),
    roughness: new THREE.ShaderMaterial({
      uniforms: { map: { value: std.roughnessMap } },
      vertexShader: 'varying vec2 vUv; void main() { vUv = uv; ' +
                    'gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }',
      fragmentShader: 'uniform sampler2D map; varying vec2 vUv; ' +
                      'void main() { gl_FragColor = vec4(vec3(texture2D(map, vUv).g), 1.0); }',
      toneMapped: false,
    }),
  });
});

function setMode(mode) {
  for (const [mesh, m] of looks) mesh.material = m[mode] || m.shaded;
  document.querySelector(`input[name=mode][value=${mode}]`).checked = true;
}
function setBackground(on) {
  scene.background = on ? env : null;
  document.getElementById('background').checked = on;
}
function setExposure(ev) {
  renderer.toneMappingExposure = Math.pow(2, ev);
  document.getElementById('ev').value = ev - DEFAULT_EV;
  document.getElementById('evtext').textContent = (ev >= 0 ? '+' : '') + ev.toFixed(2) + ' EV';
}
for (const r of document.querySelectorAll('input[name=mode]')) r.addEventListener('change', () => setMode(r.value));
document.getElementById('background').addEventListener('change', (e) => setBackground(e.target.checked));
document.getElementById('ev').addEventListener('input', (e) => setExposure(DEFAULT_EV + Number(e.target.value)));
setMode(opts.get('mode') || 'shaded');
setBackground(opts.get('background') !== '0');
setExposure(opts.has('ev') ? Number(opts.get('ev')) : DEFAULT_EV);

// frame the object: from the front-right, a little above (three's +Y is nefii's +Z)
const sphere = new THREE.Box3().setFromObject(model).getBoundingSphere(new THREE.Sphere());
const dist = sphere.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.1;
camera.position.copy(sphere.center).add(new THREE.Vector3(1.0, 0.55, 1.0).normalize().multiplyScalar(dist));
camera.near = dist / 100; camera.far = dist * 100; camera.updateProjectionMatrix();
controls.target.copy(sphere.center);

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});
window.nefiiView = { THREE, renderer, scene, camera, controls, model, env, setMode, setBackground, setExposure };
let frames = 0;
renderer.setAnimationLoop(() => {
  controls.update();
  renderer.render(scene, camera);
  if (++frames === 2) document.title = 'nefii view: ready';
});
</script>
</body>
</html>
"""

// Drawing what the SceneStore holds with three.js, as client/render.py and client/compose.py
// draw it: flat, unlit faces whose colours carry the baked shading (no GPU lighting, no colour
// management, no tone mapping), two-sided, a 90-degree-style perspective with the headless
// client's near and far planes, the sky-blue background, and, in near-far streams, the far
// cubemap behind the geometry with its per-pixel range and the morph of the intermediate band
// done per vertex on the GPU.

import * as THREE from "three";
import { BACKGROUND, FAR, NEAR, lookRotation } from "./shading.js";

// Colours are sRGB bytes already shaded; three must pass them through untouched.
THREE.ColorManagement.enabled = false;

const GEOMETRY_VERTEX = `
in vec3 position;
in vec3 color;
uniform mat4 modelViewMatrix;
uniform mat4 projectionMatrix;
uniform bool uMorph;
uniform vec3 uU;
uniform vec3 uO;
uniform float uR1;
uniform float uR2;
flat out vec3 vColor;

// visibility/nearfar/partition.py morph(): near stays, far moves by U - O, the band between
// is seen from a blend of U and O.
vec3 morph(vec3 P) {
  float rho = length(P.xz - uO.xz);
  if (rho >= uR2) return P + (uU - uO);
  if (rho <= uR1) return P;
  float wo = (rho - uR1) / (uR2 - uR1);
  float wu = 1.0 - wo;
  vec3 vu = P - uU;
  vec3 vo = P - uO;
  float lu = length(vu);
  float lo = length(vo);
  vec3 du = lu > 0.0 ? vu / lu : vec3(0.0);
  vec3 d = wu * du + wo * vo / lo;
  float ld = length(d);
  if (ld <= 1e-12) return P;
  return uU + (wu * lu + wo * lo) * d / ld;
}

void main() {
  vColor = color;
  vec3 p = uMorph ? morph(position) : position;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(p, 1.0);
}`;

const GEOMETRY_FRAGMENT = `
precision highp float;
flat in vec3 vColor;
out vec4 fragColor;
void main() { fragColor = vec4(vColor, 1.0); }`;

const CUBE_VERTEX = `
in vec3 position;
void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }`;

// The far cubemap behind the geometry (client/compose.py): per pixel the world ray of its
// centre, the nearest texel as visibility.nearfar.cube_texels picks it, its colour, and its
// range as depth, so the geometry wins only where it is nearer (morph) or where nothing else
// is (conventional compositing).
const CUBE_FRAGMENT = `
precision highp float;
precision highp sampler2DArray;
uniform sampler2DArray uColors;
uniform sampler2DArray uRanges;
uniform int uRes;
uniform mat3 uCamToWorld;
uniform mat3 uFaceRot[6];
uniform vec2 uTan;
uniform vec2 uSize;
uniform float uNear;
uniform float uFar;
uniform bool uMorph;
out vec4 fragColor;
void main() {
  vec2 ndc = 2.0 * gl_FragCoord.xy / uSize - 1.0;
  vec3 ray = vec3(ndc.x * uTan.x, ndc.y * uTan.y, -1.0);
  vec3 dir = uCamToWorld * ray;
  vec3 a = abs(dir);
  int axis = (a.x >= a.y && a.x >= a.z) ? 0 : (a.y >= a.z ? 1 : 2);
  float major = a[axis];
  int face = 2 * axis + (dir[axis] < 0.0 ? 1 : 0);
  vec3 c = uFaceRot[face] * dir;
  float r = float(uRes);
  int col = int(clamp(floor((c.x / major + 1.0) * 0.5 * r), 0.0, r - 1.0));
  int row = int(clamp(floor((1.0 - c.y / major) * 0.5 * r), 0.0, r - 1.0));
  float range = texelFetch(uRanges, ivec3(col, row, face), 0).r;
  if (range <= 0.0) discard; // nothing far in this direction
  float depth = range / length(ray);
  float z = (uFar + uNear) / (uFar - uNear) - 2.0 * uFar * uNear / ((uFar - uNear) * depth);
  gl_FragDepth = uMorph ? clamp(0.5 * z + 0.5, 0.0, 1.0) : 1.0;
  fragColor = vec4(texelFetch(uColors, ivec3(col, row, face), 0).rgb, 1.0);
}`;

/** Row-major rotations (rows right, up, back) of the six cube faces, +X -X +Y -Y +Z -Z. */
function faceRotations() {
  const faces = [[[1, 0, 0], [0, 1, 0]], [[-1, 0, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 1]],
    [[0, -1, 0], [0, 0, -1]], [[0, 0, 1], [0, 1, 0]], [[0, 0, -1], [0, 1, 0]]];
  return faces.map(([f, u]) => {
    // look_rotation with an explicit up.
    const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
    const r = cross(f, u);
    const up = cross(r, f);
    return new THREE.Matrix3().set(...r, ...up, ...f.map((x) => -x));
  });
}

export class ViewRenderer {
  /** `canvas`; options: fov (vertical, degrees), antialias, width/height (fixed drawing size
   * in pixels, else the canvas' CSS size times the device pixel ratio). */
  constructor(canvas, { fov = 90, antialias = true, width = null, height = null } = {}) {
    this.canvas = canvas;
    this.fixed = width !== null && height !== null ? [width, height] : null;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias, powerPreference: "high-performance" });
    this.renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
    this.renderer.toneMapping = THREE.NoToneMapping;
    this.renderer.setPixelRatio(this.fixed ? 1 : window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(...BACKGROUND.map((c) => c / 255));
    this.camera = new THREE.PerspectiveCamera(fov, 1, NEAR, FAR);
    this.uniforms = {
      uMorph: { value: false }, uU: { value: new THREE.Vector3() }, uO: { value: new THREE.Vector3() },
      uR1: { value: 1 }, uR2: { value: 2 },
    };
    this.material = new THREE.RawShaderMaterial({
      glslVersion: THREE.GLSL3, vertexShader: GEOMETRY_VERTEX, fragmentShader: GEOMETRY_FRAGMENT,
      uniforms: this.uniforms, side: THREE.DoubleSide, depthFunc: THREE.LessDepth,
    });
    this.staticMesh = this.mesh();
    this.dynamicMesh = this.mesh();
    this.layout = -1;
    this.cube = null;
    this.cubeMesh = null;
    this.cubeFor = null;
    this.drawn = 0;
    this.resize();
  }

  mesh() {
    const m = new THREE.Mesh(new THREE.BufferGeometry(), this.material);
    m.frustumCulled = false;
    this.scene.add(m);
    return m;
  }

  /** Draw with near plane `near` (metres, > 0): the welcome's `near_plane`, the one the
   * server's answers assume; a farther one could show holes the PVS was not built for. */
  setNear(near) {
    if (!(Number.isFinite(near) && near > 0)) throw new Error(`near plane must be > 0 m, got ${near}`);
    this.camera.near = near;
    this.camera.updateProjectionMatrix();
    if (this.cubeMesh) this.cubeMesh.material.uniforms.uNear.value = near;
  }

  resize() {
    const [w, h] = this.fixed ?? [this.canvas.clientWidth || 1, this.canvas.clientHeight || 1];
    this.renderer.setSize(w, h, this.fixed !== null);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  /** Upload what changed in the store: the slots written since the last frame (the whole
   * arrays after they grew), and the moving triangles and spheres at scene time `t`. */
  sync(store, t) {
    const g = this.staticMesh.geometry;
    if (this.layout !== store.layout) {
      g.dispose();
      const fresh = new THREE.BufferGeometry();
      fresh.setAttribute("position", new THREE.BufferAttribute(store.positions, 3).setUsage(THREE.DynamicDrawUsage));
      fresh.setAttribute("color", new THREE.BufferAttribute(store.colors, 3, true).setUsage(THREE.DynamicDrawUsage));
      this.staticMesh.geometry = fresh;
      this.layout = store.layout;
      store.takeDirty();
    } else {
      const dirty = store.takeDirty();
      if (dirty.length) {
        for (const name of ["position", "color"]) {
          const a = g.getAttribute(name);
          a.clearUpdateRanges();
          for (const [s, e] of dirty) a.addUpdateRange(9 * s, 9 * (e - s));
          a.needsUpdate = true;
        }
      }
    }
    this.staticMesh.geometry.setDrawRange(0, 3 * store.used);
    // Triangles drawn: the held ones (moving ones included) and the spheres' faces.
    this.drawn = store.count + (this.drawnSpheres ?? 0);
    // Moving triangles and spheres are rebuilt when the store or (if anything has more than
    // one keyframe) the scene time changed.
    const animated = [store.keys, store.spheres].some((k) => k.times !== null && k.times.length > 1);
    const key = `${store.version}:${animated ? t : ""}`;
    if (key === this.dynamicKey) return;
    this.dynamicKey = key;
    const moving = store.keys.byId.size ? store.movingAt(t) : null;
    const spheres = store.sphereInfo.size ? store.spheresAt(t) : null;
    this.drawnSpheres = spheres ? spheres.positions.length / 9 : 0;
    this.drawn = store.count + this.drawnSpheres;
    const dyn = this.dynamicMesh.geometry;
    if (moving || spheres || dyn.getAttribute("position")) {
      const parts = [moving, spheres].filter(Boolean);
      const n = parts.reduce((s, p) => s + p.positions.length, 0);
      const pos = new Float32Array(n), col = new Uint8Array(n);
      let at = 0;
      for (const p of parts) { pos.set(p.positions, at); col.set(p.colors, at); at += p.positions.length; }
      dyn.dispose();
      const fresh = new THREE.BufferGeometry();
      fresh.setAttribute("position", new THREE.BufferAttribute(pos, 3));
      fresh.setAttribute("color", new THREE.BufferAttribute(col, 3, true));
      this.dynamicMesh.geometry = fresh;
    }
  }

  /** Use `cube` (decode.decodeCubemap) as the far field behind the geometry, with the
   * near-far morph on (`morph`) or conventional compositing; null: none. */
  setCubemap(cube, origin, morph = true) {
    if (cube === this.cubeFor && (cube === null || this.uniforms.uMorph.value === morph)) return;
    this.cubeFor = cube;
    if (this.cubeMesh) {
      this.scene.remove(this.cubeMesh);
      for (const k of ["uColors", "uRanges"]) this.cubeMesh.material.uniforms[k].value.dispose();
      this.cubeMesh.material.dispose();
      this.cubeMesh = null;
    }
    this.uniforms.uMorph.value = false;
    if (cube === null) return;
    const R = cube.resolution, n = 6 * R * R;
    const rgba = new Uint8Array(4 * n);
    for (let i = 0; i < n; i++) {
      rgba[4 * i] = cube.colors[3 * i];
      rgba[4 * i + 1] = cube.colors[3 * i + 1];
      rgba[4 * i + 2] = cube.colors[3 * i + 2];
      rgba[4 * i + 3] = 255;
    }
    // Empty texels (+inf) become 0, which the shader skips.
    const ranges = Float32Array.from(cube.ranges, (r) => (Number.isFinite(r) ? r : 0));
    const tex = (data, format, type) => {
      const t = new THREE.DataArrayTexture(data, R, R, 6);
      t.format = format;
      t.type = type;
      t.minFilter = t.magFilter = THREE.NearestFilter;
      t.generateMipmaps = false;
      t.needsUpdate = true;
      return t;
    };
    const quad = new THREE.BufferGeometry();
    quad.setAttribute("position", new THREE.BufferAttribute(new Float32Array([-1, -1, 0, 3, -1, 0, -1, 3, 0]), 3));
    const material = new THREE.RawShaderMaterial({
      glslVersion: THREE.GLSL3, vertexShader: CUBE_VERTEX, fragmentShader: CUBE_FRAGMENT,
      depthFunc: THREE.AlwaysDepth, depthWrite: true,
      uniforms: {
        uColors: { value: tex(rgba, THREE.RGBAFormat, THREE.UnsignedByteType) },
        uRanges: { value: tex(ranges, THREE.RedFormat, THREE.FloatType) },
        uRes: { value: R }, uCamToWorld: { value: new THREE.Matrix3() },
        uFaceRot: { value: faceRotations() }, uTan: { value: new THREE.Vector2() },
        uSize: { value: new THREE.Vector2() }, uNear: { value: this.camera.near }, uFar: { value: FAR },
        uMorph: { value: morph },
      },
    });
    this.cubeMesh = new THREE.Mesh(quad, material);
    this.cubeMesh.frustumCulled = false;
    this.cubeMesh.renderOrder = -1;
    this.scene.add(this.cubeMesh);
    const o = cube.center;
    this.uniforms.uO.value.set(o[0] - origin[0], o[1] - origin[1], o[2] - origin[2]);
    this.uniforms.uR1.value = cube.r1;
    this.uniforms.uR2.value = cube.r2;
    this.uniforms.uMorph.value = morph;
  }

  /** Draw from `eye` (metres from the store origin) looking along `forward`. */
  render(eye, forward) {
    const { right, up, back } = lookRotation(forward);
    const m = new THREE.Matrix4().makeBasis(new THREE.Vector3(...right), new THREE.Vector3(...up), new THREE.Vector3(...back));
    this.camera.quaternion.setFromRotationMatrix(m);
    this.camera.position.set(eye[0], eye[1], eye[2]);
    this.camera.updateMatrixWorld(true);
    this.uniforms.uU.value.set(eye[0], eye[1], eye[2]);
    if (this.cubeMesh) {
      const u = this.cubeMesh.material.uniforms;
      u.uCamToWorld.value.setFromMatrix4(m);
      const tanY = Math.tan((this.camera.fov * Math.PI) / 360);
      u.uTan.value.set(tanY * this.camera.aspect, tanY);
      this.renderer.getDrawingBufferSize(u.uSize.value);
    }
    this.renderer.render(this.scene, this.camera);
  }
}

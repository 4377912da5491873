/**
 * One 3D view: a canvas with its renderer, camera, orbit controls, one animated glTF model (one AnimationMixer
 * per model), a skeleton overlay, contact markers and penetration highlights. Frames are set from outside (the
 * shared timeline); the view never advances time by itself.
 */
import {
  AnimationMixer, Box3, BufferAttribute, Color, DirectionalLight, GridHelper, Group, HemisphereLight, LoopOnce,
  Mesh, MeshBasicMaterial, PerspectiveCamera, PlaneGeometry, PropertyBinding, Scene,
  SkeletonHelper, SphereGeometry, Vector3, WebGLRenderer, BufferGeometry, Line, LineBasicMaterial,
} from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const BASE_COLOR = new Color(1, 1, 1); // vertex colour multiplies the material's: white keeps it
const PEN_COLOR = new Color(0xe0302a);
const MARKER_GEOM = new SphereGeometry(1, 16, 12);

/** The clip's frame count and frame rate from its keyframe times (the writer samples every frame). */
export function clipTiming(clip) {
  let n = 0;
  for (const t of clip.tracks) n = Math.max(n, t.times.length);
  const fps = n > 1 && clip.duration > 0 ? (n - 1) / clip.duration : 30;
  return { frames: Math.max(1, n), fps };
}

export class ModelView {
  /**
   * @param {HTMLElement} container where the canvas goes (sized by CSS)
   * @param {{name: string}} opts name: "source", "before", "after" or "file"
   */
  constructor(container, { name }) {
    this.name = name;
    this.container = container;
    this.canvas = document.createElement('canvas');
    this.canvas.className = 'view-canvas';
    this.canvas.dataset.view = name;
    container.appendChild(this.canvas);
    this.renderer = new WebGLRenderer({ canvas: this.canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.scene = new Scene();
    this.scene.background = new Color(0x1d2127);
    this.camera = new PerspectiveCamera(35, 1, 0.02, 200);
    this.camera.position.set(0, 1.3, 4.5);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.target.set(0, 0.9, 0);
    this.controls.update();
    this.scene.add(new HemisphereLight(0xffffff, 0x445566, 1.6));
    const sun = new DirectionalLight(0xffffff, 2.2);
    sun.position.set(2, 4, 3);
    this.scene.add(sun);
    const fill = new DirectionalLight(0xaaccff, 0.8);
    fill.position.set(-3, 2, -2);
    this.scene.add(fill);
    this.grid = new GridHelper(20, 40, 0x59606b, 0x3a4048);
    this.scene.add(this.grid);
    const floor = new Mesh(new PlaneGeometry(40, 40), new MeshBasicMaterial({ color: 0x262b32 }));
    floor.rotation.x = -Math.PI / 2;
    floor.position.y = -0.002;
    this.scene.add(floor);
    this.markers = new Group();
    this.scene.add(this.markers);
    this.model = null;
    this.mixer = null;
    this.action = null;
    this.clip = null;
    this.skinned = [];
    this.skeletonHelper = null;
    this.frame = 0;
    this.fps = 30;
    this.dirty = true;
    this.renders = 0;
    this.highlighted = null;
    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(container);
    this.resize();
  }

  /** Follow the container's size. */
  resize() {
    const w = Math.max(1, this.container.clientWidth);
    const h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  /**
   * Show a loaded glTF ({scene, animations}); plays the clip `clipIndex` (default the first).
   * @returns {{frames: number, fps: number} | null} the clip's timing, null without animation
   */
  setModel(gltf, clipIndex = 0) {
    if (this.model) this.scene.remove(this.model);
    if (this.skeletonHelper) { this.scene.remove(this.skeletonHelper); this.skeletonHelper = null; }
    this.model = gltf.scene;
    this.scene.add(this.model);
    this.skinned = [];
    this.model.traverse((o) => {
      if (o.isSkinnedMesh) this.skinned.push(o);
      if (o.isMesh) o.frustumCulled = false; // skinned bounds follow the bind pose, not the animation
    });
    this.mixer = new AnimationMixer(this.model);
    this.setClip(gltf.animations, clipIndex);
    this.dirty = true;
    this.container.dataset.loaded = 'true';
    return this.clip ? clipTiming(this.clip) : null;
  }

  /** Play one of the model's clips (the single-file viewer lets the user choose). */
  setClip(animations, index) {
    if (this.action) this.action.stop();
    this.clip = animations && animations.length ? animations[Math.min(index, animations.length - 1)] : null;
    this.action = null;
    if (this.clip) {
      this.action = this.mixer.clipAction(this.clip);
      this.action.setLoop(LoopOnce, 1);
      this.action.clampWhenFinished = true;
      this.action.play();
      const t = clipTiming(this.clip);
      this.fps = t.fps;
      this.frames = t.frames;
    } else {
      this.frames = 1;
    }
    this.setFrame(0);
  }

  /** Pose the model at `frame` of its clip (clamped to the clip), exactly on the keyframe. */
  setFrame(frame) {
    const f = Math.max(0, Math.min(Math.round(frame), (this.frames || 1) - 1));
    if (this.action) {
      this.action.enabled = true;
      this.action.paused = false;
      this.action.time = Math.min(f / this.fps, this.clip.duration);
      this.mixer.update(0);
      this.frame = Math.round(this.action.time * this.fps);
    } else {
      this.frame = 0;
    }
    this.model?.updateMatrixWorld(true);
    this.container.dataset.frame = String(this.frame);
    this.dirty = true;
  }

  /** Show or hide the skeleton overlay. */
  setSkeleton(on) {
    if (on && !this.skeletonHelper && this.model) {
      this.skeletonHelper = new SkeletonHelper(this.model);
      this.skeletonHelper.material.depthTest = false;
      this.skeletonHelper.material.transparent = true;
      this.skeletonHelper.material.linewidth = 2;
      this.skeletonHelper.renderOrder = 10;
      this.scene.add(this.skeletonHelper);
    }
    if (this.skeletonHelper) this.skeletonHelper.visible = on;
    this.dirty = true;
  }

  /** The bone (or node) of a joint name, as GLTFLoader named it. */
  bone(name) {
    if (!this.model || !name) return null;
    return this.model.getObjectByName(name) || this.model.getObjectByName(PropertyBinding.sanitizeNodeName(name));
  }

  /** World position of vertex `index` of the (single) skinned mesh, posed at the current frame. */
  vertexPosition(index, target = new Vector3()) {
    const mesh = this.skinned[0];
    if (!mesh) return null;
    const pos = mesh.geometry.attributes.position;
    if (!Number.isInteger(index) || index < 0 || index >= pos.count) return null;
    mesh.getVertexPosition(index, target);
    return target.applyMatrix4(mesh.matrixWorld);
  }

  /** The model's height (bounding box of the rest pose) in metres, for marker sizes. */
  height() {
    if (!this.model) return 1.8;
    const box = new Box3().setFromObject(this.model);
    const h = box.max.y - box.min.y;
    return Number.isFinite(h) && h > 0.1 ? h : 1.8;
  }

  /**
   * Replace the markers: [{position: Vector3, color: number, size?: number}] and lines [{a, b, color}].
   */
  setMarkers(points, lines = []) {
    for (const c of [...this.markers.children]) {
      this.markers.remove(c);
      if (c.isLine) c.geometry.dispose();
    }
    const r = 0.024 * (this._height ??= this.height()) / 1.8;
    for (const p of points) {
      const m = new Mesh(MARKER_GEOM, new MeshBasicMaterial({ color: p.color, depthTest: false, transparent: true, opacity: 0.9 }));
      m.position.copy(p.position);
      m.scale.setScalar(r * (p.size ?? 1));
      m.renderOrder = 20;
      this.markers.add(m);
    }
    for (const l of lines) {
      const g = new BufferGeometry().setFromPoints([l.a, l.b]);
      const line = new Line(g, new LineBasicMaterial({ color: l.color, depthTest: false, transparent: true }));
      line.renderOrder = 19;
      this.markers.add(line);
    }
    this.dirty = true;
  }

  /** Tint the vertices in `vertices` (indices of the single skinned mesh) red; null clears. */
  highlight(vertices) {
    const mesh = this.skinned[0];
    if (!mesh) return;
    const geom = mesh.geometry;
    const n = geom.attributes.position.count;
    if (!geom.attributes.color) {
      if (!vertices || !vertices.length) return;
      const colors = new Float32Array(n * 3);
      for (let i = 0; i < n; i += 1) BASE_COLOR.toArray(colors, i * 3);
      geom.setAttribute('color', new BufferAttribute(colors, 3));
      const mats = Array.isArray(mesh.material) ? mesh.material : [mesh.material];
      for (const m of mats) { m.vertexColors = true; m.needsUpdate = true; }
    }
    const attr = geom.attributes.color;
    if (this.highlighted) for (const i of this.highlighted) BASE_COLOR.toArray(attr.array, i * 3);
    this.highlighted = [];
    for (const i of vertices || []) {
      if (Number.isInteger(i) && i >= 0 && i < n) { PEN_COLOR.toArray(attr.array, i * 3); this.highlighted.push(i); }
    }
    attr.needsUpdate = true;
    this.dirty = true;
  }

  /** World position of the skeleton's root bone (the hips for our files), or the model's origin. */
  rootPosition(target = new Vector3()) {
    const bone = this.skinned[0]?.skeleton.bones[0];
    return (bone || this.model)?.getWorldPosition(target) ?? target.set(0, 0, 0);
  }

  /**
   * Bounds of the skeleton and mesh over the clip (sampled frames): `world` in world space and `local` relative
   * to the root's ground position at each frame (to frame a camera that follows the root). Leaves frame 0.
   */
  motionBounds(samples = 12) {
    const world = new Box3();
    const local = new Box3();
    if (!this.model) return { world, local };
    const v = new Vector3();
    const root = new Vector3();
    const frames = this.frames || 1;
    for (let k = 0; k < samples; k += 1) {
      this.setFrame(Math.round((k * (frames - 1)) / Math.max(1, samples - 1)));
      this.rootPosition(root);
      root.y = 0;
      this.model.traverse((o) => {
        if (!o.isBone) return;
        o.getWorldPosition(v);
        world.expandByPoint(v);
        local.expandByPoint(v.sub(root));
      });
    }
    this.setFrame(0);
    if (world.isEmpty()) { // no skeleton: the meshes' bounds
      world.setFromObject(this.model);
      local.copy(world);
      return { world, local };
    }
    // Bones are inside the skin: pad by a little for the flesh (more where the body is wide).
    const pad = Math.max(0.08, 0.06 * (world.max.y - world.min.y));
    world.expandByScalar(pad);
    local.expandByScalar(pad);
    world.min.y = Math.min(world.min.y, 0);
    local.min.y = Math.min(local.min.y, 0);
    return { world, local };
  }

  /** Keep the camera's offset from the root while the root moves (call after setFrame). */
  follow(on) {
    if (!on || !this.model) { this.followOffset = null; return; }
    const root = this.rootPosition(new Vector3());
    root.y = 0;
    if (!this.followOffset) { this.followOffset = this.controls.target.clone().sub(root); return; }
    const want = root.add(this.followOffset);
    const delta = want.sub(this.controls.target);
    if (delta.lengthSq() < 1e-12) return;
    this.controls.target.add(delta);
    this.camera.position.add(delta);
    this.dirty = true;
  }

  /**
   * Aim the camera at `object` (a bone) from `distance` metres, keeping the current viewing direction, so a joint
   * such as a hand fills the view (call after setFrame to stay on it while it moves). Returns the bone's position.
   */
  focusOn(object, distance) {
    const at = object.getWorldPosition(new Vector3());
    const dir = this.camera.position.clone().sub(this.controls.target);
    if (dir.lengthSq() < 1e-12) dir.set(0, 0.2, 1);
    dir.setLength(distance);
    this.controls.target.copy(at);
    this.camera.position.copy(at).add(dir);
    this.camera.near = Math.max(0.005, distance / 50);
    this.camera.far = Math.max(50, distance * 100);
    this.camera.updateProjectionMatrix();
    this.dirty = true;
    return at;
  }

  /** After the user panned: the root-relative target becomes the new reference. */
  resetFollow() {
    if (this.followOffset) this.followOffset = null;
  }

  /** Aim the camera at a box (from the front, slightly above). */
  frameBox(box) {
    if (box.isEmpty()) return;
    const center = box.getCenter(new Vector3());
    const radius = Math.max(0.5, box.getSize(new Vector3()).length() / 2) * 0.92;
    const fov = (this.camera.fov * Math.PI) / 180;
    const fit = Math.min(fov, 2 * Math.atan(Math.tan(fov / 2) * this.camera.aspect));
    const dist = radius / Math.sin(fit / 2);
    const dir = new Vector3(0.38, 0.22, 0.9).normalize();
    this.controls.target.copy(center);
    this.camera.position.copy(center).addScaledVector(dir, dist);
    this.camera.near = Math.max(0.01, dist / 100);
    this.camera.far = dist * 10 + 50;
    this.camera.updateProjectionMatrix();
    this.controls.update();
    this.dirty = true;
  }

  /**
   * Copy another view's camera (linked cameras). With `relative`, only its direction and distance from its
   * target: each view keeps its own target (when the cameras follow each character's root).
   */
  copyCamera(other, relative = false) {
    if (relative) {
      this.camera.position.copy(this.controls.target).add(other.camera.position.clone().sub(other.controls.target));
    } else {
      this.camera.position.copy(other.camera.position);
      this.controls.target.copy(other.controls.target);
    }
    this.camera.quaternion.copy(other.camera.quaternion);
    this.camera.near = other.camera.near;
    this.camera.far = other.camera.far;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  /** Draw if anything changed since the last draw. */
  render(force = false) {
    if (!this.dirty && !force) return false;
    this.renderer.render(this.scene, this.camera);
    this.dirty = false;
    this.renders += 1;
    this.container.dataset.renders = String(this.renders);
    return true;
  }

  dispose() {
    this.resizeObserver.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
    this.renderer.forceContextLoss?.();
    this.canvas.remove();
  }
}

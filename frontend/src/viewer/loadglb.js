/** glTF/GLB bytes to a three.js scene with its clips (GLTFLoader), and clones for identical files (SkeletonUtils). */
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import * as SkeletonUtils from 'three/addons/utils/SkeletonUtils.js';

/** Parse GLB or embedded glTF bytes. External resources are refused (as the service refuses them). */
export function parseGltf(buffer) {
  const loader = new GLTFLoader();
  loader.manager.setURLModifier((url) => {
    if (url.startsWith('data:') || url.startsWith('blob:')) return url;
    throw new Error(`external resource ${url} is not loaded: embed it (GLB or data URI)`);
  });
  return new Promise((resolve, reject) => {
    loader.parse(buffer, '', resolve, (e) => reject(e instanceof Error ? e : new Error(String(e?.message ?? e))));
  });
}

/**
 * A second, independent copy of a loaded glTF: skinned meshes re-bound to the copied bones, and geometry and
 * materials copied too (a view paints its own vertex colours). Clips are shared (they are read-only).
 */
export function cloneGltf(gltf) {
  const scene = SkeletonUtils.clone(gltf.scene);
  scene.traverse((o) => {
    if (!o.isMesh) return;
    o.geometry = o.geometry.clone();
    o.material = Array.isArray(o.material) ? o.material.map((m) => m.clone()) : o.material.clone();
  });
  return { scene, animations: gltf.animations };
}

/** True when two ArrayBuffers hold the same bytes. */
export function sameBytes(a, b) {
  if (!a || !b || a.byteLength !== b.byteLength) return false;
  const x = new Uint32Array(a, 0, a.byteLength >> 2);
  const y = new Uint32Array(b, 0, b.byteLength >> 2);
  for (let i = 0; i < x.length; i += 1) if (x[i] !== y[i]) return false;
  const xa = new Uint8Array(a);
  const ya = new Uint8Array(b);
  for (let i = x.length * 4; i < xa.length; i += 1) if (xa[i] !== ya[i]) return false;
  return true;
}
